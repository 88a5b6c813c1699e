"""Behavior Metrics brain files, run unchanged: ``--brain path/to/brain.py`` (or ``--brain behavior_metrics
--brain-option file=path/to/brain.py``).

Written from the interface's documented behaviour (``reference/behavior-metrics.md``), not from its code. A Behavior
Metrics brain file defines a class ``Brain``, built as ``Brain(sensors, actuators, handler=None)`` (newer ones also
take ``model`` and ``config``), whose ``execute()`` is called once per camera frame. Inside it reads the frame with
``sensors.get_camera('camera_0').getImage().data`` (a BGR numpy array), commands the car with
``actuators.get_motor('motors_0').sendV(v)`` and ``.sendW(w)`` (m/s and rad/s, positive w turns left, as ROS'
``cmd_vel``), and may hand debug images to the GUI with ``handler.update_frame(frame_id, image)``.

The adapter plays Behavior Metrics' part: per frame it puts the image behind the camera, calls ``execute()``, and
answers with whatever the motors were last told (motors keep their last command, as on the ROS topic). ``reset``
builds a new ``Brain`` so nothing leaks from one episode to the next, and seeds ``random`` and numpy's global
generator, which such files use. Debug images are kept only as the latest one per frame id (``debug_images``): no
viewer reads them yet, and keeping one each is cheap.
"""

from __future__ import annotations

import importlib.util
import inspect
import random
import sys
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

from brains.base import Action, Observation
from brains.registry import BrainOptionsError


class Image:
    """What ``getImage()`` returns in Behavior Metrics: the pixels in ``data`` (H x W x 3 uint8, **BGR**)."""

    def __init__(self, data: np.ndarray, *, stamp_s: float):
        self.data = data
        self.height, self.width = data.shape[:2]
        self.format = "BGR8"
        self.timeStamp = stamp_s  # noqa: N815 (Behavior Metrics' spelling)


class Camera:
    """``sensors.get_camera(name)``: the current frame behind ``getImage()``."""

    def __init__(self) -> None:
        self.image: Image | None = None

    def getImage(self) -> Image | None:  # noqa: N802 (Behavior Metrics' spelling)
        return self.image


class Motors:
    """``actuators.get_motor(name)``: remembers the last linear (m/s) and angular (rad/s) speed it was sent."""

    def __init__(self) -> None:
        self.v_mps = 0.0
        self.w_radps = 0.0

    def sendV(self, v: float) -> None:  # noqa: N802
        self.v_mps = float(v)

    def sendW(self, w: float) -> None:  # noqa: N802
        self.w_radps = float(w)

    def sendVW(self, v: float, w: float) -> None:  # noqa: N802
        self.sendV(v)
        self.sendW(w)


class Sensors:
    """``sensors``: every camera name answers with the one car camera (BM's F1 has one, ``camera_0``)."""

    def __init__(self, camera: Camera):
        self.camera = camera

    def get_camera(self, name: str = "camera_0") -> Camera:
        return self.camera


class Actuators:
    """``actuators``: every motor name drives the one car (BM's F1 has one, ``motors_0``)."""

    def __init__(self, motors: Motors):
        self.motors = motors

    def get_motor(self, name: str = "motors_0") -> Motors:
        return self.motors


class Handler:
    """The GUI handler: ``update_frame(frame_id, image)`` keeps the latest debug image of each frame id."""

    def __init__(self) -> None:
        self.debug_images: dict[str, np.ndarray] = {}

    def update_frame(self, frame_id: str, image: np.ndarray, *args: Any, **kwargs: Any) -> None:
        self.debug_images[str(frame_id)] = image

    def update_pose3d(self, *args: Any, **kwargs: Any) -> None:
        """Some brains report poses to the GUI too: nothing here draws them."""


def load_brain_file(path: str | Path) -> ModuleType:
    """Import a Behavior Metrics brain file as a module of its own; one-line :class:`BrainOptionsError` if unusable."""
    path = Path(path).expanduser().resolve()
    if not path.is_file():
        raise BrainOptionsError(f"Behavior Metrics brain file {str(path)!r} not found")
    name = f"behavior_metrics_brain_{abs(hash(str(path))):x}"
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    try:
        spec.loader.exec_module(module)
    except Exception as error:  # the user's file: whatever it raises, say where
        del sys.modules[name]
        raise BrainOptionsError(
            f"Behavior Metrics brain file {str(path)!r} failed to import: {type(error).__name__}: {error}"
        ) from None
    if not inspect.isclass(getattr(module, "Brain", None)):
        raise BrainOptionsError(f"Behavior Metrics brain file {str(path)!r} defines no class Brain")
    return module


class BehaviorMetricsBrain:
    """A drivebench brain serving the ``Brain`` class of a Behavior Metrics brain file.

    file: the brain file. model: passed as the constructor's ``model`` (newer brains: their weights' path).
    config: passed as ``config`` (a dict) to brains that take one.
    """

    def __init__(self, *, file: str, model: str | None = None, config: dict[str, Any] | None = None):
        self.file = str(file)
        self._brain_class = load_brain_file(file).Brain
        self._model, self._config = model, config
        self.camera, self.motors, self.handler = Camera(), Motors(), Handler()
        self._brain: Any = None
        self.reset(seed=0)

    @property
    def debug_images(self) -> dict[str, np.ndarray]:
        """The brain's latest ``handler.update_frame`` image of each frame id."""
        return self.handler.debug_images

    def _new_brain(self) -> Any:
        accepted = inspect.signature(self._brain_class).parameters
        extra = {
            key: value
            for key, value in (("model", self._model), ("config", self._config))
            if key in accepted or any(p.kind is p.VAR_KEYWORD for p in accepted.values())
        }
        sensors, actuators = Sensors(self.camera), Actuators(self.motors)
        try:
            return self._brain_class(sensors, actuators, self.handler, **extra)
        except Exception as error:
            raise BrainOptionsError(
                f"Behavior Metrics brain {self.file!r}: Brain(sensors, actuators, handler"
                f"{''.join(', ' + k for k in extra)}) failed: {type(error).__name__}: "
                f"{error}"
            ) from None

    def reset(self, *, seed: int) -> None:
        """A fresh ``Brain`` and still motors; ``random`` and numpy's global generator seeded from ``seed``."""
        random.seed(seed)
        np.random.seed(seed % 2**32)
        self.motors.sendVW(0.0, 0.0)
        self.handler.debug_images.clear()
        self._brain = self._new_brain()

    def act(self, observation: Observation) -> Action:
        bgr = np.ascontiguousarray(observation.image_rgb[..., ::-1])  # a copy: the file may draw on it
        self.camera.image = Image(bgr, stamp_s=observation.stamp_ns / 1e9)
        self._brain.execute()
        return Action(speed_mps=self.motors.v_mps, yaw_rate_radps=self.motors.w_radps)
