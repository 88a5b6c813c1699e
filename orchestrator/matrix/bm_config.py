"""A Behavior Metrics experiment config (``configs/gazebo/*.yml``) as a drivebench matrix: pure, no processes.

What maps to what (``docs/behavior-metrics.md`` has the whole table):

* ``Behaviors.Robot.BrainPath`` (one or a list): the brains, each a Behavior Metrics brain file; relative paths
  start at the checkout's ``behavior_metrics`` folder (``--bm-root``), else at the config's folder.
* ``Parameters``: every brain's ``config`` option; ``Model`` (one, or a list parallel to ``BrainPath``) its
  ``model`` option; ``ImageTranform`` becomes the matrix's perturbation (drivebench's noise model of the same name,
  applied to every brain's frames) and the brains get ``ImageTranform: ''``, so no frame is perturbed twice.
* ``Simulation.World`` (one or a list of launch files): one part per world, its circuit and world variation from
  :data:`BM_WORLDS`, with ``Experiment.Timeout`` (one, or a list parallel to the worlds) as its
  ``limits.max_sim_seconds``; without a timeout, BM's default: the circuit's reference lap x 1.1.
* ``Experiment.Repetitions``: the matrix's repetitions; ``Experiment.Name``: its name; ``PilotTimeCycle``:
  ``limits.step_s`` (ms to s). BM's F1 camera is 640x480: so is the matrix's.

Keys drivebench cannot honour (the GUI's ``Layout``, ``Dataset`` bags, ``Stats`` output and perfect laps, ROS topics,
``RealTimeUpdateRate``, random spawn points) are listed in :attr:`Conversion.dropped`, each once, and written as
comments at the head of the matrix. Every mistake is a :class:`BMConfigError`, one line naming the key.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from protocol.suggest import did_you_mean

# Behavior Metrics' F1 world launch files (the name without folder and .launch) -> (circuit, world variation).
_BASE: dict[str, str] = {
    "simple_circuit": "simple",
    "many_curves": "many_curves",
    "montmelo": "montmelo",
    "montreal": "montreal",
    "nurburgring": "nurburgring",
}
_VARIANTS: dict[str, dict[str, Any]] = {
    "": {},
    "_line": {},
    "_basic": {},  # the same circuit with a plainer look; drivebench draws one look for both
    "_no_red_line": {"line": "none"},
    "_no_red_line_no_wall": {"line": "none", "walls": "off"},
    "_no_wall": {"walls": "off"},
    "_line_no_wall": {"walls": "off"},
    "_no_sun": {"lighting": "no_sun"},
    "_line_no_sun": {"lighting": "no_sun"},
    "_white_line": {"line": "white"},
    "_white_road": {"road": "white"},
    "_white_road_no_red_line": {"road": "white", "line": "none"},
}
# Which variants exist for which circuit (reference/behavior-metrics.md section 4): only these names are known.
_EXISTING: dict[str, tuple[str, ...]] = {
    "simple_circuit": (
        "",
        "_basic",
        "_no_red_line",
        "_no_red_line_no_wall",
        "_no_sun",
        "_no_wall",
        "_white_line",
        "_white_road",
        "_white_road_no_red_line",
    ),
    "many_curves": ("", "_no_red_line", "_no_red_line_no_wall", "_no_wall"),
    "montmelo": (
        "_line",
        "_line_no_sun",
        "_line_no_wall",
        "_no_red_line",
        "_no_red_line_no_wall",
        "_white_line",
        "_white_road",
        "_white_road_no_red_line",
    ),
    "montreal": ("_line", "_line_no_wall", "_no_red_line", "_no_red_line_no_wall"),
    "nurburgring": ("_line", "_line_no_wall", "_no_red_line", "_no_red_line_no_wall"),
}
BM_WORLDS: dict[str, tuple[str, dict[str, Any]]] = {
    base + variant: (_BASE[base], _VARIANTS[variant]) for base, variants in _EXISTING.items() for variant in variants
}
BM_WORLDS.update({"monaco_line": ("monaco", {}), "extended_simple_circuit": ("extended_simple", {})})  # training only

# BM's reference lap of the explicit brain (s, reference/behavior-metrics.md section 4); default timeout = x 1.1.
REFERENCE_LAP_S = {"simple": 75.0, "many_curves": 151.0, "montmelo": 122.0, "montreal": 248.0, "nurburgring": 88.0}
DEFAULT_TIMEOUT_FACTOR = 1.1
# BM has no brain timeout (its loop paces on wall-clock time); a BM brain's first frame may load a network, and an
# episode's first perturbed frame waits for albumentations' import (1 s here; 13 s was seen under heavy load).
BRAIN_TIMEOUT_S = 60.0
BM_CAMERA = "640x480"  # BM's F1 camera; its brains crop rows of a 480-row image

# Keys drivebench reads; every other key present is reported as dropped, with why.
_WHY_DROPPED = {
    "Behaviors.Layout": "the GUI's frame layout (no GUI: `drivebench view` shows a run in Foxglove)",
    "Behaviors.Dataset": "dataset bags (record with `drivebench matrix --record`, build with `drivebench dataset`)",
    "Behaviors.Stats": "BM's output folder and perfect-lap bags (drivebench scores laps on its own circuits)",
    "Behaviors.Robot.Sensors": "ROS topics (the car has camera_0 and pose3d_0 on the bus)",
    "Behaviors.Robot.Actuators": "ROS topics and MaxV/MaxW (BM never enforces them either)",
    "Behaviors.Robot.Environment": "the simulator is drivebench's",
    "Behaviors.Simulation.RealTimeUpdateRate": "lock-step: simulated time does not depend on wall-clock time",
    "Behaviors.Simulation.RandomSpawnPoint": "BM's unseeded random spawn (variations: {start_m: "
    "[0, 150, 300]} drives every brain from chosen points along the circuit)",
    "Behaviors.Simulation.SpawnPoints": "BM's spawn points, Gazebo poses (a variation start_m=METRES starts an "
    "episode that far along the circuit)",
    "Behaviors.Experiment.UseWorldTimeouts": "a second timeout list (Timeout is what BM's headless loop uses)",
    "Behaviors.Robot.AsyncMode": "lock-step is always in step with the simulator",
}
_READ = {
    "Behaviors.Robot.BrainPath",
    "Behaviors.Robot.Parameters",
    "Behaviors.Robot.PilotTimeCycle",
    "Behaviors.Robot.Type",
    "Behaviors.Simulation.World",
    "Behaviors.Experiment.Name",
    "Behaviors.Experiment.Description",
    "Behaviors.Experiment.Timeout",
    "Behaviors.Experiment.Repetitions",
}


class BMConfigError(ValueError):
    """A Behavior Metrics config drivebench cannot convert: one line naming the key and what is wrong."""


@dataclass
class Conversion:
    """The matrix (as YAML-ready data), the keys left out with why, and notes on what changed meaning."""

    matrix: dict[str, Any]
    dropped: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    def text(self, *, source: str) -> str:
        """The matrix file: a header naming the source, what was dropped and noted, then the YAML."""
        lines = [f"# Converted from the Behavior Metrics config {source} by `drivebench bm import`."]
        lines += [f"# dropped: {line}" for line in self.dropped] + [f"# note: {line}" for line in self.notes]
        return "\n".join(lines) + "\n" + yaml.safe_dump(self.matrix, sort_keys=False, width=120)


def world_of(launch: str) -> tuple[str, str, dict[str, Any]]:
    """(world name, circuit, variation) of a BM launch file or world name; :class:`BMConfigError` if unknown."""
    name = Path(str(launch)).name
    for suffix in (".launch.py", ".launch", ".world"):
        name = name.removesuffix(suffix)
    if name not in BM_WORLDS:
        raise BMConfigError(
            f"Simulation.World: unknown Behavior Metrics world {launch!r} (known: {', '.join(sorted(BM_WORLDS))})"
        )
    circuit, variation = BM_WORLDS[name]
    return name, circuit, dict(variation)


def _listed(value: Any) -> list[Any]:
    return list(value) if isinstance(value, list) else [value]


def _key_paths(data: Any, prefix: str = "") -> list[str]:
    """Dotted paths of every key of nested mappings, mappings' own paths included."""
    if not isinstance(data, dict):
        return []
    paths = []
    for key, value in data.items():
        path = f"{prefix}.{key}" if prefix else str(key)
        paths.append(path)
        paths += _key_paths(value, path)
    return paths


