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
"""

from __future__ import annotations

import enum
import struct
from dataclasses import dataclass

from protocol.ros2.interfaces import dds_type_name, type_hash

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
