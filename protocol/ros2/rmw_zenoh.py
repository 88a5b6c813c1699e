"""rmw_zenoh's names on the bus, from its design document (ros2/rmw_zenoh ``docs/design.md``): the key expression
of a topic's data, the liveliness tokens that announce nodes and their publishers and subscriptions, and the
attachment every put carries. ROS 2's keys, not drivebench's (those are ``protocol.keys``): a bridge on the same
router publishes and subscribes on these so that ROS 2 nodes with ``RMW_IMPLEMENTATION=rmw_zenoh_cpp`` see it.

* data: ``<domain_id>/<fully qualified topic, no leading slash>/<DDS type name>/<RIHS01 type hash>``;
* liveliness: ``@ros2_lv/<domain_id>/<session id>/<node id>/<entity id>/<kind>/<enclave>/<namespace>/<node name>``,
  then for a publisher or subscription ``/<topic>/<DDS type name>/<type hash>/<qos>``; every ``/`` inside a name is
  written ``%``, an empty enclave or namespace is ``%``;
* attachment: sequence number (int64 LE), source timestamp (int64 LE, ns since the UNIX epoch), the GID's length (one
  byte, 16) and the 16-byte GID of the publisher.

:class:`RosNode` puts these on a drivebench :class:`~protocol.bus.Bus`'s Zenoh session: a node token, and publishers
and subscriptions with their tokens, that ROS 2 tools on the same router list and talk to.
"""

from __future__ import annotations

import enum
import hashlib
import itertools
import logging
import os
import struct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import zenoh

from protocol.bus import Bus, RejectCounter
from protocol.ros2 import cdr
from protocol.ros2.interfaces import dds_type_name, type_hash

log = logging.getLogger("drivebench.ros2")
DOMAIN_ID_ENV = "ROS_DOMAIN_ID"  # ROS 2's own variable (not drivebench's): which ROS 2 graph a node joins
MAX_DOMAIN_ID = 232  # REP: domain ids 0..232 (DDS's port arithmetic; rmw_zenoh keeps ROS 2's range)

LIVELINESS_ROOT = "@ros2_lv"
GID_BYTES = 16
_ATTACHMENT = struct.Struct("<qqB")


class EntityKind(enum.StrEnum):
    """What a liveliness token announces."""

    NODE = "NN"
    PUBLISHER = "MP"
    SUBSCRIPTION = "MS"
    SERVICE_SERVER = "SS"
    SERVICE_CLIENT = "SC"


def qos_token(*, depth: int = 10) -> str:
    """The QoS part of a token for ROS 2's default profile (reliable, volatile, keep last ``depth``): rmw_zenoh
    leaves every default field empty and writes the depth (``::,10:,:,:,,``, the design document's ``chatter``)."""
    return f"::,{depth}:,:,:,,"


def fully_qualified(topic: str, *, namespace: str = "") -> str:
    """``cmd_vel`` in namespace ``/robot1`` -> ``/robot1/cmd_vel``; an absolute name (``/cmd_vel``) stays."""
    if topic.startswith("/"):
        return topic
    return f"{namespace.rstrip('/')}/{topic}" if namespace else f"/{topic}"


def topic_key(*, domain_id: int, topic: str, type_name: str) -> str:
    """The key expression of ``topic``'s data (``/cmd_vel``, ``geometry_msgs/msg/Twist``, domain 0 ->
    ``0/cmd_vel/geometry_msgs::msg::dds_::Twist_/RIHS01_9c45...``)."""
    name = fully_qualified(topic).strip("/")
    return f"{domain_id}/{name}/{dds_type_name(type_name)}/{type_hash(type_name)}"


def mangle(name: str) -> str:
    """A name inside a token: every ``/`` as ``%``, an empty one as ``%``."""
    return name.replace("/", "%") if name else "%"


