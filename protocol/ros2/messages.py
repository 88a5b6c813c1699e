"""drivebench's bus messages as standard ROS 2 messages, the same for bags and the live bridge.

=============================  ==================================  ===========================================
ROS 2 topic                    type                                from
=============================  ==================================  ===========================================
``/camera/truth/image_raw``    ``sensor_msgs/msg/Image`` (rgb8)    the simulator's frames (``<p>/sim/camera``)
``/camera/brain/image_raw``    ``sensor_msgs/msg/Image`` (rgb8)    the frames brains see (``<p>/noise/camera``)
``/brain/<name>/cmd_vel``      ``geometry_msgs/msg/Twist``         each command of a brain: linear.x m/s,
                                                                   angular.z rad/s
``/odom``                      ``nav_msgs/msg/Odometry``           the ground-truth pose (``world`` -> ``car``)
``/tf``                        ``tf2_msgs/msg/TFMessage``          the same pose as a transform
``/clock``                     ``rosgraph_msgs/msg/Clock``         the simulated time of each pose
``/episode/events``            ``std_msgs/msg/String`` (JSON)      start, laps, brain switches, end
``/metrics/live``              ``std_msgs/msg/String`` (JSON)      the scorer's live metrics
``/episode/score``             ``std_msgs/msg/String`` (JSON)      the score of each episode
=============================  ==================================  ===========================================

Stamps are simulated time: the caller passes the message's time on one clock for the whole run (a recording's log
time, which continues across episodes), so ``/clock`` never runs back. Dropped camera frames carry no image and
become no message. Events and metrics travel as the JSON drivebench records (every field named, with its unit),
in ``std_msgs/msg/String``: every ROS 2 tool shows it, and no custom package is needed to read it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import msgspec

from protocol.mapping import topics
from protocol.messages import CameraFrame, Command, EpisodeEvent, EpisodeScore, LiveMetrics, Pose

IMAGE = "sensor_msgs/msg/Image"
TWIST = "geometry_msgs/msg/Twist"
ODOMETRY = "nav_msgs/msg/Odometry"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
CLOCK = "rosgraph_msgs/msg/Clock"
STRING = "std_msgs/msg/String"

WORLD_FRAME = "world"  # the frames of drivebench's Foxglove views (protocol.mapping.views), so both agree
CAR_FRAME = "car"
CAMERA_FRAME = "camera"
ODOM_TOPIC = "/odom"
TF_TOPIC = "/tf"
CLOCK_TOPIC = "/clock"
_JSON_TOPICS = {
    EpisodeEvent: topics.EPISODE_EVENTS,
    LiveMetrics: topics.METRICS_LIVE,
    EpisodeScore: topics.EPISODE_SCORE,
}
_ZERO_COVARIANCE = [0.0] * 36  # ground truth: no uncertainty to report


@dataclass(frozen=True)
class RosMessage:
    """One ROS 2 message to publish or record.

    topic: the fully qualified topic name. type_name: ``pkg/msg/Type``. stamp_ns: simulated time in ns (the bag's
    log time, the header's stamp). message: the value, as ``protocol.ros2.cdr`` encodes it.
    """

    topic: str
    type_name: str
    stamp_ns: int
    message: dict[str, Any]


def camera_topic(key_topic: str) -> str:
    """``/camera/truth`` (a recording's stable topic) -> ``/camera/truth/image_raw`` (ROS 2's camera convention)."""
    return f"{key_topic}/image_raw"


def command_topic(brain: str) -> str:
    """The Twist topic of one brain's commands: ``/brain/<name>/cmd_vel``."""
    return topics.command_topic(brain) + "_vel"


def ros_messages(key_topic: str, message: msgspec.Struct, *, stamp_ns: int) -> list[RosMessage]:
    """The ROS 2 messages that stand for one bus message recorded on stable topic ``key_topic``
    (``protocol.mapping.topics``); none for a dropped frame or a message ROS 2 has no place for."""
    if isinstance(message, CameraFrame):
        if message.dropped or not message.data:
            return []
        return [RosMessage(camera_topic(key_topic), IMAGE, stamp_ns, image(message, stamp_ns=stamp_ns))]
    if isinstance(message, Command):
        return [RosMessage(command_topic(message.brain), TWIST, stamp_ns, twist(message))]
    if isinstance(message, Pose):
        return [
            RosMessage(ODOM_TOPIC, ODOMETRY, stamp_ns, odometry(message, stamp_ns=stamp_ns)),
            RosMessage(TF_TOPIC, TF_MESSAGE, stamp_ns, transforms(message, stamp_ns=stamp_ns)),
            RosMessage(CLOCK_TOPIC, CLOCK, stamp_ns, {"clock": time(stamp_ns)}),
        ]
    topic = _JSON_TOPICS.get(type(message))
    if topic is None:
        return []
    return [RosMessage(topic, STRING, stamp_ns, {"data": msgspec.json.encode(message).decode()})]


def time(stamp_ns: int) -> dict[str, int]:
    """``builtin_interfaces/msg/Time`` of a time in ns."""
    sec, nanosec = divmod(stamp_ns, 1_000_000_000)
    return {"sec": sec, "nanosec": nanosec}


def header(stamp_ns: int, frame_id: str) -> dict[str, Any]:
    return {"stamp": time(stamp_ns), "frame_id": frame_id}


def image(frame: CameraFrame, *, stamp_ns: int) -> dict[str, Any]:
    """``sensor_msgs/msg/Image``: drivebench frames are packed RGB rows, top row first (``rgb8``)."""
    return {
        "header": header(stamp_ns, CAMERA_FRAME),
        "height": frame.height_px,
        "width": frame.width_px,
        "encoding": "rgb8",
        "is_bigendian": 0,
        "step": frame.width_px * 3,
        "data": frame.data,
    }


def vector(x: float = 0.0, y: float = 0.0, z: float = 0.0) -> dict[str, float]:
    return {"x": x, "y": y, "z": z}


def twist(command: Command) -> dict[str, Any]:
    """``geometry_msgs/msg/Twist`` of a command: forward speed (m/s) as linear.x, yaw rate (rad/s) as angular.z."""
    return {"linear": vector(command.speed_mps), "angular": vector(z=command.yaw_rate_radps)}


def speeds_of_twist(message: dict[str, Any]) -> tuple[float, float]:
    """(speed_mps, yaw_rate_radps) of a decoded Twist: the two of its six numbers a car on a plane can take."""
    return float(message["linear"]["x"]), float(message["angular"]["z"])


def _yaw_quaternion(yaw_rad: float) -> dict[str, float]:
    return {"x": 0.0, "y": 0.0, "z": math.sin(yaw_rad / 2), "w": math.cos(yaw_rad / 2)}


def odometry(pose: Pose, *, stamp_ns: int) -> dict[str, Any]:
    """``nav_msgs/msg/Odometry``: the pose in ``world``, the twist in the car's frame (REP-105's convention)."""
    return {
        "header": header(stamp_ns, WORLD_FRAME),
        "child_frame_id": CAR_FRAME,
        "pose": {
            "pose": {"position": vector(pose.x_m, pose.y_m), "orientation": _yaw_quaternion(pose.yaw_rad)},
            "covariance": _ZERO_COVARIANCE,
        },
        "twist": {
            "twist": {"linear": vector(pose.speed_mps), "angular": vector(z=pose.yaw_rate_radps)},
            "covariance": _ZERO_COVARIANCE,
        },
    }


def transforms(pose: Pose, *, stamp_ns: int) -> dict[str, Any]:
    """``tf2_msgs/msg/TFMessage`` with the one transform ``world`` -> ``car``."""
    transform = {"translation": vector(pose.x_m, pose.y_m), "rotation": _yaw_quaternion(pose.yaw_rad)}
    return {
        "transforms": [{"header": header(stamp_ns, WORLD_FRAME), "child_frame_id": CAR_FRAME, "transform": transform}]
    }
