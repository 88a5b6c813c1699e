"""A matrix as planned: its brains and its episodes, each with the full spec it will run (``orchestrator.matrix.load``
reads them from a matrix file). Pure data, no I/O."""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgspec

from protocol.deploy.typed_yaml import FileError
from protocol.episode_spec import EpisodeSpec

DEFAULT_VARIATION = "default"
NO_PERTURBATION = "none"


class MatrixError(FileError):
    """A mistake in a matrix file. ``str(error)`` is one line: ``FILE:LINE: what is wrong (what is allowed)``
    (``FILE: ...`` when the file itself cannot be read). ``source``, ``line`` (1-based, or None) and ``message``
    are kept as attributes."""


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
    group: the brain as compared, when this entry is one training run of it (the label written in the matrix
        file; the entry's own label is ``<group>-s<seed>``); "" otherwise.
    training_seed: the seed of that training run, read from its checkpoint; None otherwise.
    """

    label: str
    brain: str
    weights: Path | None = None
    options: tuple[tuple[str, Any], ...] = ()
    group: str = ""
    training_seed: int | None = None

    @property
    def compared_as(self) -> str:
        """The name reports compare this brain under: its group for a training run, else its label."""
        return self.group or self.label

    def launch_options(self) -> tuple[str, ...]:
        """Constructor options as ``key=<JSON value>`` overrides for the brain host (``--set options.KEY=VALUE``),
        weights last as ``weights="<absolute path>"``. Every value reads back as the same value with YAML."""
        texts = tuple(f"{key}={yaml_json(value)}" for key, value in self.options)
        if self.weights is not None:
            texts += (f"weights={json.dumps(str(self.weights))}",)
        return texts

    def to_dict(self) -> dict[str, Any]:
        """JSON-able form (:class:`BrainRecord`'s): ``{"label", "brain", "weights" (absolute path or None),
        "options" (mapping)}``, plus ``"group"`` and ``"training_seed"`` for a training run (absent otherwise, so
        earlier results read alike)."""
        return msgspec.to_builtins(BrainRecord.of(self))

    @classmethod
    def from_dict(cls, entry: dict[str, Any], *, label: str = "") -> BrainEntry:
        """The entry :meth:`to_dict` wrote (results, an episode's config.yaml) read back as the same entry. ``label``:
        the episode's brain label, for an entry an older drivebench wrote without one (results files stay
        readable)."""
        weights = entry.get("weights")
        return cls(
            label=entry.get("label", label),
            brain=entry.get("brain", label),
            weights=Path(weights) if weights else None,
            options=tuple((entry.get("options") or {}).items()),
            group=entry.get("group", ""),
            training_seed=entry.get("training_seed"),
        )


class BrainRecord(msgspec.Struct, kw_only=True, forbid_unknown_fields=True, omit_defaults=True):
    """A :class:`BrainEntry` as files record it (a results row, an episode's config.yaml): ``weights`` as an
    absolute path or None (written either way), ``options`` as a mapping, ``group`` and ``training_seed`` for a
    training run only (absent otherwise, so that earlier files read alike)."""

    label: str
    brain: str
    weights: str | None
    options: dict[str, Any]
    group: str | None = None
    training_seed: int | None = None

    @classmethod
    def of(cls, entry: BrainEntry) -> BrainRecord:
        trained = entry.training_seed is not None
        return cls(
            label=entry.label,
            brain=entry.brain,
            weights=None if entry.weights is None else str(entry.weights),
            options=dict(entry.options),
            group=entry.group if trained else None,
            training_seed=entry.training_seed,
        )

    def entry(self) -> BrainEntry:
        return BrainEntry.from_dict(msgspec.to_builtins(self))


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


class EpisodeConfig(msgspec.Struct, kw_only=True, forbid_unknown_fields=True):
    """A matrix episode's ``episodes/<index>/config.yaml``: the stack's ``run_id``, the ``matrix``'s name, the
    episode's ``key``, its full spec (``episode``), and every brain it launched (its own, then the matrix's shadows),
    written and read back through this struct (``orchestrator.matrix.executor``: ``write_episode_config``,
    ``read_episode_config``)."""

    run_id: str
    matrix: str
    key: str
    episode: EpisodeSpec
    brains: list[BrainRecord]

    @classmethod
    def of(cls, episode: PlannedEpisode, *, matrix: Matrix, run_id: str) -> EpisodeConfig:
        brains = [BrainRecord.of(entry) for entry in (episode.brain, *matrix.shadows)]
        return cls(run_id=run_id, matrix=matrix.name, key=episode.key, episode=episode.spec, brains=brains)


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


def yaml_json(value: Any) -> str:
    """JSON text that PyYAML reads back as the same value: JSON's ``1e-07`` is a string to YAML 1.1, which wants
    a dot in the mantissa (``1.0e-07``)."""
    if isinstance(value, float):
        text = json.dumps(value)
        mantissa, e, exponent = text.partition("e")
        return f"{mantissa}.0e{exponent}" if e and "." not in mantissa else text
    if isinstance(value, list):
        return "[" + ", ".join(yaml_json(item) for item in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{json.dumps(str(key))}: {yaml_json(item)}" for key, item in value.items()) + "}"
    return json.dumps(value)


def smoke_form(
    matrix: Matrix,
    *,
    brains: Iterable[str] | None = None,
    cells_per_part: int = 2,
    sim_seconds: float = 4.0,
    camera_wh: tuple[int, int] = (160, 120),
) -> Matrix:
    """``matrix`` cut to seconds (``--smoke``, what CI runs): the brains labelled in ``brains`` (default: all), the
    first ``cells_per_part`` conditions (world x perturbation) on the first ``cells_per_part`` circuits of every part,
    repetition 0, ``sim_seconds`` of simulated time on a small camera (``camera_wh``; a Behavior Metrics brain file
    keeps its episode's camera, as BM's brains crop fixed rows of BM's 640x480 frame). Keys stay the full matrix's, so
    every kept episode still lands in its report cell."""
    wanted = None if brains is None else set(brains)
    kept: list[PlannedEpisode] = []
    conditions_by_part: dict[str, list] = {}
    circuits_by_part: dict[str, list] = {}
    for episode in matrix.episodes:
        if (wanted is not None and episode.brain.label not in wanted) or episode.repetition != 0:
            continue
        if not _kept(circuits_by_part.setdefault(episode.part, []), episode.circuit, cells_per_part):
            continue
        conditions = conditions_by_part.setdefault(episode.part, [])
        if not _kept(conditions, (episode.variation, episode.perturbation), cells_per_part):
            continue
        camera = episode.spec.camera
        if not _is_bm_brain(episode.brain):  # BM's brains crop fixed rows of BM's frame: a small one crops nothing
            camera = msgspec.structs.replace(camera, width_px=camera_wh[0], height_px=camera_wh[1])
        spec = msgspec.structs.replace(episode.spec, max_sim_seconds=sim_seconds, camera=camera)
        kept.append(dataclasses.replace(episode, index=len(kept), spec=spec))
    return dataclasses.replace(
        matrix,
        name=f"{matrix.name}-smoke",
        episodes=tuple(kept),
        brains=tuple(b for b in matrix.brains if wanted is None or b.label in wanted),
    )


def _is_bm_brain(entry: BrainEntry) -> bool:
    from brains.registry import is_behavior_metrics_brain

    return is_behavior_metrics_brain(entry.brain)


def _kept(seen: list, item: Any, limit: int) -> bool:
    """Whether ``item`` is among the first ``limit`` distinct items met (recording it when there is room)."""
    if item in seen:
        return True
    if len(seen) >= limit:
        return False
    seen.append(item)
    return True


def with_renderer(matrix: Matrix, choose: Callable[[str], str]) -> Matrix:
    """``matrix`` with each episode's renderer replaced by ``choose(renderer)`` (the command line's choice, or
    "auto" resolved where the stacks run)."""
    episodes = tuple(
        dataclasses.replace(episode, spec=msgspec.structs.replace(episode.spec, renderer=choose(episode.spec.renderer)))
        for episode in matrix.episodes
    )
    return dataclasses.replace(matrix, episodes=episodes)


def plan_table(matrix: Matrix) -> str:
    """The planned episodes, one per line (``drivebench matrix FILE --plan``)."""
    lines = [f"{matrix.name}: {len(matrix.episodes)} episode(s)"]
    lines += [f"{episode.index:4d}  {episode.key}  seed {episode.spec.seed}" for episode in matrix.episodes]
    return "\n".join(lines)


def plan_json(matrix: Matrix) -> str:
    """The planned episodes as one JSON array (``drivebench matrix FILE --plan --json``)."""
    episodes = [
        {"index": episode.index, "key": episode.key, "spec": msgspec.to_builtins(episode.spec)}
        for episode in matrix.episodes
    ]
    return json.dumps(episodes, indent=2)