def dropped_keys(data: dict[str, Any]) -> list[str]:
    """Each key of the config drivebench does not honour, once (the outermost), with why."""
    dropped: list[str] = []
    for path in _key_paths(data):
        if path in _READ or any(path.startswith(read + ".") for read in _READ) or path in ("Behaviors",):
            continue
        if path in ("Behaviors.Robot", "Behaviors.Simulation", "Behaviors.Experiment"):
            continue
        if any(path.startswith(done + ".") for done in dropped):
            continue
        dropped.append(path)
    return [f"{path}: {_WHY_DROPPED.get(path, 'not a key drivebench knows')}" for path in dropped]


def _section(data: dict[str, Any], *names: str) -> dict[str, Any]:
    """The mapping at Behaviors.<names...> ({} when absent); :class:`BMConfigError` when it is not a mapping."""
    value: Any = data.get("Behaviors")
    where = "Behaviors"
    for name in names:
        value = value.get(name) if isinstance(value, dict) else None
        where += f".{name}"
    if value is None:
        return {}
    if not isinstance(value, dict):
        raise BMConfigError(f"{where} must be a mapping, got {value!r}")
    return value


def _per_item(value: Any, count: int, *, key: str, of: str) -> list[Any]:
    """A value given once or as a list parallel to ``count`` items of ``of``."""
    values = _listed(value)
    if len(values) == 1:
        return values * count
    if len(values) != count:
        raise BMConfigError(f"{key} has {len(values)} entries for {count} {of} (one, or one per {of[:-1]})")
    return values


