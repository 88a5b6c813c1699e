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

import itertools
import re
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgspec
import yaml

from circuits import circuit_names
from circuits.library import GENERATED_NAMES, is_circuit_name
from orchestrator.matrix_brains import check_unique_labels, read_brain_entries
from orchestrator.matrix_conditions import (
    VARIATION_KEYS,
    Axis,
    Perturbation,
    World,
    read_axes,
    read_listed_worlds,
    read_perturbation,
    read_perturbations,
    read_variation_value,
    read_world,
    read_worlds,
)
from orchestrator.matrix_plan import (
    DEFAULT_VARIATION,
    NO_PERTURBATION,
    BrainEntry,
    Matrix,
    MatrixError,
    PlannedEpisode,
    part_of,
    smoke_form,
    with_renderer,
)
from orchestrator.yaml_nodes import NodeReader, label_text, line_of
from protocol.keys import check_name
from protocol.messages import CameraSpec, EpisodeSpec

# The protocol's own lists of world and camera variation keys (it has no public name for them).
from protocol.variations import (
    VariationError,
    apply_variation,
)
from services.simulator.renderers import default_renderer

TOP_LEVEL_KEYS = (
    "name",
    "brains",
    "circuits",
    "variations",
    "worlds",
    "perturbations",
    "repetitions",
    "limits",
    "camera",
    "seed",
    "realtime",
    "renderer",
    "shadows",
    "exclude",
    "include",
    "parts",
)
# What a part may set for itself; everything else (brains, shadows, camera, seed, realtime) is the matrix's.
PART_KEYS = ("circuits", "variations", "worlds", "perturbations", "repetitions", "limits", "exclude", "include")
LIMIT_KEYS = ("laps", "max_sim_seconds", "brain_timeout_s", "step_s")
CAMERA_FIELDS = tuple(field.name for field in msgspec.structs.fields(CameraSpec))
MAX_EPISODES = 100_000  # a typo in repetitions should fail here, not exhaust memory
MATRIX_RENDERER = "auto"  # without `renderer:` or $DRIVEBENCH_RENDERER: gl where EGL works (parity: README)

_CAMERA_SIZE = re.compile(r"\s*(\d+)\s*[xX]\s*(\d+)\s*")


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
    reader = NodeReader(source, error_type=MatrixError, top_level_keys=TOP_LEVEL_KEYS)
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
    return Matrix(
        name=_name(reader, top, source),
        source=source,
        text=text,
        brains=plan.brains,
        shadows=plan.shadows,
        episodes=tuple(episodes),
        variation_keys=tuple(variation_keys),
        parts=tuple(part for part, _ in parts if part),
    )


def _check_one_world_form(reader: NodeReader, entries: dict[str, tuple[yaml.Node, yaml.Node]]) -> None:
    if "variations" in entries and "worlds" in entries:
        raise reader.error(entries["worlds"][0], "give variations (a product) or worlds (a list), not both")


def _parts(
    reader: NodeReader, root: yaml.Node, top: dict[str, tuple[yaml.Node, yaml.Node]]
) -> list[tuple[str, dict[str, tuple[yaml.Node, yaml.Node]]]]:
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


def _name(reader: NodeReader, top: dict[str, tuple[yaml.Node, yaml.Node]], source: str) -> str:
    if "name" in top:
        return reader.text(top["name"][1], what="name")
    return "matrix" if source.startswith("<") else Path(source).stem


# -- circuits, settings ------------------------------------------------------------------------------------------


def _circuit(reader: NodeReader, node: yaml.Node) -> str:
    name = reader.text(node, what="a circuit")
    if not is_circuit_name(name):
        raise reader.error(
            node,
            f"unknown circuit {name!r} (known: {', '.join(circuit_names())}, "
            f"or {GENERATED_NAMES}; see `drivebench circuits list`)",
        )
    return name


def _circuits(reader: NodeReader, node: yaml.Node) -> list[str]:
    circuits: dict[str, int] = {}
    for item in reader.items(node, what="circuits"):
        name = _circuit(reader, item)
        if name in circuits:
            raise reader.error(item, f"circuit {name!r} is listed twice (also on line {circuits[name]})")
        circuits[name] = line_of(item)
    return list(circuits)


def _spec_error(error: msgspec.ValidationError) -> str:
    return re.sub(r" - at `\$[^`]*`$", "", str(error))


def _base_spec(reader: NodeReader, top: dict[str, tuple[yaml.Node, yaml.Node]]) -> EpisodeSpec:
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


def _spec_field(reader: NodeReader, node: yaml.Node, *, key: str, what: str) -> Any:
    value = reader.scalar(node, what=what)
    try:
        msgspec.convert({key: value}, EpisodeSpec)
    except msgspec.ValidationError as error:
        raise reader.error(node, f"bad {what} {value!r}: {_spec_error(error)}") from None
    return value