@dataclass(frozen=True)
class Node:
    """One ROS 2 node as rmw_zenoh announces it.

    domain_id: ``ROS_DOMAIN_ID``. session_id: the Zenoh session's id (hex). node_id: the node's number in its
    session. name / namespace / enclave: ROS 2's (namespace and enclave may be empty).
    """

    domain_id: int
    session_id: str
    node_id: int
    name: str
    namespace: str = ""
    enclave: str = ""

    def _prefix(self, entity_id: int, kind: EntityKind) -> str:
        return (
            f"{LIVELINESS_ROOT}/{self.domain_id}/{self.session_id}/{self.node_id}/{entity_id}/{kind}/"
            f"{mangle(self.enclave)}/{mangle(self.namespace)}/{self.name}"
        )

    def token(self) -> str:
        """The node's own token (entity id = node id, kind ``NN``)."""
        return self._prefix(self.node_id, EntityKind.NODE)

    def endpoint_token(
        self, *, entity_id: int, kind: EntityKind, topic: str, type_name: str, qos: str | None = None
    ) -> str:
        """The token of one publisher or subscription of this node on ``topic`` (relative names resolve in the
        node's namespace)."""
        qualified = fully_qualified(topic, namespace=self.namespace)
        return (
            f"{self._prefix(entity_id, kind)}/{mangle(qualified)}/{dds_type_name(type_name)}/{type_hash(type_name)}/"
            f"{qos_token() if qos is None else qos}"
        )


def attachment(*, sequence: int, source_timestamp_ns: int, gid: bytes) -> bytes:
    """The attachment of one put: the publisher's sequence number, the source time and its 16-byte GID."""
    if len(gid) != GID_BYTES:
        raise ValueError(f"a GID is {GID_BYTES} bytes, got {len(gid)}")
    return _ATTACHMENT.pack(sequence, source_timestamp_ns, GID_BYTES) + gid


@dataclass(frozen=True)
class Attachment:
    """A put's attachment, decoded: sequence number, source time (ns since the UNIX epoch), publisher GID."""

    sequence: int
    source_timestamp_ns: int
    gid: bytes


def parse_attachment(data: bytes) -> Attachment:
    """The attachment of a put from a ROS 2 publisher; a ValueError says what is wrong with it."""
    if len(data) < _ATTACHMENT.size:
        raise ValueError(f"an rmw_zenoh attachment is {_ATTACHMENT.size + GID_BYTES} bytes, got {len(data)}")
    sequence, stamp_ns, gid_length = _ATTACHMENT.unpack_from(data)
    gid = bytes(data[_ATTACHMENT.size :])
    if gid_length != len(gid):
        raise ValueError(f"an rmw_zenoh attachment whose GID length says {gid_length} bytes, got {len(gid)}")
    return Attachment(sequence=sequence, source_timestamp_ns=stamp_ns, gid=gid)


def domain_id_from_env() -> int:
    """``ROS_DOMAIN_ID`` as ROS 2 reads it (unset or empty: domain 0); ValueError names a bad value. ROS 2's variable,
    not drivebench's: it is not in ``protocol.environment``'s table of ``DRIVEBENCH_*`` variables."""
    text = os.environ.get("ROS_DOMAIN_ID", "").strip()
    if not text:
        return 0
    if not text.isdigit():
        raise ValueError(f"{DOMAIN_ID_ENV}: a ROS 2 domain id is an integer 0..{MAX_DOMAIN_ID}, got {text!r}")
    return check_domain_id(int(text), where=DOMAIN_ID_ENV)


def check_domain_id(domain_id: int, *, where: str) -> int:
    if not 0 <= domain_id <= MAX_DOMAIN_ID:
        raise ValueError(f"{where}: a ROS 2 domain id is an integer 0..{MAX_DOMAIN_ID}, got {domain_id}")
    return domain_id


def gid_of(token: str) -> bytes:
    """A publisher's 16-byte GID: rmw_zenoh derives it from the entity; a hash of its token is as unique."""
    return hashlib.sha256(token.encode()).digest()[:GID_BYTES]