def _brain_path(written: Any, *, bm_root: Path | None, config_dir: Path) -> Path:
    """The brain file a BrainPath names: an absolute path as written (so it names the file wherever the matrix
    goes), a relative one found under the checkout or the config's folder, resolved."""
    if not isinstance(written, str) or not written.endswith(".py"):
        raise BMConfigError(f"Robot.BrainPath: {written!r} is not a brain file (path/to/brain.py)")
    path = Path(written).expanduser()
    if path.is_absolute() and path.is_file():
        return path
    tried = [path] if path.is_absolute() else [base / path for base in (bm_root, config_dir) if base is not None]
    for candidate in tried:
        if candidate.is_file():
            return candidate.resolve()
    looked = ", ".join(str(candidate) for candidate in tried)
    hint = "" if bm_root is not None else "; give --bm-root (BrainPath starts at the checkout's behavior_metrics)"
    raise BMConfigError(f"Robot.BrainPath: brain file {written!r} not found (looked for {looked}){hint}")


def _image_transform(option: Any) -> str:
    """BM's ImageTranform option, checked here: one BM does not have would only fail when the matrix plans."""
    from brains.behavior_metrics.interfaces import TRANSFORM_OPTIONS

    if option not in TRANSFORM_OPTIONS:
        known = ", ".join(repr(name) for name in TRANSFORM_OPTIONS)
        raise BMConfigError(
            f"Parameters.ImageTranform {option!r} is not one of Behavior Metrics' options ({known})"
            + did_you_mean(option if not isinstance(option, str) else option.lower(), TRANSFORM_OPTIONS[1:])
        )
    return str(option)


def _brains(
    robot: dict[str, Any], *, bm_root: Path | None, config_dir: Path, out_dir: Path, bm_root_option: str | None
) -> tuple[list[dict[str, Any]], str, list[str]]:
    """(the brains entries, the ImageTranform taken out of their config, notes)."""
    if "BrainPath" not in robot:
        raise BMConfigError("Behaviors.Robot.BrainPath is missing: which brain files to run")
    written = _listed(robot["BrainPath"])
    paths = [_brain_path(p, bm_root=bm_root, config_dir=config_dir) for p in written]
    absolute = {path for path, given in zip(paths, written, strict=True) if Path(str(given)).expanduser().is_absolute()}
    parameters = robot.get("Parameters") or {}
    if not isinstance(parameters, dict):
        raise BMConfigError(f"Robot.Parameters must be a mapping, got {parameters!r}")
    models = (
        _per_item(parameters["Model"], len(paths), key="Parameters.Model", of="brains")
        if "Model" in parameters
        else [None] * len(paths)
    )
    config = {key: value for key, value in parameters.items() if key != "Model"}
    transform = _image_transform(config.get("ImageTranform", "") or "")
    notes = []
    if transform:
        config["ImageTranform"] = ""
        notes.append(
            f"Parameters.ImageTranform {transform!r} is the matrix's perturbation {transform!r} (drivebench's noise "
            "model, applied to the frames every brain sees); the brains get ImageTranform '' so no frame is "
            "perturbed twice"
        )
    brains, labels = [], set()
    for path, model in zip(paths, models, strict=True):
        label, number = path.stem, 2
        while label in labels:
            label, number = f"{path.stem}-{number}", number + 1
        labels.add(label)
        options: dict[str, Any] = {"config": dict(config)}  # a copy each: no YAML anchors in the file
        if model:  # BM passes a model only when one is set ('' is none)
            options["model"] = str(model)
        root_option = bm_root_option or _checkout_of(path, config_dir=config_dir)
        if root_option:
            options["bm_root"] = root_option
        # An absolute BrainPath stays absolute; a relative one is written relative to the matrix file.
        name = str(path) if path in absolute else os.path.relpath(path, out_dir)
        brains.append({"name": name, "label": label, "options": options})
    return brains, str(transform), notes