def _camera(reader: NodeReader, node: yaml.Node) -> CameraSpec:
    if isinstance(node, yaml.ScalarNode):
        match = _CAMERA_SIZE.fullmatch(str(reader.value(node)))
        if not match:
            raise reader.error(
                node, f"camera must look like 320x240 or {{width_px: 320, height_px: 240}}, got {node.value!r}"
            )
        fields: dict[str, Any] = {"width_px": int(match[1]), "height_px": int(match[2])}
    else:
        fields = {}
        for key, (_, value_node) in reader.mapping(node, what="camera", allowed=CAMERA_FIELDS).items():
            fields[key] = reader.scalar(value_node, what=f"camera.{key}")
            _convert_camera(reader, value_node, {key: fields[key]}, what=f"camera.{key} {fields[key]!r}")
    return _convert_camera(reader, node, fields, what="camera")


def _convert_camera(reader: NodeReader, node: yaml.Node, fields: dict[str, Any], *, what: str) -> CameraSpec:
    try:
        return msgspec.convert(fields, CameraSpec)
    except msgspec.ValidationError as error:
        raise reader.error(node, f"bad {what}: {_spec_error(error)}") from None


# -- combinations, exclude, include --------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Combination:
    """A brain on a circuit, in one world, under one perturbation (repetitions expand it)."""

    brain: BrainEntry
    circuit: str
    world: World
    perturbation: Perturbation

    def coordinates(self, repetition: int) -> dict[str, str]:
        """Axis -> label text, what exclude entries match against."""
        return {
            "brain": self.brain.label,
            "circuit": self.circuit,
            "perturbation": self.perturbation.label,
            "repetition": str(repetition),
            **self.world.texts,
        }

    def key(self, repetition: int, *, part: str = "") -> str:
        prefix = f"{part}:" if part else ""
        return f"{prefix}{self.brain.label}/{self.circuit}/{self.world.label}/{self.perturbation.label}/r{repetition}"


