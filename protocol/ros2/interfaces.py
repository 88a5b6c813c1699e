"""The ROS 2 message types drivebench speaks, as data, and what ROS 2 derives from a type's definition:

* :func:`type_hash`: REP-2016's ``RIHS01_<sha256>`` over the canonical JSON of the type description (the type and
  every type it references, sorted by name; field types as ``type_description_interfaces/msg/FieldType`` ids;
  default values left out), which rmw_zenoh puts in every key and rosbag2 in ``metadata.yaml``.
* :func:`message_definition`: the ``ros2msg`` schema text rosbag2 stores in an MCAP file (the type's fields, then
  each referenced type after a line of ``=`` and ``MSG: pkg/Type``).
* :func:`dds_type_name`: the DDS-mangled name in rmw_zenoh's keys (``geometry_msgs::msg::dds_::Twist_``).

The definitions below are the standard packages' ``.msg`` files (fields in order, comments and defaults left out:
REP-2016 does not hash defaults, and a reader needs none). Only what drivebench publishes is here.
"""

from __future__ import annotations

import functools
import hashlib
import json
import re
from dataclasses import dataclass

# ``type_description_interfaces/msg/FieldType``: the id of each primitive; a nested type is 1. A fixed array adds
# 48, a bounded sequence 96, an unbounded sequence 144.
_PRIMITIVE_IDS = {
    "int8": 2,
    "uint8": 3,
    "int16": 4,
    "uint16": 5,
    "int32": 6,
    "uint32": 7,
    "int64": 8,
    "uint64": 9,
    "float32": 10,
    "float64": 11,
    "char": 13,
    "bool": 15,
    "byte": 16,
    "string": 17,
}
_NESTED_ID = 1
_ARRAY_OFFSET = 48
_UNBOUNDED_SEQUENCE_OFFSET = 144
PRIMITIVES = frozenset(_PRIMITIVE_IDS)

_DEFINITIONS: dict[str, str] = {
    "builtin_interfaces/msg/Time": "int32 sec; uint32 nanosec",
    "std_msgs/msg/Header": "builtin_interfaces/msg/Time stamp; string frame_id",
    "std_msgs/msg/String": "string data",
    "sensor_msgs/msg/Image": (
        "std_msgs/msg/Header header; uint32 height; uint32 width; string encoding; uint8 is_bigendian; uint32 step; "
        "uint8[] data"
    ),
    "geometry_msgs/msg/Vector3": "float64 x; float64 y; float64 z",
    "geometry_msgs/msg/Point": "float64 x; float64 y; float64 z",
    "geometry_msgs/msg/Quaternion": "float64 x; float64 y; float64 z; float64 w",
    "geometry_msgs/msg/Twist": "geometry_msgs/msg/Vector3 linear; geometry_msgs/msg/Vector3 angular",
    "geometry_msgs/msg/Pose": "geometry_msgs/msg/Point position; geometry_msgs/msg/Quaternion orientation",
    "geometry_msgs/msg/PoseWithCovariance": "geometry_msgs/msg/Pose pose; float64[36] covariance",
    "geometry_msgs/msg/TwistWithCovariance": "geometry_msgs/msg/Twist twist; float64[36] covariance",
    "geometry_msgs/msg/Transform": "geometry_msgs/msg/Vector3 translation; geometry_msgs/msg/Quaternion rotation",
    "geometry_msgs/msg/TransformStamped": (
        "std_msgs/msg/Header header; string child_frame_id; geometry_msgs/msg/Transform transform"
    ),
    "nav_msgs/msg/Odometry": (
        "std_msgs/msg/Header header; string child_frame_id; geometry_msgs/msg/PoseWithCovariance pose; "
        "geometry_msgs/msg/TwistWithCovariance twist"
    ),
    "tf2_msgs/msg/TFMessage": "geometry_msgs/msg/TransformStamped[] transforms",
    "rosgraph_msgs/msg/Clock": "builtin_interfaces/msg/Time clock",
}
INTERFACES: tuple[str, ...] = tuple(_DEFINITIONS)

_FIELD_TYPE = re.compile(r"(?P<base>[\w/]+?)(?:\[(?P<length>\d*)\])?")


@dataclass(frozen=True)
class Field:
    """One field of a message type.

    name: the field's name. base: a primitive (``float64``) or a full type name (``geometry_msgs/msg/Vector3``).
    length: None for one value, 0 for an unbounded sequence (``uint8[]``), n for a fixed array (``float64[36]``).
    """

    name: str
    base: str
    length: int | None

    @property
    def nested(self) -> bool:
        return self.base not in PRIMITIVES