def _checkout_of(brain: Path, *, config_dir: Path) -> str | None:
    """The checkout a brain file imports from when none was given: BM keeps its configs (``default.yml``) in the
    folder that holds ``brains/`` and ``utils/``, so a config beside ``brains/`` names its own checkout, and the
    matrix starts as BM would (its brains import ``utils.constants`` and ``brains.f1...`` from there)."""
    root = config_dir.resolve()
    if (root / "brains").is_dir() and brain.resolve().is_relative_to(root):
        return str(root)
    return None


def _parts(simulation: dict[str, Any], experiment: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """One part per BM world: its circuit, its world variation and its timeout."""
    if "World" not in simulation:
        raise BMConfigError("Behaviors.Simulation.World is missing: which worlds to run")
    worlds = [world_of(launch) for launch in _listed(simulation["World"])]
    timeouts = (
        _per_item(experiment["Timeout"], len(worlds), key="Experiment.Timeout", of="worlds")
        if "Timeout" in experiment
        else [None] * len(worlds)
    )
    parts: dict[str, dict[str, Any]] = {}
    for (name, circuit, variation), timeout in zip(worlds, timeouts, strict=True):
        if timeout is None:
            if circuit not in REFERENCE_LAP_S:
                raise BMConfigError(f"Experiment.Timeout: none given and world {name!r} has no BM reference lap")
            timeout = round(REFERENCE_LAP_S[circuit] * DEFAULT_TIMEOUT_FACTOR, 1)
        if not isinstance(timeout, int | float) or isinstance(timeout, bool) or timeout <= 0:
            raise BMConfigError(f"Experiment.Timeout: {timeout!r} for world {name!r} is not a number of seconds > 0")
        part_name, number = name, 2
        while part_name in parts:
            part_name, number = f"{name}-{number}", number + 1
        part: dict[str, Any] = {"circuits": [circuit]}
        if variation:
            part["worlds"] = [variation]
        part["limits"] = {"laps": 1, "max_sim_seconds": float(timeout), "brain_timeout_s": BRAIN_TIMEOUT_S}
        parts[part_name] = part
    return parts


def convert_bm_config(
    data: Any, *, config_path: Path, out_path: Path, bm_root: Path | None = None, bm_root_option: str | None = None
) -> Conversion:
    """The matrix of a BM experiment config's data. ``bm_root``: the checkout's folder that holds ``brains/`` (for
    relative BrainPaths); ``bm_root_option``: what the brains get as their ``bm_root`` option (as written)."""
    if not isinstance(data, dict) or not isinstance(data.get("Behaviors"), dict):
        raise BMConfigError("no Behaviors mapping at the top: not a Behavior Metrics config")
    robot, simulation = _section(data, "Robot"), _section(data, "Simulation")
    experiment = _section(data, "Experiment")
    if str(robot.get("Type", "f1")) != "f1":
        raise BMConfigError(f"Robot.Type {robot.get('Type')!r}: drivebench runs Behavior Metrics' F1 car only")
    brains, transform, notes = _brains(
        robot, bm_root=bm_root, config_dir=config_path.parent, out_dir=out_path.parent, bm_root_option=bm_root_option
    )
    name = re.sub(r"[^A-Za-z0-9_.-]+", "_", str(experiment.get("Name") or config_path.stem)).strip("_.-") or "bm"
    matrix: dict[str, Any] = {"name": name, "brains": brains, "camera": BM_CAMERA, "seed": 0}
    if transform:
        matrix["perturbations"] = [transform]
    repetitions = experiment.get("Repetitions", 1)
    if not isinstance(repetitions, int) or isinstance(repetitions, bool) or repetitions < 1:
        raise BMConfigError(f"Experiment.Repetitions must be an integer >= 1, got {repetitions!r}")
    matrix["repetitions"] = repetitions
    cycle_ms = robot.get("PilotTimeCycle", 50)
    if not isinstance(cycle_ms, int | float) or isinstance(cycle_ms, bool) or cycle_ms <= 0:
        raise BMConfigError(f"Robot.PilotTimeCycle must be milliseconds > 0, got {cycle_ms!r}")
    if cycle_ms != 50:
        matrix["limits"] = {"step_s": cycle_ms / 1000.0}
    matrix["parts"] = _parts(simulation, experiment)
    if description := experiment.get("Description"):
        notes.append(f"Experiment.Description: {description}")
    return Conversion(matrix=matrix, dropped=dropped_keys(data), notes=notes)
