"""Test matrices: a YAML file of brains x circuits x variations x perturbations x repetitions, expanded into the
planned episodes of a matrix run. Pure: no bus, no processes; every mistake is found here, before anything starts.

A matrix file::

    name: generalization                      # default: the file's stem
    brains: [explicit, {name: memdccp, weights: runs/train/memdccp.ckpt, label: memdccp-v1, options: {threads: 1}}]
    circuits: [simple, montmelo, montreal]    # built-in, user, random:SEED or twisty:SEED circuits
    variations: {line: [red, white, none], road: [grey, white], walls: [on, off]}   # default: one "default" world
    # or, instead of the product, the worlds one by one:
    #   worlds: [{line: red}, {line: none, walls: off}, {line: red, direction: reverse}]
    perturbations: [none, {salt_pepper: 0.2}, {camera: left}, "gaussian=10"]         # default: [none]
    repetitions: 3                            # default 1; episode seed = seed + repetition
    limits: {laps: 1, max_sim_seconds: 300, brain_timeout_s: 10}                      # also step_s
    camera: 320x240                           # or {width_px: 320, height_px: 240, hfov_rad: ...}
    seed: 7                                   # default 0
    realtime: false                           # default false (lock-step)
    renderer: pybullet                        # pybullet, gl or auto (default: auto; --renderer overrides)
    shadows: [{name: constant, options: {speed_mps: 2}}]   # brains that see the same frames but never drive
    exclude: [{brain: explicit, line: none}]  # drop every combination matching ALL the given keys
    include: [{brain: explicit, circuit: monaco}]          # extra combinations, expanded over repetitions

Parts: a matrix may be several experiments over the same brains (the paper's tables), each its own product::

    parts:
      montmelo: {circuits: [montmelo], repetitions: 3}
      noise: {circuits: [montreal], perturbations: [{salt_pepper: 0.2}, {salt_pepper: 0.4}]}

A part sets any of circuits, variations or worlds, perturbations, repetitions, limits, exclude and include; what it
does not set comes from the top level. Its episodes' keys start with ``<part>:``, and parts expand in written order.

Expansion order: brains, then circuits, then the variation values (product, keys in written order), then
perturbations, then repetitions (innermost). ``exclude`` applies to that product only; ``include`` entries come
after it, in written order, each over every repetition, and are never excluded (as in GitHub Actions matrices).
Wherever a list is expected, a single item stands for a one-item list.

Labels (as stored in results and used in episode keys):
    variation    ``"line=white,road=grey,walls=off"`` (keys in written order, booleans as on/off; ``"default"``
                 when no variation applies)
    perturbation ``"none"``, or its items joined by ``+``: ``"salt_pepper=0.2+camera=left"``,
                 ``"occlusion:patches=2,size_fraction=0.3"`` for a model given a mapping of parameters
    episode key  ``"<brain label>/<circuit>/<variation label>/<perturbation label>/r<repetition>"``, in a part
                 ``"<part>:<brain label>/..."`` (stable across re-parses of the same text: what ``--resume`` compares)

Every mistake raises :class:`MatrixError`, one line: ``FILE:LINE: what is wrong (what is allowed)``.
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import math
import re
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgspec
import yaml
from yaml.constructor import SafeConstructor

from brains.registry import UnknownBrainError, bus_name, is_brain_file, require_brain
from circuits import circuit_names
from circuits.library import GENERATED_NAMES, is_circuit_name
from protocol.keys import check_name
from protocol.messages import NOISE_MODELS, CameraSpec, EpisodeSpec, NoiseStage

# The protocol's own lists of world and camera variation keys (it has no public name for them).
from protocol.variations import (
    CAMERA_KEYS,
    ROUTE_KEYS,
    WORLD_KEYS,
    VariationError,
    apply_variation,
    noise_stage,
    parse_pairs,
)
from services.simulator.renderers import default_renderer

TOP_LEVEL_KEYS = ("name", "brains", "circuits", "variations", "worlds", "perturbations", "repetitions", "limits",
                  "camera", "seed", "realtime", "renderer", "shadows", "exclude", "include", "parts")
# What a part may set for itself; everything else (brains, shadows, camera, seed, realtime) is the matrix's.
PART_KEYS = ("circuits", "variations", "worlds", "perturbations", "repetitions", "limits", "exclude", "include")
BRAIN_KEYS = ("name", "weights", "label", "options")
LIMIT_KEYS = ("laps", "max_sim_seconds", "brain_timeout_s", "step_s")
VARIATION_KEYS = (*WORLD_KEYS, *CAMERA_KEYS, *ROUTE_KEYS)
CAMERA_PERTURBATION_KEYS = CAMERA_KEYS
NOISE_MODEL_NAMES = tuple(model.__struct_config__.tag for model in NOISE_MODELS)
CAMERA_FIELDS = tuple(field.name for field in msgspec.structs.fields(CameraSpec))
MAX_EPISODES = 100_000  # a typo in repetitions should fail here, not exhaust memory
DEFAULT_VARIATION = "default"
MATRIX_RENDERER = "auto"  # without `renderer:` or $DRIVEBENCH_RENDERER: gl where EGL works (parity: README)
NO_PERTURBATION = "none"

_OPTION_KEY = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
# An item of a perturbation string: "model", "model=value", "model:key=value,..." or "camera_key=value".
_STRING_ITEM = re.compile(r"\s*([A-Za-z_][A-Za-z0-9_]*)\s*(?:([=:])(.*))?", re.S)
# "+" joins items; one followed by a digit or sign belongs to a number ("1e+5", "brightness=+0.2").
_ITEM_JOIN = re.compile(r"\+(?=\s*[A-Za-z_])")
_CAMERA_SIZE = re.compile(r"\s*(\d+)\s*[xX]\s*(\d+)\s*")


class MatrixError(ValueError):
    """A mistake in a matrix file. ``str(error)`` is one line: ``FILE:LINE: what is wrong (what is allowed)``
    (``FILE: ...`` when the file itself cannot be read). ``source``, ``line`` (1-based, or None) and ``message``
    are kept as attributes."""

    def __init__(self, message: str, *, source: str, line: int | None) -> None:
        self.message = re.sub(r"\s*\n\s*", " ", message).strip()
        self.source = source
        self.line = line
        where = source if line is None else f"{source}:{line}"
        super().__init__(f"{where}: {self.message}")


@dataclass(frozen=True)
class BrainEntry:
    """One brain of a matrix (or a shadow brain).

    label: unique name of the entry within the matrix; it is also the brain process's bus name and the episode's
        ``active_brain``, so letters, digits, ``_ . -`` only. Default: the brain's bus name
        (``brains.registry.bus_name``), or ``<that>-<weights stem>``.
    brain: a brain name as ``brains.registry.resolve`` takes it: built-in, installed (entry point),
        ``package.module:Class``, or a Behavior Metrics brain file (absolute once read).
    weights: absolute path of the checkpoint (resolved from the matrix file's folder), or None.
    options: the brain's constructor options, in written order, as (key, JSON-able value) pairs.
    """

    label: str
    brain: str
    weights: Path | None = None
    options: tuple[tuple[str, Any], ...] = ()

    def launch_options(self) -> tuple[str, ...]:
        """Constructor options as ``key=<JSON value>`` overrides for the brain host (``--set options.KEY=VALUE``),
        weights last as ``weights="<absolute path>"``. Every value reads back as the same value with YAML."""
        texts = tuple(f"{key}={_yaml_json(value)}" for key, value in self.options)
        if self.weights is not None:
            texts += (f"weights={json.dumps(str(self.weights))}",)
        return texts

    def to_dict(self) -> dict[str, Any]:
        """JSON-able form: ``{"label", "brain", "weights" (absolute path or None), "options" (mapping)}``."""
        return {"label": self.label, "brain": self.brain,
                "weights": None if self.weights is None else str(self.weights), "options": dict(self.options)}


@dataclass(frozen=True)
class PlannedEpisode:
    """One episode of a matrix, as planned before anything runs.

    key: stable id, ``"<brain label>/<circuit>/<variation>/<perturbation>/r<repetition>"``.
    index: position in the matrix's expansion, from 0.
    variation / perturbation: labels (see the module docstring).
    spec: the full episode spec: limits, camera, ``seed = matrix seed + repetition``, world variation and camera
        perturbations applied, noise stages in written order, ``active_brain = brain.label``.
    """

    key: str
    index: int
    brain: BrainEntry
    circuit: str
    variation: str
    perturbation: str
    repetition: int
    spec: EpisodeSpec
    part: str = ""


def part_of(key: str) -> str:
    """The part of an episode key (``"noise:explicit/montreal/..."`` -> ``"noise"``), ``""`` outside parts. Brain
    labels have no ``:``, so a ``:`` before the first ``/`` can only end a part's name."""
    head = key.split("/", 1)[0]
    return head.split(":", 1)[0] if ":" in head else ""


@dataclass(frozen=True)
class Matrix:
    """A parsed and expanded matrix file.

    name: the matrix's name (default: the file's stem). source: where it was read from. text: the file's text.
    brains: the driving brains, in written order. shadows: brains that get the same frames but never drive.
    episodes: every planned episode, in expansion order. variation_keys: the variation axes, in written order.
    parts: the part names in written order (empty for a matrix without parts).
    """

    name: str
    source: str
    text: str
    brains: tuple[BrainEntry, ...]
    shadows: tuple[BrainEntry, ...]
    episodes: tuple[PlannedEpisode, ...]
    variation_keys: tuple[str, ...]
    parts: tuple[str, ...] = ()


def load_matrix(path: Path) -> Matrix:
    """Read and expand the matrix file ``path``; weights are resolved from its folder.

    Raises :class:`MatrixError` for a missing or unreadable file and for every mistake in it."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise MatrixError("the matrix file is not UTF-8 text", source=str(path), line=None) from None
    except OSError as error:
        reason = error.strerror or str(error)
        raise MatrixError(f"cannot read the matrix file ({reason})", source=str(path), line=None) from None
    return parse_matrix(text, source=str(path), base_dir=path.parent)


def parse_matrix(text: str, *, source: str = "<matrix>", base_dir: Path = Path(".")) -> Matrix:
    """Expand the matrix in ``text``. ``source`` names it in errors (and gives the default name: its stem);
    relative weights paths are resolved from ``base_dir``. Raises :class:`MatrixError` for every mistake."""
    reader = _Reader(source)
    root = reader.compose(text)
    top = reader.mapping(root, what="the matrix", allowed=TOP_LEVEL_KEYS)
    if "brains" not in top:
        raise reader.error(root, "missing 'brains' (a matrix needs brains and circuits)")
    _check_one_world_form(reader, top)
    parts = _parts(reader, root, top)
    episodes: list[PlannedEpisode] = []
    variation_keys: dict[str, None] = {}
    for part, entries in parts:
        plan = _Plan.read(reader, entries, base_dir=Path(base_dir), part=part)
        episodes += plan.expand(reader, entries, first_index=len(episodes))
        variation_keys.update(dict.fromkeys(axis.key for axis in plan.axes))
    if len(episodes) > MAX_EPISODES:
        raise reader.error(top["parts"][0], f"the matrix expands to {len(episodes)} episodes (at most {MAX_EPISODES})")
    return Matrix(name=_name(reader, top, source), source=source, text=text, brains=plan.brains,
                  shadows=plan.shadows, episodes=tuple(episodes), variation_keys=tuple(variation_keys),
                  parts=tuple(part for part, _ in parts if part))


def _check_one_world_form(reader: _Reader, entries: dict[str, tuple[yaml.Node, yaml.Node]]) -> None:
    if "variations" in entries and "worlds" in entries:
        raise reader.error(entries["worlds"][0], "give variations (a product) or worlds (a list), not both")


def _parts(reader: _Reader, root: yaml.Node,
           top: dict[str, tuple[yaml.Node, yaml.Node]]) -> list[tuple[str, dict[str, tuple[yaml.Node, yaml.Node]]]]:
    """(part name, the keys it expands with) of each part; one nameless part for a matrix without ``parts``."""
    if "parts" not in top:
        if "circuits" not in top:
            raise reader.error(root, "missing 'circuits' (a matrix needs brains and circuits)")
        return [("", top)]
    shared = {key: entry for key, entry in top.items() if key != "parts"}
    parts = []
    for name, (name_node, part_node) in reader.mapping(top["parts"][1], what="parts").items():
        try:
            check_name(name, what="part name")
        except ValueError as error:
            raise reader.error(name_node, str(error)) from None
        entries = reader.mapping(part_node, what=f"part {name!r}", allowed=PART_KEYS)
        _check_one_world_form(reader, entries)
        merged = dict(shared)
        if "variations" in entries or "worlds" in entries:  # a part's worlds replace the top level's, either form
            merged.pop("variations", None)
            merged.pop("worlds", None)
        merged.update(entries)
        if "circuits" not in merged:
            raise reader.error(name_node, f"part {name!r} has no circuits (give them in the part or at the top level)")
        parts.append((name, merged))
    if not parts:
        raise reader.error(top["parts"][1], "parts is empty (give at least one part, or leave parts out)")
    return parts


# -- reading YAML nodes with their line numbers ------------------------------------------------------------------


def _line(node: yaml.Node) -> int:
    return node.start_mark.line + 1


class _Reader:
    """Turns YAML nodes into values, raising :class:`MatrixError` at the node's line."""

    def __init__(self, source: str) -> None:
        self.source = source

    def error(self, node: yaml.Node | None, message: str) -> MatrixError:
        return MatrixError(message, source=self.source, line=1 if node is None else _line(node))

    def compose(self, text: str) -> yaml.Node:
        try:
            root = yaml.compose(text, Loader=yaml.SafeLoader)
        except yaml.MarkedYAMLError as error:
            mark = error.problem_mark or error.context_mark
            line = 1 if mark is None else mark.line + 1
            raise MatrixError(f"invalid YAML: {error.problem or error.context}", source=self.source,
                              line=line) from None
        except yaml.YAMLError as error:  # a character YAML does not allow: a position, no mark
            position = getattr(error, "position", None)
            line = 1 if position is None else text.count("\n", 0, position) + 1
            raise MatrixError(f"invalid YAML: {error}", source=self.source, line=line) from None
        if not isinstance(root, yaml.MappingNode):
            raise MatrixError("the top level must be a mapping (keys: " + ", ".join(TOP_LEVEL_KEYS) + ")",
                              source=self.source, line=1 if root is None else _line(root))
        self._check_duplicates(root, seen=set())
        return root

    def _check_duplicates(self, node: yaml.Node, *, seen: set[int]) -> None:
        if id(node) in seen:  # aliases may make cycles
            return
        seen.add(id(node))
        if isinstance(node, yaml.MappingNode):
            first: dict[Any, int] = {}
            for key_node, value_node in node.value:
                key = key_node.value if isinstance(key_node, yaml.ScalarNode) else id(key_node)
                if key in first:
                    raise self.error(key_node, f"duplicate key {key!r} (first on line {first[key]})")
                first[key] = _line(key_node)
                self._check_duplicates(value_node, seen=seen)
        elif isinstance(node, yaml.SequenceNode):
            for item in node.value:
                self._check_duplicates(item, seen=seen)

    def mapping(self, node: yaml.Node, *, what: str,
                allowed: Iterable[str] | None = None) -> dict[str, tuple[yaml.Node, yaml.Node]]:
        """key -> (key node, value node), in written order; keys must be text (and within ``allowed``)."""
        if not isinstance(node, yaml.MappingNode):
            raise self.error(node, f"{what} must be a mapping, got {_describe(node)}")
        allowed = None if allowed is None else tuple(allowed)
        entries = {}
        for key_node, value_node in node.value:
            key = self.value(key_node)
            if not isinstance(key, str):
                raise self.error(key_node, f"keys of {what} must be text, got {key!r}")
            if allowed is not None and key not in allowed:
                raise self.error(key_node, f"unknown key {key!r} in {what} (allowed: {', '.join(allowed)})")
            entries[key] = (key_node, value_node)
        return entries

    def items(self, node: yaml.Node, *, what: str) -> list[yaml.Node]:
        """The items of a non-empty list; any other node stands for a one-item list."""
        if isinstance(node, yaml.SequenceNode):
            if not node.value:
                raise self.error(node, f"{what} is an empty list (give at least one)")
            return list(node.value)
        if isinstance(node, yaml.ScalarNode) and self.value(node) is None:
            raise self.error(node, f"{what} is empty (give at least one)")
        return [node]

    def value(self, node: yaml.Node) -> Any:
        """The plain Python value of a node (YAML 1.1 rules: ``on``/``off`` are booleans)."""
        try:
            return SafeConstructor().construct_object(node, deep=True)
        except yaml.YAMLError as error:  # a tag the safe loader does not know (!!python/object, !custom)
            problem = getattr(error, "problem", None) or error
            raise self.error(node, f"cannot read this value: {problem}") from None

    def scalar(self, node: yaml.Node, *, what: str) -> Any:
        if not isinstance(node, yaml.ScalarNode):
            raise self.error(node, f"{what} must be a single value, got {_describe(node)}")
        return self.value(node)

    def text(self, node: yaml.Node, *, what: str) -> str:
        value = self.scalar(node, what=what)
        if not isinstance(value, str) or not value.strip():
            raise self.error(node, f"{what} must be text, got {value!r}")
        return value.strip()

    def integer(self, node: yaml.Node, *, what: str, minimum: int) -> int:
        value = self.scalar(node, what=what)
        if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
            raise self.error(node, f"{what} must be an integer >= {minimum}, got {value!r}")
        return value

    def yaml_text(self, node: yaml.Node, text: str) -> Any:
        """A value written inside a string (``"gaussian=10"``), read as YAML like the command line does."""
        try:
            return yaml.safe_load(text)
        except yaml.YAMLError:
            raise self.error(node, f"cannot read the value {text.strip()!r}") from None


def _describe(node: yaml.Node) -> str:
    if node.tag == "tag:yaml.org,2002:null":
        return "nothing"
    if isinstance(node, yaml.MappingNode):
        return "a mapping"
    if isinstance(node, yaml.SequenceNode):
        return "a list"
    return repr(node.value)


def _text(value: Any) -> str:
    """A value as it appears in labels: booleans as on/off, floats in their shortest exact form."""
    if isinstance(value, bool):
        return "on" if value else "off"
    if isinstance(value, float):
        return repr(value)
    if value is None:
        return "none"
    return str(value)


def _name(reader: _Reader, top: dict[str, tuple[yaml.Node, yaml.Node]], source: str) -> str:
    if "name" in top:
        return reader.text(top["name"][1], what="name")
    return "matrix" if source.startswith("<") else Path(source).stem


# -- brains ------------------------------------------------------------------------------------------------------


def _brain_entries(reader: _Reader, node: yaml.Node, *, what: str,
                   base_dir: Path) -> list[tuple[BrainEntry, yaml.Node]]:
    return [(_brain_entry(reader, item, what=what, base_dir=base_dir), item)
            for item in reader.items(node, what=what)]


def _brain_entry(reader: _Reader, node: yaml.Node, *, what: str, base_dir: Path) -> BrainEntry:
    if isinstance(node, yaml.MappingNode):
        fields = reader.mapping(node, what=f"a {what} entry", allowed=BRAIN_KEYS)
    else:
        fields = {"name": (node, node)}
    if "name" not in fields:
        raise reader.error(node, f"a {what} entry needs a name (keys: {', '.join(BRAIN_KEYS)})")
    name_node = fields["name"][1]
    name = reader.text(name_node, what="a brain name")
    if is_brain_file(name):  # a Behavior Metrics brain file, next to the matrix file unless absolute
        name = str((base_dir / Path(name).expanduser()).resolve())
    try:
        require_brain(name)
    except UnknownBrainError as error:
        raise reader.error(name_node, str(error)) from None
    weights = _weights(reader, fields["weights"][1], base_dir=base_dir) if "weights" in fields else None
    options = _options(reader, fields["options"][1]) if "options" in fields else ()
    label = _label(reader, fields.get("label", (node, None))[1], name=name, weights=weights, entry=node)
    return BrainEntry(label=label, brain=name, weights=weights, options=options)


def _weights(reader: _Reader, node: yaml.Node, *, base_dir: Path) -> Path:
    written = reader.text(node, what="weights")
    path = base_dir / written
    try:
        path = Path(written).expanduser()
        path = (path if path.is_absolute() else base_dir / path).resolve()
        found = path.exists()
    except (OSError, ValueError, RuntimeError):  # a NUL byte, an unknown ~user, a symlink loop
        found = False
    if not found:
        raise reader.error(node, f"weights file {written!r} not found (looked for {path}; relative paths start "
                                 f"at the matrix file's folder)")
    return path


def _options(reader: _Reader, node: yaml.Node) -> tuple[tuple[str, Any], ...]:
    options = []
    for key, (key_node, value_node) in reader.mapping(node, what="options").items():
        if key == "weights":
            raise reader.error(key_node, "give weights as the entry's own `weights`, not as an option")
        if not _OPTION_KEY.fullmatch(key):
            raise reader.error(key_node, f"option name {key!r} must be an identifier (letters, digits, '_')")
        value = reader.value(value_node)
        try:
            json.dumps(value, allow_nan=False)
        except (TypeError, ValueError):
            raise reader.error(value_node, f"option {key!r} must be a JSON value (text, number, boolean, list, "
                                           f"mapping), got {value!r}") from None
        options.append((key, value))
    return tuple(options)


def _label(reader: _Reader, node: yaml.Node | None, *, name: str, weights: Path | None, entry: yaml.Node) -> str:
    if node is not None:
        label = reader.text(node, what="label")
        where = node
    else:
        # "-" and not "@": the label is the brain's bus name, and key chunks allow letters, digits, _ . - only.
        label = bus_name(name) if weights is None else f"{bus_name(name)}-{weights.stem}"
        where = entry
    try:
        return check_name(label, what="brain label")
    except ValueError as error:
        hint = "" if node is not None else "; give the entry a `label`"
        raise reader.error(where, f"{error} (it is the brain's bus name{hint})") from None


def _check_unique_labels(reader: _Reader, entries: list[tuple[BrainEntry, yaml.Node]]) -> None:
    first: dict[str, int] = {}
    for entry, node in entries:
        if entry.label in first:
            raise reader.error(node, f"duplicate brain label {entry.label!r} (also on line {first[entry.label]}; "
                                     f"labels of brains and shadows must differ: give one a `label`)")
        first[entry.label] = _line(node)


# -- circuits, settings ------------------------------------------------------------------------------------------


def _circuit(reader: _Reader, node: yaml.Node) -> str:
    name = reader.text(node, what="a circuit")
    if not is_circuit_name(name):
        raise reader.error(node, f"unknown circuit {name!r} (known: {', '.join(circuit_names())}, "
                                 f"or {GENERATED_NAMES}; see `drivebench circuits list`)")
    return name


def _circuits(reader: _Reader, node: yaml.Node) -> list[str]:
    circuits: dict[str, int] = {}
    for item in reader.items(node, what="circuits"):
        name = _circuit(reader, item)
        if name in circuits:
            raise reader.error(item, f"circuit {name!r} is listed twice (also on line {circuits[name]})")
        circuits[name] = _line(item)
    return list(circuits)


def _spec_error(error: msgspec.ValidationError) -> str:
    return re.sub(r" - at `\$[^`]*`$", "", str(error))


def _base_spec(reader: _Reader, top: dict[str, tuple[yaml.Node, yaml.Node]]) -> EpisodeSpec:
    """The spec every episode starts from: limits, camera and realtime (circuit, seed, brain set per episode)."""
    fields: dict[str, Any] = {}
    if "limits" in top:
        for key, (_, value_node) in reader.mapping(top["limits"][1], what="limits", allowed=LIMIT_KEYS).items():
            fields[key] = _spec_field(reader, value_node, key=key, what=f"limits.{key}")
    if "realtime" in top:
        fields["realtime"] = _spec_field(reader, top["realtime"][1], key="realtime", what="realtime")
    if "renderer" in top:
        fields["renderer"] = _spec_field(reader, top["renderer"][1], key="renderer", what="renderer")
    else:
        try:
            fields["renderer"] = default_renderer(MATRIX_RENDERER)
        except ValueError as error:
            raise MatrixError(str(error), source=reader.source, line=None) from None
    if "camera" in top:
        fields["camera"] = _camera(reader, top["camera"][1])
    try:
        return msgspec.convert(fields, EpisodeSpec)
    except msgspec.ValidationError as error:
        raise reader.error(top.get("limits", (None, None))[1], f"limits: {_spec_error(error)}") from None


def with_renderer(matrix: Matrix, choose: Callable[[str], str]) -> Matrix:
    """``matrix`` with each episode's renderer replaced by ``choose(renderer)`` (the command line's choice, or
    "auto" resolved where the stacks run)."""
    episodes = tuple(dataclasses.replace(episode, spec=msgspec.structs.replace(
        episode.spec, renderer=choose(episode.spec.renderer))) for episode in matrix.episodes)
    return dataclasses.replace(matrix, episodes=episodes)


def _spec_field(reader: _Reader, node: yaml.Node, *, key: str, what: str) -> Any:
    value = reader.scalar(node, what=what)
    try:
        msgspec.convert({key: value}, EpisodeSpec)
    except msgspec.ValidationError as error:
        raise reader.error(node, f"bad {what} {value!r}: {_spec_error(error)}") from None
    return value


def _camera(reader: _Reader, node: yaml.Node) -> CameraSpec:
    if isinstance(node, yaml.ScalarNode):
        match = _CAMERA_SIZE.fullmatch(str(reader.value(node)))
        if not match:
            raise reader.error(node, f"camera must look like 320x240 or {{width_px: 320, height_px: 240}}, "
                                     f"got {node.value!r}")
        fields: dict[str, Any] = {"width_px": int(match[1]), "height_px": int(match[2])}
    else:
        fields = {}
        for key, (_, value_node) in reader.mapping(node, what="camera", allowed=CAMERA_FIELDS).items():
            fields[key] = reader.scalar(value_node, what=f"camera.{key}")
            _convert_camera(reader, value_node, {key: fields[key]}, what=f"camera.{key} {fields[key]!r}")
    return _convert_camera(reader, node, fields, what="camera")


def _convert_camera(reader: _Reader, node: yaml.Node, fields: dict[str, Any], *, what: str) -> CameraSpec:
    try:
        return msgspec.convert(fields, CameraSpec)
    except msgspec.ValidationError as error:
        raise reader.error(node, f"bad {what}: {_spec_error(error)}") from None


# -- variations ----------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Axis:
    """One variation key and its values: (label text, value as apply_variation takes it, line)."""

    key: str
    values: tuple[tuple[str, Any, int], ...]


@dataclass(frozen=True)
class _World:
    """One world variation: its label, the items to apply, and the label text of each key (for exclude)."""

    label: str
    items: tuple[tuple[str, Any], ...] = ()

    @property
    def texts(self) -> dict[str, str]:
        return {key: _text(value) for key, value in self.items}


def _variation_value(reader: _Reader, node: yaml.Node, *, key: str) -> Any:
    value = reader.scalar(node, what=f"a value of {key}")
    _check_finite(reader, node, key, value)
    try:
        apply_variation(EpisodeSpec(), {key: value})
    except VariationError as error:
        raise reader.error(node, f"bad {key} value {value!r}: {error}") from None
    return value


def _check_variation_key(reader: _Reader, node: yaml.Node, key: str) -> None:
    if key not in VARIATION_KEYS:
        raise reader.error(node, f"unknown variation key {key!r} (allowed: {', '.join(VARIATION_KEYS)})")


def _axes(reader: _Reader, node: yaml.Node | None) -> list[_Axis]:
    if node is None:
        return []
    axes = []
    for key, (key_node, values_node) in reader.mapping(node, what="variations").items():
        _check_variation_key(reader, key_node, key)
        values: dict[str, tuple[str, Any, int]] = {}
        for item in reader.items(values_node, what=f"variations.{key}"):
            value = _variation_value(reader, item, key=key)
            text = _text(value)
            if text in values:
                raise reader.error(item, f"{key} value {text!r} is listed twice (also on line {values[text][2]})")
            values[text] = (text, value, _line(item))
        axes.append(_Axis(key=key, values=tuple(values.values())))
    return axes


def _worlds(axes: list[_Axis]) -> list[_World]:
    if not axes:
        return [_World(label=DEFAULT_VARIATION)]
    return [_world([(axis.key, value) for axis, (_, value, _) in zip(axes, combination)])
            for combination in itertools.product(*(axis.values for axis in axes))]


def _listed_worlds(reader: _Reader, node: yaml.Node) -> tuple[list[_World], list[_Axis]]:
    """``worlds:``, a list of variation mappings: the worlds in written order, and per key the values they use
    (the axes exclude entries may name)."""
    worlds: dict[str, tuple[_World, int]] = {}
    values: dict[str, dict[str, tuple[str, Any, int]]] = {}
    for item in reader.items(node, what="worlds"):
        items = []
        for key, (key_node, value_node) in reader.mapping(item, what="a world").items():
            _check_variation_key(reader, key_node, key)
            value = _variation_value(reader, value_node, key=key)
            items.append((key, value))
            values.setdefault(key, {}).setdefault(_text(value), (_text(value), value, _line(value_node)))
        world = _world(items)
        if world.label in worlds:
            raise reader.error(item, f"world {world.label!r} is listed twice (also on line {worlds[world.label][1]})")
        worlds[world.label] = (world, _line(item))
    axes = [_Axis(key=key, values=tuple(texts.values())) for key, texts in values.items()]
    return [world for world, _ in worlds.values()], axes


def _world(items: list[tuple[str, Any]]) -> _World:
    if not items:
        return _World(label=DEFAULT_VARIATION)
    return _World(label=",".join(f"{key}={_text(value)}" for key, value in items), items=tuple(items))


# -- perturbations -------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Perturbation:
    """Noise stages (in written order) and camera variation items of one perturbation, with its label and line."""

    label: str
    line: int
    noise: tuple[NoiseStage, ...] = ()
    camera: tuple[tuple[str, Any], ...] = ()


def _perturbation(reader: _Reader, node: yaml.Node) -> _Perturbation:
    noise, camera, labels = [], [], []
    for key, params, item_node in _perturbation_items(reader, node):
        if key in NOISE_MODEL_NAMES:
            noise.append(_noise(reader, item_node, key, params))
        elif key in CAMERA_PERTURBATION_KEYS:
            _camera_item(reader, item_node, key, params)
            camera.append((key, params))
        else:
            raise reader.error(item_node, f"unknown perturbation {key!r} (noise models: {', '.join(NOISE_MODEL_NAMES)}"
                                          f"; camera keys: {', '.join(CAMERA_PERTURBATION_KEYS)}; or none)")
        labels.append(_item_label(key, params))
    return _Perturbation(label="+".join(labels) or NO_PERTURBATION, line=_line(node), noise=tuple(noise),
                         camera=tuple(camera))


def _perturbation_items(reader: _Reader, node: yaml.Node) -> Iterator[tuple[str, Any, yaml.Node]]:
    """(key, parameters, node) of each item: noise model or camera key; nothing for ``none``."""
    if isinstance(node, yaml.MappingNode):
        entries = reader.mapping(node, what="a perturbation")
        if not entries:
            raise reader.error(node, "an empty perturbation (write none for no perturbation)")
        for key, (key_node, value_node) in entries.items():
            if isinstance(value_node, yaml.SequenceNode):
                raise reader.error(value_node, f"perturbation {key!r} takes a value or a mapping, not a list")
            yield key, reader.value(value_node), key_node
        return
    value = reader.scalar(node, what="a perturbation")
    if value is None or (isinstance(value, str) and value.strip().lower() == NO_PERTURBATION):
        return
    if not isinstance(value, str):
        raise reader.error(node, f"a perturbation is none, \"model=value\", \"camera=left\" or a mapping of them, "
                                 f"got {value!r}")
    for part in _ITEM_JOIN.split(value):
        yield (*_string_item(reader, node, part), node)


def _string_item(reader: _Reader, node: yaml.Node, text: str) -> tuple[str, Any]:
    match = _STRING_ITEM.fullmatch(text)
    if not match:
        raise reader.error(node, f"bad perturbation item {text.strip()!r} (want model, model=value, "
                                 f"model:key=value,... or camera=PRESET)")
    key, separator, rest = match[1], match[2], match[3]
    if separator is None:
        return key, {}
    if separator == "=":
        return key, reader.yaml_text(node, rest)
    try:
        pairs = parse_pairs(rest)
    except VariationError as error:
        raise reader.error(node, f"bad perturbation item {text.strip()!r}: {error}") from None
    return key, {name: reader.yaml_text(node, value) for name, value in pairs}


def _noise(reader: _Reader, node: yaml.Node, model: str, params: Any) -> NoiseStage:
    try:
        return noise_stage({model: params})
    except VariationError as error:
        raise reader.error(node, f"bad {model} parameters {params!r}: {error}") from None


def _camera_item(reader: _Reader, node: yaml.Node, key: str, value: Any) -> None:
    if isinstance(value, (dict, list)):
        raise reader.error(node, f"perturbation {key!r} takes a single value, got {value!r}")
    _check_finite(reader, node, key, value)
    try:
        apply_variation(EpisodeSpec(), {key: value})
    except VariationError as error:
        raise reader.error(node, f"bad {key} value {value!r}: {error}") from None


def _check_finite(reader: _Reader, node: yaml.Node, key: str, value: Any) -> None:
    if isinstance(value, float) and not math.isfinite(value):
        raise reader.error(node, f"{key} must be a finite number, got {value!r}")


def _item_label(key: str, params: Any) -> str:
    if isinstance(params, dict):
        if not params:
            return key
        return f"{key}:" + ",".join(f"{name}={_text(value)}" for name, value in params.items())
    return f"{key}={_text(params)}"


def _perturbations(reader: _Reader, node: yaml.Node | None) -> list[_Perturbation]:
    if node is None:
        return [_Perturbation(label=NO_PERTURBATION, line=1)]
    perturbations: dict[str, _Perturbation] = {}
    for item in reader.items(node, what="perturbations"):
        perturbation = _perturbation(reader, item)
        if perturbation.label in perturbations:
            first = perturbations[perturbation.label].line
            raise reader.error(item, f"perturbation {perturbation.label!r} is listed twice (also on line {first})")
        perturbations[perturbation.label] = perturbation
    return list(perturbations.values())


# -- combinations, exclude, include --------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Combination:
    """A brain on a circuit, in one world, under one perturbation (repetitions expand it)."""

    brain: BrainEntry
    circuit: str
    world: _World
    perturbation: _Perturbation

    def coordinates(self, repetition: int) -> dict[str, str]:
        """Axis -> label text, what exclude entries match against."""
        return {"brain": self.brain.label, "circuit": self.circuit, "perturbation": self.perturbation.label,
                "repetition": str(repetition), **self.world.texts}

    def key(self, repetition: int, *, part: str = "") -> str:
        prefix = f"{part}:" if part else ""
        return f"{prefix}{self.brain.label}/{self.circuit}/{self.world.label}/{self.perturbation.label}/r{repetition}"


@dataclass
class _Plan:
    """Everything read from the file (or one part of it), before expansion."""

    brains: tuple[BrainEntry, ...]
    shadows: tuple[BrainEntry, ...]
    circuits: list[str]
    axes: list[_Axis]
    worlds: list[_World]
    perturbations: list[_Perturbation]
    repetitions: int
    seed: int
    base: EpisodeSpec
    part: str = ""

    @classmethod
    def read(cls, reader: _Reader, top: dict[str, tuple[yaml.Node, yaml.Node]], *, base_dir: Path,
             part: str = "") -> _Plan:
        brains = _brain_entries(reader, top["brains"][1], what="brains", base_dir=base_dir)
        shadows = (_brain_entries(reader, top["shadows"][1], what="shadows", base_dir=base_dir)
                   if "shadows" in top else [])
        _check_unique_labels(reader, brains + shadows)
        repetitions = reader.integer(top["repetitions"][1], what="repetitions", minimum=1) \
            if "repetitions" in top else 1
        seed = reader.integer(top["seed"][1], what="seed", minimum=0) if "seed" in top else 0
        if "worlds" in top:
            worlds, axes = _listed_worlds(reader, top["worlds"][1])
        else:
            axes = _axes(reader, _value_node(top, "variations"))
            worlds = _worlds(axes)
        return cls(brains=tuple(entry for entry, _ in brains), shadows=tuple(entry for entry, _ in shadows),
                   circuits=_circuits(reader, top["circuits"][1]), axes=axes, worlds=worlds,
                   perturbations=_perturbations(reader, _value_node(top, "perturbations")),
                   repetitions=repetitions, seed=seed, base=_base_spec(reader, top), part=part)

    def expand(self, reader: _Reader, top: dict[str, tuple[yaml.Node, yaml.Node]], *,
               first_index: int = 0) -> list[PlannedEpisode]:
        self._check_size(reader, top)
        excludes = [self._exclude(reader, item) for item in _list_of(reader, top, "exclude")]
        planned: dict[str, tuple[_Combination, int]] = {}
        for combination in self._product():
            for repetition in range(self.repetitions):
                coordinates = combination.coordinates(repetition)
                if not any(_matches(exclude, coordinates) for exclude in excludes):
                    planned[combination.key(repetition, part=self.part)] = (combination, repetition)
        for item in _list_of(reader, top, "include"):
            combination = self._include(reader, item)
            for repetition in range(self.repetitions):
                planned.setdefault(combination.key(repetition, part=self.part), (combination, repetition))
        if not planned:
            where = top["exclude"][0] if "exclude" in top else None
            what = f"part {self.part!r}" if self.part else "the matrix"
            raise reader.error(where, f"{what} expands to no episodes (every combination is excluded)")
        return [self._episode(reader, key, first_index + index, combination, repetition)
                for index, (key, (combination, repetition)) in enumerate(planned.items())]

    def _check_size(self, reader: _Reader, top: dict[str, tuple[yaml.Node, yaml.Node]]) -> None:
        count = len(self.brains) * len(self.circuits) * len(self.perturbations) * self.repetitions
        count *= len(self.worlds)
        if count > MAX_EPISODES:
            raise reader.error(_value_node(top, "repetitions"),
                               f"the matrix expands to {count} episodes (at most {MAX_EPISODES})")

    def _product(self) -> Iterator[_Combination]:
        for brain, circuit, world, perturbation in itertools.product(self.brains, self.circuits, self.worlds,
                                                                     self.perturbations):
            yield _Combination(brain=brain, circuit=circuit, world=world, perturbation=perturbation)

    def _exclude(self, reader: _Reader, node: yaml.Node) -> dict[str, str]:
        """An exclude entry as axis -> label text; every value must be one the matrix has (typos fail here)."""
        allowed = ("brain", "circuit", "repetition", "perturbation", *(axis.key for axis in self.axes))
        entries = reader.mapping(node, what="an exclude entry")
        for key, (key_node, _) in entries.items():
            if key in VARIATION_KEYS and key not in allowed:
                raise reader.error(key_node, f"exclude key {key!r} is not a variation axis of this matrix (allowed: "
                                             f"{', '.join(allowed)})")
            if key not in allowed:
                raise reader.error(key_node, f"unknown key {key!r} in an exclude entry (allowed: {', '.join(allowed)})")
        if not entries:
            raise reader.error(node, f"an empty exclude entry would drop everything (keys: {', '.join(allowed)})")
        return {key: self._exclude_value(reader, key, value_node) for key, (_, value_node) in entries.items()}

    def _exclude_value(self, reader: _Reader, key: str, node: yaml.Node) -> str:
        if key == "perturbation":
            text = _perturbation(reader, node).label
            known = [perturbation.label for perturbation in self.perturbations]
        elif key == "repetition":
            text = str(reader.integer(node, what="exclude repetition", minimum=0))
            known = [str(repetition) for repetition in range(self.repetitions)]
        else:
            text = _text(reader.scalar(node, what=f"exclude {key}"))
            known = self._known(key)
        if text not in known:
            raise reader.error(node, f"exclude {key} {text!r} is not in this matrix (known: {', '.join(known)})")
        return text

    def _known(self, key: str) -> list[str]:
        if key == "brain":
            return [brain.label for brain in self.brains]
        if key == "circuit":
            return list(self.circuits)
        return [text for axis in self.axes if axis.key == key for text, _, _ in axis.values]

    def _include(self, reader: _Reader, node: yaml.Node) -> _Combination:
        allowed = ("brain", "circuit", "perturbation", *VARIATION_KEYS)
        entries = reader.mapping(node, what="an include entry", allowed=allowed)
        if "brain" not in entries or "circuit" not in entries:
            raise reader.error(node, "an include entry needs brain and circuit (other keys: perturbation, "
                                     "variation keys)")
        brain_node = entries["brain"][1]
        label = reader.text(brain_node, what="include brain")
        brains = {brain.label: brain for brain in self.brains}
        if label not in brains:
            raise reader.error(brain_node, f"include brain {label!r} is not a brain label of this matrix "
                                           f"(labels: {', '.join(brains)})")
        perturbation = (_perturbation(reader, entries["perturbation"][1]) if "perturbation" in entries
                        else _Perturbation(label=NO_PERTURBATION, line=_line(node)))
        return _Combination(brain=brains[label], circuit=_circuit(reader, entries["circuit"][1]),
                            world=self._include_world(reader, entries), perturbation=perturbation)

    def _include_world(self, reader: _Reader, entries: dict[str, tuple[yaml.Node, yaml.Node]]) -> _World:
        # Matrix axes first, in their order, so an include of an existing combination has the same label.
        axis_keys = [axis.key for axis in self.axes]
        keys = [key for key in axis_keys if key in entries]
        keys += [key for key in entries if key in VARIATION_KEYS and key not in axis_keys]
        return _world([(key, _variation_value(reader, entries[key][1], key=key)) for key in keys])

    def _episode(self, reader: _Reader, key: str, index: int, combination: _Combination,
                 repetition: int) -> PlannedEpisode:
        spec = msgspec.structs.replace(self.base, circuit=combination.circuit, seed=self.seed + repetition,
                                       active_brain=combination.brain.label,
                                       noise=list(combination.perturbation.noise))
        try:
            if combination.world.items:
                spec = apply_variation(spec, dict(combination.world.items))
            for item_key, value in combination.perturbation.camera:  # one by one: presets add up
                spec = apply_variation(spec, {item_key: value})
        except VariationError as error:
            raise MatrixError(f"episode {key}: {error}", source=reader.source,
                              line=combination.perturbation.line) from None
        return PlannedEpisode(key=key, index=index, brain=combination.brain, circuit=combination.circuit,
                              variation=combination.world.label, perturbation=combination.perturbation.label,
                              repetition=repetition, spec=spec, part=self.part)


def _value_node(top: dict[str, tuple[yaml.Node, yaml.Node]], key: str) -> yaml.Node | None:
    return top[key][1] if key in top else None


def _list_of(reader: _Reader, top: dict[str, tuple[yaml.Node, yaml.Node]], key: str) -> list[yaml.Node]:
    return reader.items(top[key][1], what=key) if key in top else []


def _matches(exclude: dict[str, str], coordinates: dict[str, str]) -> bool:
    return all(coordinates.get(key) == text for key, text in exclude.items())


def _yaml_json(value: Any) -> str:
    """JSON text that PyYAML reads back as the same value: JSON's ``1e-07`` is a string to YAML 1.1, which wants
    a dot in the mantissa (``1.0e-07``)."""
    if isinstance(value, float):
        text = json.dumps(value)
        mantissa, e, exponent = text.partition("e")
        return f"{mantissa}.0e{exponent}" if e and "." not in mantissa else text
    if isinstance(value, list):
        return "[" + ", ".join(_yaml_json(item) for item in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{json.dumps(str(key))}: {_yaml_json(item)}" for key, item in value.items()) + "}"
    return json.dumps(value)


def smoke_form(matrix: Matrix, *, brains: Iterable[str] | None = None, cells_per_part: int = 2,
               sim_seconds: float = 4.0, camera_wh: tuple[int, int] = (160, 120)) -> Matrix:
    """``matrix`` cut to seconds (``--smoke``, what CI runs): the brains labelled in ``brains`` (default: all), the
    first ``cells_per_part`` conditions of every part, repetition 0, ``sim_seconds`` of simulated time on a small
    camera. Keys stay the full matrix's, so every kept episode still lands in its report cell."""
    wanted = None if brains is None else set(brains)
    kept: list[PlannedEpisode] = []
    conditions_by_part: dict[str, list] = {}
    for episode in matrix.episodes:
        if (wanted is not None and episode.brain.label not in wanted) or episode.repetition != 0:
            continue
        conditions = conditions_by_part.setdefault(episode.part, [])
        condition = (episode.variation, episode.perturbation)
        if condition not in conditions:
            if len(conditions) >= cells_per_part:
                continue
            conditions.append(condition)
        camera = msgspec.structs.replace(episode.spec.camera, width_px=camera_wh[0], height_px=camera_wh[1])
        spec = msgspec.structs.replace(episode.spec, max_sim_seconds=sim_seconds, camera=camera)
        kept.append(dataclasses.replace(episode, index=len(kept), spec=spec))
    return dataclasses.replace(matrix, name=f"{matrix.name}-smoke", episodes=tuple(kept),
                               brains=tuple(b for b in matrix.brains if wanted is None or b.label in wanted))
