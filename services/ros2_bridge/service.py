"""The ROS 2 bridge: one run's camera frames, poses and commands, published again as a ROS 2 node would publish
them through rmw_zenoh (``protocol.ros2.rmw_zenoh``), so that ROS 2 tools on the same router see the run.

=========================  ==============================  ===================================================
ROS 2 topic (default)      type                            from
=========================  ==============================  ===================================================
``/camera/image_raw``      ``sensor_msgs/msg/Image``       the simulator's frames (``<p>/sim/camera``, rgb8)
``/odom``                  ``nav_msgs/msg/Odometry``       the ground-truth pose (``world`` -> ``car``)
``/clock``                 ``rosgraph_msgs/msg/Clock``     the simulated time of each pose
``/brain/<name>/cmd_vel``  ``geometry_msgs/msg/Twist``     each brain's commands
``/episode/events``        ``std_msgs/msg/String`` (JSON)  start, laps, brain switches, end
``/metrics/live``          ``std_msgs/msg/String`` (JSON)  the scorer's live metrics
``/episode/score``         ``std_msgs/msg/String`` (JSON)  the score of each episode
=========================  ==============================  ===================================================

Events, metrics and scores are the JSON drivebench records, as in the bags (``protocol.ros2.messages``).

Stamps are the episode's simulated time (ns since its start, as on drivebench's bus): a ROS 2 node with
``use_sim_time`` follows ``/clock``, which starts again at 0 with each episode. The bridge only watches: it drives
nothing (a ROS 2 node drives through the ``ros2`` brain, ``brains.ros2``).
"""

from __future__ import annotations

import logging

import msgspec

from protocol import keys
from protocol.bus import OBSERVER_BUS, Bus, BusConfig, Inbox
from protocol.deploy.runtime import stop_requested
from protocol.messages import CameraFrame, Command, EpisodeEvent, EpisodeScore, LiveMetrics, Pose
from protocol.ros2 import messages
from protocol.ros2.rmw_zenoh import MAX_DOMAIN_ID, RosNode, RosPublisher

log = logging.getLogger("drivebench.ros2_bridge")

ROLE = "ros2_bridge"


class Ros2BridgeConfig(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """Config of the ROS 2 bridge.

    domain_id: the ROS 2 domain (``ROS_DOMAIN_ID``) of every key and token. node: the ROS 2 node's name.
    camera_topic, odom_topic, clock_topic: the ROS 2 topics of the frames, poses and simulated time.
    command_topic: the Twist topic of each brain's commands, ``{brain}`` standing for the brain's bus name.
    bus: a Zenoh client by default (``protocol.bus.OBSERVER_BUS``): it only watches.
    """

    bus: BusConfig = OBSERVER_BUS
    run_id: str = "default"
    name: str = ROLE
    domain_id: int = 0
    node: str = "drivebench_bridge"
    camera_topic: str = "/camera/image_raw"
    odom_topic: str = messages.ODOM_TOPIC
    clock_topic: str = messages.CLOCK_TOPIC
    command_topic: str = "/brain/{brain}/cmd_vel"

    def __post_init__(self) -> None:
        if not 0 <= self.domain_id <= MAX_DOMAIN_ID:
            raise ValueError(f"domain_id must be within 0..{MAX_DOMAIN_ID}, got {self.domain_id}")
        if "{brain}" not in self.command_topic:
            raise ValueError(f"command_topic must contain {{brain}}, got {self.command_topic!r}")


class Ros2Bridge:
    def __init__(self, config: Ros2BridgeConfig, bus: Bus):
        self.config = config
        run = config.run_id
        self._node = RosNode(bus, name=config.node, domain_id=config.domain_id)
        self._camera = self._node.publisher(config.camera_topic, messages.IMAGE)
        self._odom = self._node.publisher(config.odom_topic, messages.ODOMETRY)
        self._clock = self._node.publisher(config.clock_topic, messages.CLOCK)
        # By topic: a brain's command publisher (and its token) appears with its first command, the JSON topics'
        # with their first message.
        self._lazy: dict[str, RosPublisher] = {}
        self._inbox = Inbox()
        bus.subscribe(keys.camera_raw(run), CameraFrame, inbox=self._inbox)
        bus.subscribe(keys.pose(run), Pose, inbox=self._inbox)
        bus.subscribe(keys.commands_all(run), Command, inbox=self._inbox)
        bus.subscribe(keys.events(run), EpisodeEvent, inbox=self._inbox)
        bus.subscribe(keys.live_metrics(run), LiveMetrics, inbox=self._inbox)
        bus.subscribe(keys.score(run), EpisodeScore, inbox=self._inbox)
        # Declared last: whoever sees this token can rely on the subscriptions above.
        bus.declare_alive(keys.alive(run, ROLE, config.name))

    def serve_forever(self) -> None:
        log.info("ROS 2 bridge ready on run %s, domain %d", self.config.run_id, self.config.domain_id)
        while not stop_requested():
            received = self._inbox.recv(timeout_s=0.1)
            if received is not None:
                self.forward(received.message)

    def forward(self, message: msgspec.Struct) -> None:
        """Publish one bus message as the ROS 2 message(s) that stand for it."""
        stamp_ns = message.header.stamp_ns  # type: ignore[attr-defined]
        if isinstance(message, CameraFrame):
            if not message.dropped and message.data:
                self._camera.publish(messages.IMAGE, messages.image(message, stamp_ns=stamp_ns))
        elif isinstance(message, Pose):
            self._odom.publish(messages.ODOMETRY, messages.odometry(message, stamp_ns=stamp_ns))
            self._clock.publish(messages.CLOCK, {"clock": messages.time(stamp_ns)})
        elif isinstance(message, Command):
            topic = self.config.command_topic.replace("{brain}", message.brain)
            self._publisher(topic, messages.TWIST).publish(messages.TWIST, messages.twist(message))
        else:  # events, live metrics, scores: JSON in std_msgs/msg/String, as the bags carry them
            for ros in messages.ros_messages("", message, stamp_ns=stamp_ns):
                self._publisher(ros.topic, ros.type_name).publish(ros.type_name, ros.message)

    def _publisher(self, topic: str, type_name: str) -> RosPublisher:
        if topic not in self._lazy:
            self._lazy[topic] = self._node.publisher(topic, type_name)
        return self._lazy[topic]


def main(argv: list[str] | None = None) -> int:
    from protocol.deploy.runtime import service_main

    return service_main(
        ROLE,
        "drivebench ROS 2 bridge: a run's camera, pose, clock and commands on rmw_zenoh's keys",
        Ros2BridgeConfig,
        Ros2Bridge,
        argv,
    )