@dataclass
class _Plan:
    """Everything read from the file (or one part of it), before expansion."""

    brains: tuple[BrainEntry, ...]
    shadows: tuple[BrainEntry, ...]
    circuits: list[str]
    axes: list[Axis]
    worlds: list[World]
    perturbations: list[Perturbation]
    repetitions: int
    seed: int
    base: EpisodeSpec
    part: str = ""

    @classmethod
    def read(
        cls, reader: NodeReader, top: dict[str, tuple[yaml.Node, yaml.Node]], *, base_dir: Path, part: str = ""
    ) -> _Plan:
        brains = read_brain_entries(reader, top["brains"][1], what="brains", base_dir=base_dir)
        shadows = (
            read_brain_entries(reader, top["shadows"][1], what="shadows", base_dir=base_dir) if "shadows" in top else []
        )
        check_unique_labels(reader, brains + shadows)
        repetitions = (
            reader.integer(top["repetitions"][1], what="repetitions", minimum=1) if "repetitions" in top else 1
        )
        seed = reader.integer(top["seed"][1], what="seed", minimum=0) if "seed" in top else 0
        if "worlds" in top:
            worlds, axes = read_listed_worlds(reader, top["worlds"][1])
        else:
            axes = read_axes(reader, _value_node(top, "variations"))
            worlds = read_worlds(axes)
        return cls(
            brains=tuple(entry for entry, _ in brains),
            shadows=tuple(entry for entry, _ in shadows),
            circuits=_circuits(reader, top["circuits"][1]),
            axes=axes,
            worlds=worlds,
            perturbations=read_perturbations(reader, _value_node(top, "perturbations")),
            repetitions=repetitions,
            seed=seed,
            base=_base_spec(reader, top),
            part=part,
        )

    def expand(
        self, reader: NodeReader, top: dict[str, tuple[yaml.Node, yaml.Node]], *, first_index: int = 0
    ) -> list[PlannedEpisode]:
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
        return [
            self._episode(reader, key, first_index + index, combination, repetition)
            for index, (key, (combination, repetition)) in enumerate(planned.items())
        ]

    def _check_size(self, reader: NodeReader, top: dict[str, tuple[yaml.Node, yaml.Node]]) -> None:
        count = len(self.brains) * len(self.circuits) * len(self.perturbations) * self.repetitions
        count *= len(self.worlds)
        if count > MAX_EPISODES:
            raise reader.error(
                _value_node(top, "repetitions"), f"the matrix expands to {count} episodes (at most {MAX_EPISODES})"
            )

    def _product(self) -> Iterator[_Combination]:
        for brain, circuit, world, perturbation in itertools.product(
            self.brains, self.circuits, self.worlds, self.perturbations
        ):
            yield _Combination(brain=brain, circuit=circuit, world=world, perturbation=perturbation)

    def _exclude(self, reader: NodeReader, node: yaml.Node) -> dict[str, str]:
        """An exclude entry as axis -> label text; every value must be one the matrix has (typos fail here)."""
        allowed = ("brain", "circuit", "repetition", "perturbation", *(axis.key for axis in self.axes))
        entries = reader.mapping(node, what="an exclude entry")
        for key, (key_node, _) in entries.items():
            if key in VARIATION_KEYS and key not in allowed:
                raise reader.error(
                    key_node,
                    f"exclude key {key!r} is not a variation axis of this matrix (allowed: {', '.join(allowed)})",
                )
            if key not in allowed:
                raise reader.error(key_node, f"unknown key {key!r} in an exclude entry (allowed: {', '.join(allowed)})")
        if not entries:
            raise reader.error(node, f"an empty exclude entry would drop everything (keys: {', '.join(allowed)})")
        return {key: self._exclude_value(reader, key, value_node) for key, (_, value_node) in entries.items()}

    def _exclude_value(self, reader: NodeReader, key: str, node: yaml.Node) -> str:
        if key == "perturbation":
            text = read_perturbation(reader, node).label
            known = [perturbation.label for perturbation in self.perturbations]
        elif key == "repetition":
            text = str(reader.integer(node, what="exclude repetition", minimum=0))
            known = [str(repetition) for repetition in range(self.repetitions)]
        else:
            text = label_text(reader.scalar(node, what=f"exclude {key}"))
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

    def _include(self, reader: NodeReader, node: yaml.Node) -> _Combination:
        allowed = ("brain", "circuit", "perturbation", *VARIATION_KEYS)
        entries = reader.mapping(node, what="an include entry", allowed=allowed)
        if "brain" not in entries or "circuit" not in entries:
            raise reader.error(
                node, "an include entry needs brain and circuit (other keys: perturbation, variation keys)"
            )
        brain_node = entries["brain"][1]
        label = reader.text(brain_node, what="include brain")
        brains = {brain.label: brain for brain in self.brains}
        if label not in brains:
            raise reader.error(
                brain_node, f"include brain {label!r} is not a brain label of this matrix (labels: {', '.join(brains)})"
            )
        perturbation = (
            read_perturbation(reader, entries["perturbation"][1])
            if "perturbation" in entries
            else Perturbation(label=NO_PERTURBATION, line=line_of(node))
        )
        return _Combination(
            brain=brains[label],
            circuit=_circuit(reader, entries["circuit"][1]),
            world=self._include_world(reader, entries),
            perturbation=perturbation,
        )

    def _include_world(self, reader: NodeReader, entries: dict[str, tuple[yaml.Node, yaml.Node]]) -> World:
        # Matrix axes first, in their order, so an include of an existing combination has the same label.
        axis_keys = [axis.key for axis in self.axes]
        keys = [key for key in axis_keys if key in entries]
        keys += [key for key in entries if key in VARIATION_KEYS and key not in axis_keys]
        return read_world([(key, read_variation_value(reader, entries[key][1], key=key)) for key in keys])

    def _episode(
        self, reader: NodeReader, key: str, index: int, combination: _Combination, repetition: int
    ) -> PlannedEpisode:
        spec = msgspec.structs.replace(
            self.base,
            circuit=combination.circuit,
            seed=self.seed + repetition,
            active_brain=combination.brain.label,
            noise=list(combination.perturbation.noise),
        )
        try:
            if combination.world.items:
                spec = apply_variation(spec, dict(combination.world.items))
            for item_key, value in combination.perturbation.camera:  # one by one: presets add up
                spec = apply_variation(spec, {item_key: value})
        except VariationError as error:
            raise MatrixError(
                f"episode {key}: {error}", source=reader.source, line=combination.perturbation.line
            ) from None
        return PlannedEpisode(
            key=key,
            index=index,
            brain=combination.brain,
            circuit=combination.circuit,
            variation=combination.world.label,
            perturbation=combination.perturbation.label,
            repetition=repetition,
            spec=spec,
            part=self.part,
        )


def _value_node(top: dict[str, tuple[yaml.Node, yaml.Node]], key: str) -> yaml.Node | None:
    return top[key][1] if key in top else None


def _list_of(reader: NodeReader, top: dict[str, tuple[yaml.Node, yaml.Node]], key: str) -> list[yaml.Node]:
    return reader.items(top[key][1], what=key) if key in top else []


def _matches(exclude: dict[str, str], coordinates: dict[str, str]) -> bool:
    return all(coordinates.get(key) == text for key, text in exclude.items())


__all__ = [
    "DEFAULT_VARIATION",
    "NO_PERTURBATION",
    "BrainEntry",
    "Matrix",
    "MatrixError",
    "PlannedEpisode",
    "load_matrix",
    "parse_matrix",
    "part_of",
    "smoke_form",
    "with_renderer",
]