@functools.cache
def fields(type_name: str) -> tuple[Field, ...]:
    """The fields of ``type_name`` (``geometry_msgs/msg/Twist``), in order; a KeyError names an unknown type."""
    try:
        definition = _DEFINITIONS[type_name]
    except KeyError:
        raise KeyError(f"no ROS 2 interface {type_name!r} (known: {', '.join(INTERFACES)})") from None
    parsed = []
    for item in definition.split(";"):
        field_type, name = item.split()
        match = _FIELD_TYPE.fullmatch(field_type)
        assert match is not None, field_type  # the table above is ours: a typo must fail loudly in every test
        length = match.group("length")
        parsed.append(Field(name=name, base=match.group("base"), length=None if length is None else int(length or 0)))
    return tuple(parsed)


def referenced_types(type_name: str) -> list[str]:
    """Every type ``type_name`` refers to, at any depth, sorted by name (REP-2016's order)."""
    found: set[str] = set()
    pending = [type_name]
    while pending:
        for field in fields(pending.pop()):
            if field.nested and field.base not in found:
                found.add(field.base)
                pending.append(field.base)
    return sorted(found)


def _field_type_id(field: Field) -> int:
    base_id = _NESTED_ID if field.nested else _PRIMITIVE_IDS[field.base]
    if field.length is None:
        return base_id
    return base_id + (_UNBOUNDED_SEQUENCE_OFFSET if field.length == 0 else _ARRAY_OFFSET)


def _individual_description(type_name: str) -> dict:
    """``type_description_interfaces/msg/IndividualTypeDescription`` of one type, as REP-2016 hashes it: keys in
    the message's field order, no default values."""
    return {
        "type_name": type_name,
        "fields": [
            {
                "name": field.name,
                "type": {
                    "type_id": _field_type_id(field),
                    "capacity": field.length or 0,
                    "string_capacity": 0,
                    "nested_type_name": field.base if field.nested else "",
                },
            }
            for field in fields(type_name)
        ],
    }


def type_description(type_name: str) -> dict:
    """``type_description_interfaces/msg/TypeDescription`` of ``type_name``: the type and every referenced one."""
    return {
        "type_description": _individual_description(type_name),
        "referenced_type_descriptions": [_individual_description(name) for name in referenced_types(type_name)],
    }


@functools.cache
def type_hash(type_name: str) -> str:
    """REP-2016's RIHS01 hash of ``type_name``: ``RIHS01_`` and the SHA-256 of the type description's JSON, written
    as Python's ``json.dumps`` writes it with ``", "`` and ``": "`` separators (the form the hash is defined on)."""
    text = json.dumps(type_description(type_name), ensure_ascii=True, allow_nan=False, separators=(", ", ": "))
    return "RIHS01_" + hashlib.sha256(text.encode("utf-8")).hexdigest()


def _short_name(type_name: str) -> str:
    """``geometry_msgs/msg/Vector3`` -> ``geometry_msgs/Vector3``: how ``.msg`` files and ``MSG:`` lines name it."""
    package, _, name = type_name.split("/")
    return f"{package}/{name}"


def _msg_text(type_name: str) -> str:
    lines = []
    for field in fields(type_name):
        suffix = "" if field.length is None else f"[{field.length or ''}]"
        base = _short_name(field.base) if field.nested else field.base
        lines.append(f"{base}{suffix} {field.name}\n")
    return "".join(lines)


_SEPARATOR = "=" * 80


@functools.cache
def message_definition(type_name: str) -> str:
    """The ``ros2msg`` schema text of ``type_name`` as rosbag2 stores it in MCAP: its fields, then each referenced
    type's after a separator line and ``MSG: pkg/Type``."""
    parts = [_msg_text(type_name)]
    for name in referenced_types(type_name):
        parts.append(f"{_SEPARATOR}\nMSG: {_short_name(name)}\n{_msg_text(name)}")
    return "".join(parts)


def dds_type_name(type_name: str) -> str:
    """``geometry_msgs/msg/Twist`` -> ``geometry_msgs::msg::dds_::Twist_`` (rmw_zenoh's keys and tokens)."""
    package, kind, name = type_name.split("/")
    return f"{package}::{kind}::dds_::{name}_"
