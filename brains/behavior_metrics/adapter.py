"""Behavior Metrics brain files, run unchanged: ``--brain path/to/brain.py`` (or ``--brain behavior_metrics
--brain-option file=path/to/brain.py``).

Written from the interface's documented behaviour (``reference/behavior-metrics.md``), not from its code. A Behavior
Metrics brain file defines a class ``Brain`` whose ``execute()`` is called once per camera frame. The adapter builds
it as Behavior Metrics builds every Gazebo brain, with keywords::

    Brain(sensors, actuators, handler=handler, config=config)                # no model set
    Brain(sensors, actuators, model=model, handler=handler, config=config)   # a model set

``config`` is always given, as BM gives its robot's ``Parameters`` (less ``Model``): BM's usual keys with BM's
values (:data:`BM_DEFAULT_CONFIG`), then the ``Parameters`` of a BM config file (option ``config_file``), then the
option ``config`` (``--brain-option config={GPU: false}``), each over the one before. What the brain sees is in
``brains.behavior_metrics.interfaces`` (an RGB camera, the pose, the motors, the handler with ``transform_image``).

Per frame the adapter puts the image (and, for a file that asks for ``get_pose3d``, the simulator's pose of that
frame) behind the sensors, calls ``execute()``, and answers with whatever the motors were last told. ``reset`` builds
a new ``Brain`` (BM loads the brain anew for every run), and seeds ``random``, numpy's global generator and the
handler's perturbations from the episode's seed.

Mistakes are one line naming the file: an import that needs a BM checkout (option ``bm_root``,
``brains.behavior_metrics.checkout``), a constructor that raises (a config key it needs and does not get), an
unknown ``ImageTranform``; all found by :meth:`BehaviorMetricsBrain.preflight` before a stack starts. What only
``execute()`` shows ends the brain host with one last line naming the file, the line and the error.
"""

from __future__ import annotations

import inspect
import random
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from brains.base import Action, Observation
from brains.behavior_metrics.checkout import line_in, load_brain_file, where_in
from brains.behavior_metrics.interfaces import (
    TRANSFORM_OPTIONS,
    Actuators,
    Camera,
    Handler,
    Image,
    Motors,
    Pose3d,
    Pose3dSensor,
    Sensors,
)
from brains.registry import BrainOptionsError
from protocol.suggest import did_you_mean

# The Parameters Behavior Metrics' shipped F1 configs set, with their usual values: what a brain indexes without a
# default (``config['GPU']``) is there. GPU True as in BM's configs: brains fall back to the CPU without CUDA.
BM_DEFAULT_CONFIG: dict[str, Any] = {
    "ImageTranform": "",  # (sic) BM's spelling
    "ImageCropped": True,
    "ImageSize": [100, 50],
    "ImageNormalized": True,
    "PredictionsNormalized": True,
    "GPU": True,
    "UseOptimized": False,
}


class BrainExecuteError(RuntimeError):
    """A Behavior Metrics brain's ``execute()`` raised: the brain host ends with this one line as its last."""


def read_bm_parameters(config_file: str | Path) -> tuple[dict[str, Any], Any]:
    """(the robot's Parameters less Model, Model) of a Behavior Metrics config file; one-line errors."""
    path = Path(config_file).expanduser()
    try:
        data = yaml.safe_load(path.read_text())
    except OSError as error:
        raise BrainOptionsError(f"config_file {str(path)!r}: {error.strerror or error}") from None
    except yaml.YAMLError as error:
        raise BrainOptionsError(f"config_file {str(path)!r} is not YAML: {str(error).splitlines()[0]}") from None
    robot = data.get("Behaviors", {}).get("Robot") if isinstance(data, dict) else None
    if not isinstance(robot, dict):
        raise BrainOptionsError(f"config_file {str(path)!r} has no Behaviors.Robot: not a Behavior Metrics config")
    parameters = robot.get("Parameters") or {}
    if not isinstance(parameters, dict):
        raise BrainOptionsError(f"config_file {str(path)!r}: Behaviors.Robot.Parameters must be a mapping")
    config = {key: value for key, value in parameters.items() if key != "Model"}
    return config, parameters.get("Model")


