"""The ``ros2`` brain: a ROS 2 node drives, through rmw_zenoh's keys on drivebench's own router.

Each frame the brain host hands it is published as ``sensor_msgs/msg/Image`` (rgb8) on ``image_topic``; the next
``geometry_msgs/msg/Twist`` that arrives on ``cmd_vel_topic`` after it is the answer (linear.x m/s, angular.z rad/s).
Lock-step stays: the brain waits for that Twist, and the simulator ends the episode ``brain_timeout`` when it does
not come within the episode's brain timeout. A Twist has no stamp, so "the answer" is the first one after the image;
a late answer to an earlier frame is dropped when the next frame goes out, so it cannot answer the wrong frame.

It is the node ``drivebench_brain`` (its own liveliness token, a publisher token for the image topic and a
subscription token for ``/cmd_vel``), on the brain host's Zenoh session: ``ros2 node list`` and ``ros2 topic info``
show it. A frame waits until some subscriber matches the image key, so a ROS 2 node that starts late still sees the
first frame.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Any, TypeVar

from brains.base import Action, Observation
from protocol.bus import Bus
from protocol.deploy.runtime import stop_requested
from protocol.ros2 import messages
from protocol.ros2.rmw_zenoh import Latest, RosNode, RosPublisher, check_domain_id, domain_id_from_env

log = logging.getLogger("drivebench.brains.ros2")

DEFAULT_IMAGE_TOPIC = "/camera/brain/image_raw"  # the frames brains see, as the ROS 2 bags name them
DEFAULT_CMD_VEL_TOPIC = "/cmd_vel"
WAIT_SLICE_S = 0.25  # how often a wait for the ROS 2 side looks at the host's stop flag
STOP = Action(0.0, 0.0)  # the answer when no Twist came: the simulator has ended the episode by then
T = TypeVar("T")


class Ros2Brain:
    """Options: ``domain_id`` (default ``ROS_DOMAIN_ID``, else 0), ``image_topic``, ``cmd_vel_topic``, ``node``
    (the ROS 2 node name) and ``answer_timeout_s``: how long one frame waits for its Twist before the brain answers
    a stop itself (wall seconds; longer than any brain timeout, so the simulator's timeout decides first)."""

    def __init__(
        self,
        *,
        domain_id: int | None = None,
        image_topic: str = DEFAULT_IMAGE_TOPIC,
        cmd_vel_topic: str = DEFAULT_CMD_VEL_TOPIC,
        node: str = "drivebench_brain",
        answer_timeout_s: float = 600.0,
    ):
        self.domain_id = domain_id_from_env() if domain_id is None else check_domain_id(domain_id, where="domain_id")
        self.image_topic = image_topic
        self.cmd_vel_topic = cmd_vel_topic
        self.node_name = node
        self.answer_timeout_s = float(answer_timeout_s)
        self._image: RosPublisher | None = None
        self._twists = Latest()

    def join_bus(self, bus: Bus) -> None:
        """Become a ROS 2 node on ``bus``'s session: announce the node and its two endpoints. The brain host calls
        it, with its own bus, before the first frame."""
        node = RosNode(bus, name=self.node_name, domain_id=self.domain_id)
        self._image = node.publisher(self.image_topic, messages.IMAGE)
        key = node.subscribe(self.cmd_vel_topic, messages.TWIST, self._twists.put)
        log.info("ROS 2 node %s: images on %s, Twists from %s", self.node_name, self._image.key, key)

    def reset(self, *, seed: int) -> None:
        del seed  # the node decides; nothing here is random
        self._twists.clear()

    def act(self, observation: Observation) -> Action:
        if self._image is None:
            raise RuntimeError("the ros2 brain drives through a bus: run it in a brain host (python -m brains)")
        image = self._image
        deadline = time.monotonic() + self.answer_timeout_s
        if not _until(lambda: image.wait_for_subscribers(timeout_s=WAIT_SLICE_S), deadline=deadline):
            log.warning("no ROS 2 subscriber on %s for %.0f s: stopping", self.image_topic, self.answer_timeout_s)
            return STOP
        self._twists.clear()  # a late answer to an earlier frame is not this frame's
        image.publish(messages.IMAGE, _image(observation))
        twist = _until(lambda: self._twists.next(timeout_s=WAIT_SLICE_S), deadline=deadline)
        if twist is None:
            log.warning("no Twist on %s within %.0f s: stopping", self.cmd_vel_topic, self.answer_timeout_s)
            return STOP
        speed_mps, yaw_rate_radps = messages.speeds_of_twist(twist)
        return Action(speed_mps, yaw_rate_radps)


def _until(condition: Callable[[], T | None], *, deadline: float) -> T | None:
    """The first truthy value of ``condition`` (which waits up to :data:`WAIT_SLICE_S` itself) before ``deadline``
    (monotonic s); None at the deadline, or once the host is asked to stop: a host stopping mid-frame must not wait
    for a ROS 2 node that may never answer (service loops check the stop flag every half second)."""
    while not stop_requested() and time.monotonic() < deadline:
        if value := condition():
            return value
    return None


def _image(observation: Observation) -> dict[str, Any]:
    """``sensor_msgs/msg/Image`` of an observation, stamped with its simulated time."""
    height_px, width_px = observation.image_rgb.shape[:2]
    return {
        "header": messages.header(observation.stamp_ns, messages.CAMERA_FRAME),
        "height": height_px,
        "width": width_px,
        "encoding": "rgb8",
        "is_bigendian": 0,
        "step": width_px * 3,
        "data": observation.image_rgb.tobytes(),
    }
