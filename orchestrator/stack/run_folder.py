"""A ``drivebench run`` folder's own files (beside ``logs/``): ``config.yaml``, the episode and every brain launched,
written and read back through one struct (:class:`RunConfig`), so that ``drivebench run --config RUN/config.yaml``
runs the same episode again (an attached run writes it too: its brains ran elsewhere, it names the router instead);
``score.json``; and, when the stack failed, ``failure.json`` (or ``recording_failure.json`` for a recording cut
short), machine-readable records of the failure."""

from __future__ import annotations

import contextlib
import json
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import msgspec
import yaml

from brains.registry import UnknownBrainError, require_brain
from circuits import Circuit, CircuitError, load_circuit
from orchestrator.stack.failures import StackFailure
from orchestrator.stack.launcher import BrainLaunch
from protocol import codec
from protocol.deploy import typed_yaml
from protocol.deploy.runtime import UsageError
from protocol.episode_spec import CAMERA_BOUNDS, DIRECTIONS, RENDERERS, SPEC_BOUNDS, EpisodeSpec
from protocol.messages import EpisodeScore
from protocol.suggest import did_you_mean


class LaunchedBrain(msgspec.Struct, kw_only=True, forbid_unknown_fields=True):
    """One brain process a run launched, as its config.yaml lists it: ``brain`` as ``--brain`` takes it, ``name``
    its bus name, ``options`` its ``KEY=VALUE`` overrides (weights last), ``host`` the brain host's own options.
    (A matrix's brain is ``orchestrator.matrix.plan.BrainEntry``; this is what one launch of a brain process is.)"""

    brain: str
    name: str = ""
    options: list[str] = []
    host: list[str] = []

    @classmethod
    def of(cls, launch: BrainLaunch) -> LaunchedBrain:
        return cls(brain=launch.brain, name=launch.bus_name, options=list(launch.options), host=list(launch.host))

    def launch(self) -> BrainLaunch:
        return BrainLaunch(self.brain, name=self.name, options=tuple(self.options), host=tuple(self.host))


class RunConfig(msgspec.Struct, kw_only=True, forbid_unknown_fields=True, omit_defaults=True):
    """A run folder's config.yaml, as ``drivebench run`` writes it: the episode and every brain launched (the run
    id is for reading: a run of the file gets its own). An attached run (``--attach``) launched no brain: it names
    the ``router`` it joined instead, and says it was ``attached``."""

    run_id: Any = None
    episode: EpisodeSpec
    brains: list[LaunchedBrain] = []
    router: str | None = None
    attached: bool = False


def read_run_config(path: Path) -> RunConfig:
    """A run folder's config.yaml (``--config RUN/config.yaml``), checked as the options would be: every mistake of
    the file at once, one line each with its line number (UsageError)."""
    try:
        document = typed_yaml.compose(path.read_text(), source=f"--config {path}")
        data = _note_value_mistakes(document)
        config = document.attempt(typed_yaml.convert, data, RunConfig, document=document, what="the run config")
        if config is not None:
            _check_run_config(config, document)
        document.raise_noted()
    except typed_yaml.FileError as error:
        raise UsageError(str(error)) from None
    assert config is not None  # a config that did not convert noted why, and raise_noted raised it
    return config


def write_run_config(run_dir: Path, config: RunConfig) -> Path:
    """``<run_dir>/config.yaml``: ``config`` as :func:`read_run_config` reads it back."""
    path = run_dir / "config.yaml"
    path.write_text(yaml.safe_dump(msgspec.to_builtins(config), sort_keys=False))
    return path


def _note_value_mistakes(document: typed_yaml.Document) -> Any:
    """Note what the types would not say at its own line: every unknown key, however deep (an episode spec reads
    newer senders, so msgspec ignores its unknown keys: ``lpas: 5`` would run one lap), and each value out of its
    range or choices (the spec checks them after decoding, the first only, at the episode's line). Returns the
    data without them, for the type check to find the rest."""
    faults = typed_yaml.unknown_keys(document.data, RunConfig, what="the run config")
    episode = document.data.get("episode") if isinstance(document.data, dict) else None
    faults += typed_yaml.bound_faults(episode, SPEC_BOUNDS, path=("episode",))
    camera = episode.get("camera") if isinstance(episode, dict) else None
    faults += typed_yaml.bound_faults(camera, CAMERA_BOUNDS, path=("episode", "camera"))
    for name, choices in (("direction", DIRECTIONS), ("renderer", RENDERERS)):
        value = episode.get(name, choices[0]) if isinstance(episode, dict) else choices[0]
        if isinstance(value, str) and value not in choices:
            message = f"episode.{name} must be one of {', '.join(choices)}, got {value!r}"
            faults.append(typed_yaml.Fault(("episode", name), message + did_you_mean(value, choices)))
    for fault in faults:
        document.note(document.error(fault.path, fault.message, at_key=fault.at_key))
    return typed_yaml.without(document.data, [fault.path for fault in faults])


def _check_run_config(config: RunConfig, document: typed_yaml.Document) -> None:
    """What the types do not say, every mistake noted before one error: the circuit exists and the start is on it,
    a brain is named, and each brain is one drivebench can load."""
    circuit = document.attempt(_config_circuit, config.episode, document)
    if circuit is not None:
        try:
            circuit.check_start_m(config.episode.start_m)
        except CircuitError as error:
            document.note(document.error(("episode", "start_m"), str(error)))
    if not config.brains:
        # brains has a default only because an attached run's config names none; a file without the key is a mistake
        absent = not isinstance(document.data, dict) or "brains" not in document.data
        message = "the run config is missing 'brains'" if absent else "the run config names no brain"
        document.note(document.error(() if absent else ("brains",), message))
    for index, entry in enumerate(config.brains):
        try:
            require_brain(entry.brain)
        except UnknownBrainError as error:
            document.note(document.error(("brains", index, "brain"), str(error)))
    document.raise_noted()


def _config_circuit(episode: EpisodeSpec, document: typed_yaml.Document) -> Circuit:
    try:
        return load_circuit(episode.circuit)
    except CircuitError as error:
        raise document.error(("episode", "circuit"), str(error)) from None


def write_score(run_dir: Path, score: EpisodeScore) -> Path:
    path = run_dir / "score.json"
    path.write_text(codec.to_json(score, indent=2) + "\n")
    return path


def write_recording_failure(run_dir: Path, failure: StackFailure, *, run_id: str) -> Path:
    """``recording_failure.json``: the recorder died, the episode was scored, its recording is incomplete."""
    path = run_dir / "recording_failure.json"
    path.write_text(json.dumps(failure.record(run_id=run_id), indent=2) + "\n")
    return path


@contextlib.contextmanager
def recorded_failure(run_dir: Path, *, run_id: str, on_record: Callable[[dict], None] | None = None) -> Iterator[None]:
    """A failed episode leaves a machine-readable record: ``failure.json`` in the run folder, also handed to
    ``on_record`` (``--json`` prints it on stdout); the StackFailure goes on up."""
    try:
        yield
    except StackFailure as failure:
        record = failure.record(run_id=run_id)
        (run_dir / "failure.json").write_text(json.dumps(record, indent=2) + "\n")
        if on_record is not None:
            on_record(record)
        raise
