"""Test matrices: a YAML file of brains x circuits x variations x perturbations x repetitions, expanded into the
planned episodes of a matrix run. Pure: no bus, no processes; every mistake is found here, before anything starts.

A matrix file::

    name: generalization                      # default: the file's stem; letters, digits, _ . - (a folder name)
    brains: [explicit, {name: memdccp, weights: runs/train/memdccp.ckpt, label: memdccp-v1, options: {threads: 1}}]
    circuits: [simple, montmelo, montreal]    # built-in, user, random:/twisty:/grandprix:SEED
    variations: {line: [red, white, none], road: [grey, white], walls: [on, off]}   # default: one "default" world
    #   also the route: direction: [forward, reverse], start_m: [0, 150] (metres along, below each circuit's length)
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
does not set comes from the top level. Instead of circuits and worlds, a part may ``draw`` held-out conditions
from a seed (``orchestrator.matrix.draw``: ``draw: {count: 20, seed: 7, circuits: [random, grandprix, montreal],
variations: {line: [red, white]}}``), refusing circuits the brains' training data drove. Its episodes' keys start
with ``<part>:``, and parts expand in written order.

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

Every mistake raises :class:`MatrixError`, one line: ``FILE:LINE: what is wrong (what is allowed)``. A file with
several gets them all in one error, one line each in line order (``protocol.deploy.typed_yaml.MAX_FAULTS`` at
most): the schema's mistakes first, if any; else every mistake in the values that does not follow from another (a
value with a mistake is left out, and what depends on it is not checked: an unknown circuit in a part means no
check of that part's exclude entries).
"""

from __future__ import annotations

import functools
import itertools
import re
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgspec
from msgspec import UnsetType