class RosPublisher:
    """One ROS 2 publisher: CDR payloads on its topic key, each with rmw_zenoh's attachment."""

    def __init__(self, session: zenoh.Session, *, key: str, token: str):
        self.key = key
        self.token = token
        self.gid = gid_of(token)
        self._publisher = session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
        self._sequence = itertools.count(1)  # rmw_zenoh counts from 1

    def publish(self, type_name: str, message: dict[str, Any]) -> None:
        """Put ``message`` (a value of ``type_name``, as ``protocol.ros2.cdr`` takes it) with its attachment."""
        meta = attachment(sequence=next(self._sequence), source_timestamp_ns=time.time_ns(), gid=self.gid)
        self._publisher.put(cdr.encode(type_name, message), attachment=meta)

    def has_subscribers(self) -> bool:
        """Whether some subscriber (a ROS 2 node, a plain Zenoh one) matches the key now."""
        status: Any = self._publisher.matching_status  # a MatchingStatus (zenoh's stub says bool)
        return bool(status.matching)

    def wait_for_subscribers(self, *, timeout_s: float) -> bool:
        deadline = time.monotonic() + timeout_s
        while not self.has_subscribers():
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.01)  # zenoh-python has no blocking wait on matching status
        return True


class RosNode:
    """A ROS 2 node on a drivebench bus, as rmw_zenoh makes one: its liveliness token, publishers (:meth:`publisher`)
    and subscriptions (:meth:`subscribe`), each announced by its own token. Everything goes when the bus closes.

    name / namespace: the node's ROS 2 name. domain_id: ``ROS_DOMAIN_ID`` of the graph it joins.
    """

    def __init__(self, bus: Bus, *, name: str, domain_id: int, namespace: str = ""):
        self._session = bus.session
        self._rejects: RejectCounter = bus.rejects
        self.domain_id = check_domain_id(domain_id, where="domain_id")
        self.node = Node(
            domain_id=domain_id, session_id=str(self._session.zid()), node_id=0, name=name, namespace=namespace
        )
        self._entity_ids = itertools.count(1)  # the node is entity 0 of its session here; its endpoints follow
        self._kept: list[Any] = [self._session.liveliness().declare_token(self.node.token())]

    def _endpoint(self, topic: str, type_name: str, kind: EntityKind) -> tuple[str, str]:
        qualified = fully_qualified(topic, namespace=self.node.namespace)
        token = self.node.endpoint_token(
            entity_id=next(self._entity_ids), kind=kind, topic=qualified, type_name=type_name
        )
        return topic_key(domain_id=self.domain_id, topic=qualified, type_name=type_name), token

    def publisher(self, topic: str, type_name: str) -> RosPublisher:
        """A publisher of ``type_name`` on ``topic``; its token (``MP``) is declared with it."""
        key, token = self._endpoint(topic, type_name, EntityKind.PUBLISHER)
        publisher = RosPublisher(self._session, key=key, token=token)
        self._kept.append(self._session.liveliness().declare_token(token))
        return publisher

    def subscribe(self, topic: str, type_name: str, on_message: Callable[[dict[str, Any]], None]) -> str:
        """Call ``on_message`` (on Zenoh's callback thread) with each decoded message of ``type_name`` on ``topic``;
        a payload that does not decode is counted and dropped. Declares the subscription's token (``MS``); returns
        the key expression it listens on."""
        key, token = self._endpoint(topic, type_name, EntityKind.SUBSCRIPTION)

        def on_sample(sample: zenoh.Sample) -> None:
            try:
                message = cdr.decode(type_name, sample.payload.to_bytes())
            except cdr.CdrError as error:
                self._rejects.reject(key, error, source=key)
                return
            on_message(message)

        self._kept.append(self._session.declare_subscriber(key, on_sample))
        self._kept.append(self._session.liveliness().declare_token(token))
        return key


class Latest:
    """The messages a subscription delivers, for a caller that waits for the next one (thread-safe)."""

    def __init__(self) -> None:
        self._condition = threading.Condition()
        self._messages: list[dict[str, Any]] = []

    def put(self, message: dict[str, Any]) -> None:
        with self._condition:
            self._messages.append(message)
            self._condition.notify_all()

    def clear(self) -> None:
        with self._condition:
            self._messages.clear()

    def next(self, *, timeout_s: float) -> dict[str, Any] | None:
        """The oldest message not yet taken, waiting up to ``timeout_s``; None when none came."""
        with self._condition:
            self._condition.wait_for(lambda: bool(self._messages), timeout=timeout_s)
            return self._messages.pop(0) if self._messages else None