def brain_config(*, config: dict[str, Any] | None, config_file: str | None) -> tuple[dict[str, Any], Any]:
    """(the ``config`` a brain gets, the model a config file names): BM's defaults < the file's < ``config``."""
    merged, model = dict(BM_DEFAULT_CONFIG), None
    if config_file:
        from_file, model = read_bm_parameters(config_file)
        merged.update(from_file)
    if config is not None and not isinstance(config, dict):
        raise BrainOptionsError(f"config must be a mapping of Behavior Metrics parameters, got {config!r}")
    merged.update(config or {})
    option = merged.get("ImageTranform")
    if option not in TRANSFORM_OPTIONS:
        known = ", ".join(repr(name) for name in TRANSFORM_OPTIONS)
        raise BrainOptionsError(
            f"unknown ImageTranform {option!r} (Behavior Metrics knows {known})"
            + did_you_mean(option.lower() if isinstance(option, str) else option, TRANSFORM_OPTIONS[1:])
        )
    return merged, model


class BehaviorMetricsBrain:
    """A drivebench brain serving the ``Brain`` class of a Behavior Metrics brain file.

    file: the brain file. model: passed as ``model=`` (BM: the weights' file name); a config file's single ``Model``
    when not given. config: Behavior Metrics parameters over BM's defaults and the config file's. config_file: a
    BM experiment config (YAML) whose ``Behaviors.Robot.Parameters`` the brain gets. bm_root: a BehaviorMetrics
    checkout for the file's imports of BM's modules (default ``$DRIVEBENCH_BM_ROOT``).
    """

    def __init__(
        self,
        *,
        file: str,
        model: str | None = None,
        config: dict[str, Any] | None = None,
        config_file: str | None = None,
        bm_root: str | None = None,
    ):
        self.file = str(file)
        self._path = Path(file).expanduser().resolve()
        try:
            self.config, file_model = brain_config(config=config, config_file=config_file)
        except BrainOptionsError as error:
            raise BrainOptionsError(f"Behavior Metrics brain {self.file!r}: {error}") from None
        self._model = model if model is not None else (file_model if isinstance(file_model, str) else None)
        module = load_brain_file(file, bm_root=bm_root)
        self._brain_class = module.Brain
        # A file that reads the pose makes its host wait for the simulator's pose of every frame; others do not.
        self.needs_ground_truth = "get_pose3d" in self._path.read_text(errors="replace")
        self.camera, self.pose3d, self.motors = Camera(), Pose3dSensor(), Motors()
        self.sensors, self.actuators = Sensors(self.camera, self.pose3d), Actuators(self.motors)
        self.handler = Handler(self.sensors, self.actuators, perturb=self._perturb)
        self._perturbations: dict[str, Any] = {}
        self._seed = 0
        self._brain: Any = None
        self.reset(seed=0)

    @classmethod
    def preflight(cls, **options: Any) -> None:
        """Everything a stack would find out at start-up, found now: the file imports (with its checkout), the
        config is complete for its constructor, the ImageTranform is known. Raises :class:`BrainOptionsError`."""
        cls(**options)

    @property
    def debug_images(self) -> dict[str, np.ndarray]:
        """The brain's latest ``handler.update_frame`` image of each frame id."""
        return self.handler.debug_images

    def _keywords(self) -> dict[str, Any]:
        """What Behavior Metrics passes besides sensors and actuators: ``model`` only when one is set."""
        keywords: dict[str, Any] = {"handler": self.handler, "config": self.config}
        return {"model": self._model, **keywords} if self._model else keywords  # BM: `if model:`

    def _new_brain(self) -> Any:
        keywords = self._keywords()
        call = f"Brain(sensors, actuators, {', '.join(f'{key}=...' for key in keywords)})"
        try:
            inspect.signature(self._brain_class).bind(self.sensors, self.actuators, **keywords)
        except TypeError as error:
            raise BrainOptionsError(
                f"Behavior Metrics brain {self.file!r}: its constructor does not take {call} as Behavior Metrics "
                f"calls it: {error}"
            ) from None
        try:
            return self._brain_class(self.sensors, self.actuators, **keywords)
        except Exception as error:  # the user's constructor: whatever it raises, say where
            cause = f"missing config key {error}" if isinstance(error, KeyError) else f"{type(error).__name__}: {error}"
            raise BrainOptionsError(
                f"Behavior Metrics brain {self.file!r}: {call} failed{where_in(self._path, error)}: {cause}"
            ) from None

    def _perturb(self, image: np.ndarray, option: str) -> np.ndarray:
        """``handler.transform_image``: BM's perturbation ``option`` by drivebench's seeded noise model of it."""
        if option not in TRANSFORM_OPTIONS:
            known = ", ".join(repr(name) for name in TRANSFORM_OPTIONS)
            raise ValueError(f"transform_image: unknown option {option!r} (Behavior Metrics knows {known})")
        if option == "":
            return image
        if option not in self._perturbations:
            from protocol.variations import noise_stage
            from services.noise.models import make_model

            model = make_model(noise_stage(option))
            model.reset(seed=(self._seed, TRANSFORM_OPTIONS.index(option)))
            self._perturbations[option] = model
        return self._perturbations[option].apply(np.ascontiguousarray(image, dtype=np.uint8))

    def reset(self, *, seed: int) -> None:
        """A fresh ``Brain`` and still motors; ``random``, numpy's global generator and the perturbations seeded."""
        self._seed = seed
        random.seed(seed)
        np.random.seed(seed % 2**32)
        for option, model in self._perturbations.items():
            model.reset(seed=(seed, TRANSFORM_OPTIONS.index(option)))
        self.motors.sendVW(0.0, 0.0)
        self.handler.debug_images.clear()
        self.handler.reported_pose = None
        self.camera.image, self.pose3d.pose = Image(), Pose3d()
        self._brain = self._new_brain()

    def act(self, observation: Observation) -> Action:
        stamp_s = observation.stamp_ns / 1e9
        # A copy, writable: BM's brains draw on their frames, and the host's image is a read-only view.
        self.camera.image = Image(np.array(observation.image_rgb, dtype=np.uint8, copy=True), stamp_s=stamp_s)
        truth = observation.ground_truth
        if truth is not None:
            self.pose3d.pose = Pose3d(x=truth.x_m, y=truth.y_m, yaw=truth.yaw_rad, stamp_s=stamp_s)
        counts = {name: len(_own_list(self._brain, name)) for name in ("inference_times", "suddenness_distance")}
        try:
            self._brain.execute()
        except Exception as error:  # the user's code: one line naming the file, the line and the error
            # Short (the file's name, not its path): a failure quotes the host's last log line, cut to 200 chars.
            line = line_in(self._path, error)
            where = f"{self._path.name}:{line}" if line else self._path.name
            raise BrainExecuteError(
                f"Behavior Metrics brain {where}: execute() raised {type(error).__name__}: {error}"
            ) from error
        return Action(
            speed_mps=self.motors.v_mps,
            yaw_rate_radps=self.motors.w_radps,
            model_inference_s=_appended(self._brain, "inference_times", counts["inference_times"]),
            suddenness=_appended(self._brain, "suddenness_distance", counts["suddenness_distance"]),
        )

    @property
    def gpu_inference(self) -> bool:
        """BM's ``gpu_inference``: what the brain says of itself (BM's neural brains set it), False when silent."""
        return bool(getattr(getattr(self, "_brain", None), "gpu_inference", False))


def _own_list(brain: Any, name: str) -> list:
    """A list BM's pilot reads from the brain after a run (``inference_times``, ``suddenness_distance``), or []."""
    value = getattr(brain, name, None)
    return value if isinstance(value, list) else []


def _appended(brain: Any, name: str, before: int) -> float | None:
    """The value this step appended to the brain's own list ``name``, None when it appended none (a brain that
    keeps no such list, or skipped the step, as BM's do for their first frames)."""
    values = _own_list(brain, name)
    if len(values) <= before:
        return None
    try:
        return float(values[-1])
    except (TypeError, ValueError):
        return None