from circuits import Circuit, CircuitError, circuit_names, load_circuit
from circuits.library import GENERATED_NAMES, is_circuit_name
from orchestrator.matrix.brains import check_unique_labels, read_brain_entries
from orchestrator.matrix.conditions import (
    VARIATION_KEYS,
    Axis,
    Perturbation,
    World,
    label_text,
    read_axes,
    read_listed_worlds,
    read_perturbation,
    read_perturbations,
    read_variation_value,
    read_world,
    read_worlds,
)
from orchestrator.matrix.draw import draw_conditions
from orchestrator.matrix.plan import (
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
from orchestrator.matrix.schema import MatrixFile, Part, items, read_matrix_file, text_at, written
from protocol import environment
from protocol.deploy.typed_yaml import Document, FileError, compose, convert
from protocol.deploy.typed_yaml import Path as At
from protocol.episode_spec import CameraSpec, EpisodeSpec
from protocol.keys import check_name
from protocol.suggest import did_you_mean
from protocol.variations import VariationError, apply_variation
from services.simulator.renderers import default_renderer

MAX_EPISODES = 100_000  # a typo in repetitions should fail here, not exhaust memory
# Without `renderer:` or $DRIVEBENCH_RENDERER: auto, gl where EGL works (parity: docs/guides/renderers.md).
MATRIX_RENDERER = environment.RENDERER_BY_COMMAND["matrix"]

_CAMERA_SIZE = re.compile(r"\s*(\d+)\s*[xX]\s*(\d+)\s*")

# A key of the file (or of one part) -> (its typed value, where it was written).
Entries = dict[str, tuple[Any, At]]


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
    document = compose(text, source=source, error_type=MatrixError)
    matrix = read_matrix_file(document)  # the schema's mistakes, all at once; what follows reads typed values
    name = document.attempt(_name, document, matrix.name)
    brains = _brains(document, matrix, base_dir=Path(base_dir))
    parts = _parts(document, matrix)
    episodes: list[PlannedEpisode] = []
    variation_keys: dict[str, None] = {}
    for part, entries in parts:
        plan = _Plan.read(document, entries, brains=brains[0] if brains else (), part=part)
        if plan is None or brains is None:  # exclude and include entries name brains and values: left unchecked
            continue
        episodes += document.attempt(plan.expand, document, entries, first_index=len(episodes)) or []
        variation_keys.update(dict.fromkeys(axis.key for axis in plan.axes))
    document.raise_noted()
    assert brains is not None  # a mistake in them was noted, and raised just above
    if len(episodes) > MAX_EPISODES:
        raise document.error(
            ("parts",), f"the matrix expands to {len(episodes)} episodes (at most {MAX_EPISODES})", at_key=True
        )
    return Matrix(
        name=name or ("matrix" if source.startswith("<") else Path(source).stem),
        source=source,
        text=text,
        brains=brains[0],
        shadows=brains[1],
        episodes=tuple(episodes),
        variation_keys=tuple(variation_keys),
        parts=tuple(part for part, _ in parts if part),
    )


def _name(document: Document, value: str | UnsetType) -> str | None:
    """The written ``name``, or None. It names the output folder (``runs/matrix-<name>-<time>``): a ``/`` or ``..``
    in it would put the results elsewhere, so it is held to the rule of labels."""
    if not isinstance(value, str):
        return None
    name = text_at(document, value, ("name",))
    try:
        return check_name(name, what="matrix name")
    except ValueError as error:
        raise document.error(("name",), str(error)) from None


Brains = tuple[tuple[BrainEntry, ...], tuple[BrainEntry, ...]]  # the brains, the shadows


def _brains(document: Document, matrix: MatrixFile, *, base_dir: Path) -> Brains | None:
    """The brains and the shadows of the matrix, or None once a mistake in them is noted."""
    before = document.noted
    brains = read_brain_entries(document, matrix.brains, ("brains",), base_dir=base_dir)
    shadows: list[tuple[BrainEntry, At]] = []
    if not isinstance(matrix.shadows, UnsetType):
        shadows = read_brain_entries(document, matrix.shadows, ("shadows",), base_dir=base_dir)
    check_unique_labels(document, brains + shadows)
    if document.noted > before:
        return None
    return tuple(entry for entry, _ in brains), tuple(entry for entry, _ in shadows)


def _world_form_mistake(document: Document, entries: Entries) -> FileError | None:
    """The mistake of giving two ways to pick worlds (variations, worlds, draw), if there is one."""
    if "variations" in entries and "worlds" in entries:
        return document.error(
            entries["worlds"][1], "give variations (a product) or worlds (a list), not both", at_key=True
        )
    for key in ("circuits", "variations", "worlds"):
        if "draw" in entries and key in entries:
            return document.error(
                entries[key][1], f"give draw or {key}, not both (a draw picks its circuits and worlds)", at_key=True
            )
    return None


def _parts(document: Document, matrix: MatrixFile) -> list[tuple[str, Entries]]:
    """(part name, the keys it expands with) of each part; one nameless part for a matrix without ``parts``. A part
    whose keys do not fit together is left out, its mistake noted."""
    top: Entries = {key: (value, (key,)) for key, value in written(matrix).items() if key != "parts"}
    if (mistake := _world_form_mistake(document, top)) is not None:
        document.note(mistake)
        return []
    if not isinstance(matrix.parts, dict):
        if "circuits" not in top and "draw" not in top:
            document.note(document.error((), "missing 'circuits' (a matrix needs brains and circuits)"))
            return []
        return [("", top)]
    parts = []
    for name, part in matrix.parts.items():
        entries = _part(document, top, name, part)
        if entries is not None:
            parts.append((name, entries))
    return parts


def _part(document: Document, top: Entries, name: str, part: Part) -> Entries | None:
    """The keys part ``name`` expands with: its own, and the top level's it does not replace (None once a mistake
    is noted)."""
    where = ("parts", name)
    try:
        check_name(name, what="part name")
    except ValueError as error:
        document.note(document.error(where, str(error), at_key=True))  # its keys are still worth checking
    entries: Entries = {key: (value, (*where, key)) for key, value in written(part).items()}
    if (mistake := _world_form_mistake(document, entries)) is not None:
        document.note(mistake)
        return None
    merged = dict(top)
    if "variations" in entries or "worlds" in entries:  # a part's worlds replace the top level's, either form
        merged.pop("variations", None)
        merged.pop("worlds", None)
    if "draw" in entries:  # a draw replaces the top level's circuits and worlds; they replace its draw
        for key in ("circuits", "variations", "worlds"):
            merged.pop(key, None)
    elif {"circuits", "variations", "worlds"} & entries.keys():
        merged.pop("draw", None)
    merged.update(entries)
    if "circuits" not in merged and "draw" not in merged:
        document.note(
            document.error(
                where, f"part {name!r} has no circuits (give them in the part or at the top level)", at_key=True
            )
        )
        return None
    return merged


# -- circuits, settings ------------------------------------------------------------------------------------------


def _circuit(document: Document, value: Any, path: At) -> str:
    name = text_at(document, value, path)
    if not is_circuit_name(name):
        raise document.error(
            path,
            f"unknown circuit {name!r} (known: {', '.join(circuit_names())}, "
            f"or {GENERATED_NAMES}; see `drivebench circuits list`)" + did_you_mean(name, circuit_names()),
        )
    return name


def _circuits(document: Document, value: Any, path: At) -> list[str]:
    """The circuits written at ``path``; one with a mistake is noted and left out."""
    circuits: dict[str, int] = {}
    for item, item_path in items(value, path):
        name = document.attempt(_circuit, document, item, item_path)
        if name is None:
            continue
        if name in circuits:
            document.note(
                document.error(item_path, f"circuit {name!r} is listed twice (also on line {circuits[name]})")
            )
            continue
        circuits[name] = document.line(item_path)
    return list(circuits)


def start_problem(circuit: str, start_m: float) -> str | None:
    """Why an episode on ``circuit`` cannot start ``start_m`` along it (beyond its length), or None. A start at the
    line loads nothing: a matrix of generated circuits reads as fast as before."""
    if start_m == 0.0:
        return None
    try:
        _circuit_at_line(circuit).check_start_m(start_m)
    except CircuitError as error:
        return str(error)
    return None


@functools.lru_cache(maxsize=64)
def _circuit_at_line(name: str) -> Circuit:
    # Either direction: a circuit and its reverse have the same length.
    return load_circuit(name)


# The circuits, the variation axes, the worlds and, for a draw, the drawn (circuit, world) pairs.
Conditions = tuple[list[str], list[Axis], list[World], tuple[tuple[str, World], ...] | None]


def _conditions(document: Document, entries: Entries, *, brains: tuple[BrainEntry, ...]) -> Conditions | None:
    """Where and in which worlds the episodes drive: drawn, or circuits and variations or worlds. Mistakes are noted
    (what is returned then leaves out what had one); None when a draw had one."""
    if "draw" in entries:
        drawn = document.attempt(draw_conditions, document, *entries["draw"], brains=brains, check_circuit=_circuit)
        return None if drawn is None else (drawn.circuits, list(drawn.axes), drawn.worlds, drawn.conditions)
    circuits = _circuits(document, *entries["circuits"])
    if "worlds" in entries:
        worlds, axes = read_listed_worlds(document, *entries["worlds"])
    else:
        axes = read_axes(document, *entries.get("variations", (None, ())))
        worlds = read_worlds(axes)
    return circuits, axes, worlds, None


def _base_spec(document: Document, entries: Entries) -> EpisodeSpec:
    """The spec every episode starts from: limits, camera and realtime (circuit, seed, brain set per episode). The
    schema has checked each value; what is left are the bounds that tie values together."""
    fields: dict[str, Any] = {}
    if "limits" in entries:
        fields.update(written(entries["limits"][0]))
    if "realtime" in entries:
        fields["realtime"] = entries["realtime"][0]
    if "renderer" in entries:
        fields["renderer"] = entries["renderer"][0]
    else:
        try:
            fields["renderer"] = default_renderer(MATRIX_RENDERER)
        except ValueError as error:
            raise MatrixError(str(error), source=document.source, line=None) from None
    if "camera" in entries:  # a mistake in it is noted; the limits are checked all the same
        camera = document.attempt(_camera, document, *entries["camera"])
        if camera is not None:
            fields["camera"] = camera
    return convert(fields, EpisodeSpec, document=document, path=entries.get("limits", (None, ()))[1])


def _camera(document: Document, value: Any, path: At) -> CameraSpec:
    if isinstance(value, str):
        match = _CAMERA_SIZE.fullmatch(value)
        if not match:
            raise document.error(
                path, f"camera must look like 320x240 or {{width_px: 320, height_px: 240}}, got {value!r}"
            )
        fields: dict[str, Any] = {"width_px": int(match[1]), "height_px": int(match[2])}
    else:
        fields = written(value)
    return convert(fields, CameraSpec, document=document, path=path)


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
    circuits: list[str]
    axes: list[Axis]
    worlds: list[World]
    perturbations: list[Perturbation]
    repetitions: int
    seed: int
    base: EpisodeSpec
    part: str = ""
    conditions: tuple[tuple[str, World], ...] | None = None  # drawn (circuit, world) pairs instead of the product

    @classmethod
    def read(
        cls, document: Document, entries: Entries, *, brains: tuple[BrainEntry, ...], part: str = ""
    ) -> _Plan | None:
        """The plan of ``entries``, or None once a mistake in them is noted (each value is still checked, so that
        one reading notes them all)."""
        before = document.noted
        conditions = _conditions(document, entries, brains=brains)
        perturbations = read_perturbations(document, *entries.get("perturbations", (None, ())))
        base = document.attempt(_base_spec, document, entries)
        if conditions is None or base is None or document.noted > before:
            return None
        circuits, axes, worlds, drawn = conditions
        return cls(
            brains=brains,
            circuits=circuits,
            axes=axes,
            worlds=worlds,
            conditions=drawn,
            perturbations=perturbations,
            repetitions=entries.get("repetitions", (1, ()))[0],
            seed=entries.get("seed", (0, ()))[0],
            base=base,
            part=part,
        )

    def expand(self, document: Document, entries: Entries, *, first_index: int = 0) -> list[PlannedEpisode]:
        """The planned episodes. A mistake in the size or in an episode raises; one in exclude or include entries is
        noted (each entry's), and then nothing expands: "no episodes left" would only follow from them."""
        self._check_size(document, entries)
        before = document.noted
        read_excludes = [self._exclude(document, *item) for item in _list_of(entries, "exclude")]
        read_includes = [self._include(document, *item) for item in _list_of(entries, "include")]
        if document.noted > before:
            return []
        excludes = [exclude for exclude in read_excludes if exclude is not None]
        planned: dict[str, tuple[_Combination, int]] = {}
        for combination in self._product():
            for repetition in range(self.repetitions):
                coordinates = combination.coordinates(repetition)
                if not any(_matches(exclude, coordinates) for exclude in excludes):
                    planned[combination.key(repetition, part=self.part)] = (combination, repetition)
        for combination in (include for include in read_includes if include is not None):
            for repetition in range(self.repetitions):
                planned.setdefault(combination.key(repetition, part=self.part), (combination, repetition))
        if not planned:
            what = f"part {self.part!r}" if self.part else "the matrix"
            raise document.error(
                entries.get("exclude", (None, ()))[1],
                f"{what} expands to no episodes (every combination is excluded)",
                at_key=True,
            )
        return [
            self._episode(document, key, first_index + index, combination, repetition)
            for index, (key, (combination, repetition)) in enumerate(planned.items())
        ]

    def _check_size(self, document: Document, entries: Entries) -> None:
        count = len(self.brains) * len(self.perturbations) * self.repetitions
        count *= len(self.conditions) if self.conditions is not None else len(self.circuits) * len(self.worlds)
        if count > MAX_EPISODES:
            raise document.error(
                entries.get("repetitions", (None, ()))[1],
                f"the matrix expands to {count} episodes (at most {MAX_EPISODES})",
            )

    def _product(self) -> Iterator[_Combination]:
        conditions = self.conditions
        if conditions is None:
            conditions = tuple(itertools.product(self.circuits, self.worlds))
        for brain, (circuit, world), perturbation in itertools.product(self.brains, conditions, self.perturbations):
            yield _Combination(brain=brain, circuit=circuit, world=world, perturbation=perturbation)

    def _exclude(self, document: Document, entry: dict[str, Any], path: At) -> dict[str, str] | None:
        """An exclude entry as axis -> label text; every value must be one the matrix has (typos fail here). None
        once its mistakes (each key's and each value's) are noted."""
        allowed = ("brain", "circuit", "repetition", "perturbation", *(axis.key for axis in self.axes))
        if not entry:
            document.note(
                document.error(path, f"an empty exclude entry would drop everything (keys: {', '.join(allowed)})")
            )
            return None
        before = document.noted
        texts = {}
        for key, value in entry.items():
            if key not in allowed:
                document.note(document.error((*path, key), _unknown_exclude_key(key, allowed), at_key=True))
                continue
            texts[key] = document.attempt(self._exclude_value, document, key, value, (*path, key))
        if document.noted > before:
            return None
        return {key: text for key, text in texts.items() if text is not None}

    def _exclude_value(self, document: Document, key: str, value: Any, path: At) -> str:
        if key == "perturbation":
            text = read_perturbation(document, value, path).label
            known = [perturbation.label for perturbation in self.perturbations]
        elif key == "repetition":
            text = str(_repetition(document, value, path))
            known = [str(repetition) for repetition in range(self.repetitions)]
        else:
            if isinstance(value, (dict, list)):
                raise document.error(path, f"exclude {key} must be a single value, got {value!r}")
            text = label_text(value)
            known = self._known(key)
        if text not in known:
            raise document.error(path, f"exclude {key} {text!r} is not in this matrix (known: {', '.join(known)})")
        return text

    def _known(self, key: str) -> list[str]:
        if key == "brain":
            return [brain.label for brain in self.brains]
        if key == "circuit":
            return list(self.circuits)
        return [text for axis in self.axes if axis.key == key for text, _, _ in axis.values]

    def _include(self, document: Document, entry: dict[str, Any], path: At) -> _Combination | None:
        """An include entry as a combination, or None once its mistakes (each key's and each value's) are noted."""
        allowed = ("brain", "circuit", "perturbation", *VARIATION_KEYS)
        before = document.noted
        for key in entry:
            if key not in allowed:
                document.note(
                    document.error(
                        (*path, key),
                        f"unknown key {key!r} in an include entry (allowed: {', '.join(allowed)})",
                        at_key=True,
                    )
                )
        if "brain" not in entry or "circuit" not in entry:
            document.note(
                document.error(
                    path, "an include entry needs brain and circuit (other keys: perturbation, variation keys)"
                )
            )
            return None
        brain = document.attempt(self._include_brain, document, entry["brain"], (*path, "brain"))
        perturbation = (
            document.attempt(read_perturbation, document, entry["perturbation"], (*path, "perturbation"))
            if "perturbation" in entry
            else Perturbation(label=NO_PERTURBATION, line=document.line(path))
        )
        circuit = document.attempt(_circuit, document, entry["circuit"], (*path, "circuit"))
        world = self._include_world(document, entry, path)
        start_m = dict(world.items).get("start_m")
        if circuit is not None and start_m is not None and (problem := start_problem(circuit, float(start_m))):
            document.note(document.error((*path, "start_m"), problem))
        if brain is None or perturbation is None or circuit is None or document.noted > before:
            return None
        return _Combination(brain=brain, circuit=circuit, world=world, perturbation=perturbation)

    def _start_line(self, start_m: float) -> int | None:
        """The line of the ``start_m`` value an episode took from an axis (an include's own is checked at its
        entry)."""
        lines = {float(value): line for axis in self.axes if axis.key == "start_m" for _, value, line in axis.values}
        return lines.get(start_m)

    def _include_brain(self, document: Document, value: Any, path: At) -> BrainEntry:
        label = text_at(document, value, path)
        brains = {brain.label: brain for brain in self.brains}
        if label not in brains:
            raise document.error(
                path, f"include brain {label!r} is not a brain label of this matrix (labels: {', '.join(brains)})"
            )
        return brains[label]

    def _include_world(self, document: Document, entry: dict[str, Any], path: At) -> World:
        """The include entry's world; a mistake in a value is noted (the world then holds None for it)."""
        # Matrix axes first, in their order, so an include of an existing combination has the same label.
        axis_keys = [axis.key for axis in self.axes]
        keys = [key for key in axis_keys if key in entry]
        keys += [key for key in entry if key in VARIATION_KEYS and key not in axis_keys]
        return read_world(
            [(key, document.attempt(read_variation_value, document, entry[key], (*path, key), key=key)) for key in keys]
        )

    def _episode(
        self, document: Document, key: str, index: int, combination: _Combination, repetition: int
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
                f"episode {key}: {error}", source=document.source, line=combination.perturbation.line
            ) from None
        if (problem := start_problem(combination.circuit, spec.start_m)) is not None:
            raise MatrixError(problem, source=document.source, line=self._start_line(spec.start_m))
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


def _unknown_exclude_key(key: str, allowed: tuple[str, ...]) -> str:
    if key in VARIATION_KEYS:
        return f"exclude key {key!r} is not a variation axis of this matrix (allowed: {', '.join(allowed)})"
    return f"unknown key {key!r} in an exclude entry (allowed: {', '.join(allowed)})"


def _list_of(entries: Entries, key: str) -> list[tuple[Any, At]]:
    return items(*entries[key]) if key in entries else []


def _repetition(document: Document, value: Any, path: At) -> int:
    """An exclude entry's repetition: an integer from 0."""
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise document.error(path, f"exclude repetition must be an integer >= 0, got {value!r}")
    return value


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
