"""What a Behavior Metrics brain touches, with Behavior Metrics' names and conventions, over drivebench's frames.

Written from the interface's documented behaviour (``reference/behavior-metrics.md``), not from its code:

* ``sensors.get_camera('camera_0').getImage()``: an :class:`Image` whose ``data`` is H x W x 3 uint8 **RGB** (BM's
  camera converts every ROS frame to ``rgb8``); before the first frame a 3 x 3 black image, as in BM.
* ``sensors.get_pose3d('pose3d_0').getPose3d()``: a :class:`Pose3d` (x, y, z in metres, yaw, pitch, roll in radians,
  ``q`` = [w, x, y, z], ``timeStamp`` in seconds), from the simulator's ground-truth pose of the frame, the way BM
  reads ``/F1ROS/odom``. drivebench's car drives on a plane: z, pitch and roll are 0.
* ``sensors.get_laser(...)``: BM's F1 has no laser; here it raises :class:`NoSuchSensor` naming what there is.
* ``actuators.get_motor('motors_0')``: ``sendV`` (m/s), ``sendW`` (rad/s, positive turns left), ``sendVW``; the motors
  keep the last value sent, as BM's publisher republishes the latest Twist.
* the handler: ``update_frame(frame_id, image)``, ``update_pose3d(pose)``, ``get_image(camera)``,
  ``get_motors(name)``, ``transform_image(image, option)`` (BM's image perturbations, see
  ``services.noise.models``), ``get_laser_data`` (no laser: :class:`NoSuchSensor`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

# Behavior Metrics' names for its ImageTranform options; '' leaves the image as it is.
TRANSFORM_OPTIONS: tuple[str, ...] = ("", "rain", "night", "shadow", "snow", "fog", "sunflare", "daytime", "affine")


class NoSuchSensor(LookupError):
    """A brain asked for a sensor drivebench's F1 car does not have (one line: what it asked for, what there is)."""


class Image:
    """What ``getImage()`` returns in Behavior Metrics: ``data`` (H x W x 3 uint8 RGB), its size, format and stamp."""

    def __init__(self, data: np.ndarray | None = None, *, stamp_s: float = 0.0):
        self.data = np.zeros((3, 3, 3), np.uint8) if data is None else data
        self.height, self.width = self.data.shape[:2]
        self.format = "RGB8"
        self.timeStamp = stamp_s  # Behavior Metrics' spelling


class Camera:
    """``sensors.get_camera(name)``: the current frame behind ``getImage()``."""

    def __init__(self) -> None:
        self.image = Image()

    def getImage(self) -> Image:  # Behavior Metrics' spelling
        return self.image


class Pose3d:
    """Behavior Metrics' pose: position (m), yaw, pitch and roll (rad), quaternion ``q`` = [w, x, y, z], stamp (s)."""

    def __init__(self, *, x: float = 0.0, y: float = 0.0, yaw: float = 0.0, stamp_s: float = 0.0):
        self.x, self.y, self.z, self.h = float(x), float(y), 0.0, 1
        self.yaw, self.pitch, self.roll = float(yaw), 0.0, 0.0
        self.q = [math.cos(yaw / 2.0), 0.0, 0.0, math.sin(yaw / 2.0)]
        self.timeStamp = stamp_s

    def __repr__(self) -> str:
        return f"Pose3d(x={self.x:.3f}, y={self.y:.3f}, yaw={self.yaw:.3f}, timeStamp={self.timeStamp:.3f})"


class Pose3dSensor:
    """``sensors.get_pose3d(name)``: the latest pose behind ``getPose3d()`` (BM's ListenerPose3d)."""

    def __init__(self) -> None:
        self.pose = Pose3d()

    def getPose3d(self) -> Pose3d:
        return self.pose


class Motors:
    """``actuators.get_motor(name)``: remembers the last linear (m/s) and angular (rad/s) speed it was sent."""

    def __init__(self) -> None:
        self.v_mps = 0.0
        self.w_radps = 0.0

    def sendV(self, v: float) -> None:
        self.v_mps = float(v)

    def sendW(self, w: float) -> None:
        self.w_radps = float(w)

    def sendVW(self, v: float, w: float) -> None:
        self.sendV(v)
        self.sendW(w)


class Sensors:
    """``sensors``: BM's F1 has one camera (``camera_0``) and one odometry pose (``pose3d_0``); every camera name
    answers with the car camera, every pose name with the car's pose, as drivebench's car has one of each."""

    def __init__(self, camera: Camera, pose3d: Pose3dSensor):
        self.camera, self.pose3d = camera, pose3d

    def get_camera(self, name: str = "camera_0") -> Camera:
        return self.camera

    def get_pose3d(self, name: str = "pose3d_0") -> Pose3dSensor:
        return self.pose3d

    def get_laser(self, name: str = "laser_0") -> Any:
        raise NoSuchSensor(
            f"sensors.get_laser({name!r}): Behavior Metrics' F1 car has no laser, nor has drivebench's "
            "(there are get_camera('camera_0') and get_pose3d('pose3d_0'))"
        )

    def get_bird_eye_view(self, name: str = "bird_eye_view_0") -> Any:
        raise NoSuchSensor(f"sensors.get_bird_eye_view({name!r}): a CARLA sensor; the F1 car has none")


class Actuators:
    """``actuators``: every motor name drives the one car (BM's F1 has one, ``motors_0``)."""

    def __init__(self, motors: Motors):
        self.motors = motors

    def get_motor(self, name: str = "motors_0") -> Motors:
        return self.motors


class Handler:
    """Behavior Metrics' brains handler, as a brain sees it. ``update_frame`` keeps the latest debug image of each
    frame id, ``update_pose3d`` the latest pose a brain reports (no GUI draws them); ``transform_image`` applies BM's
    perturbation ``option`` through ``perturb(image, option)`` (the adapter's seeded noise models)."""

    def __init__(self, sensors: Sensors, actuators: Actuators, *, perturb: Callable[[np.ndarray, str], np.ndarray]):
        self.sensors, self.actuators = sensors, actuators
        self.debug_images: dict[str, np.ndarray] = {}
        self.reported_pose: Any = None
        self._perturb = perturb

    def update_frame(self, frame_id: str, data: Any, *args: Any, **kwargs: Any) -> None:
        self.debug_images[str(frame_id)] = data

    def update_pose3d(self, pose_data: Any, *args: Any, **kwargs: Any) -> None:
        self.reported_pose = pose_data

    def get_image(self, camera_name: str = "camera_0") -> Image:
        return self.sensors.get_camera(camera_name).getImage()

    def get_laser_data(self, laser_name: str = "laser_0") -> Any:
        return self.sensors.get_laser(laser_name)

    def get_motors(self, motors_name: str = "motors_0") -> Motors:
        return self.actuators.get_motor(motors_name)

    def transform_image(self, image: np.ndarray, option: str) -> np.ndarray:
        """BM's ``ImageTranform`` perturbation ``option`` applied to ``image`` (RGB uint8); '' returns it as it is."""
        return self._perturb(image, option)
