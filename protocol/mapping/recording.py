"""How bus messages are stored in MCAP, both ways: the recorder writes with it, replay and datasets read with it.

One MCAP channel per bus key, named by its stable topic (``protocol.mapping.topics``: ``/camera/truth``, ...), in
encodings
Foxglove and Lichtblick show with no plugin (they cannot show msgpack, ``reference/recording.md`` §4):

* ``CameraFrame`` -> protobuf ``foxglove.RawImage`` (lossless, the default) or ``foxglove.CompressedImage``
  (JPEG). The schema is Foxglove's own, extended with four fields numbered from 1000 that carry what Foxglove's
  image has no room for (run id, episode, sequence number, dropped flag). Viewers key on the schema name and decode
  with the descriptor stored in the file, so the image shows as usual and the extra fields appear in the raw view;
  a reader built from Foxglove's stock schema skips them as unknown fields.
* every other message -> JSON with a JSON Schema generated from its struct (readable, plottable: ``.speed_mps``).

Channel metadata ``drivebench.key`` and ``drivebench.type`` name the bus key and message type (and
``drivebench.run_id`` the run), so a reader can rebuild the exact message, and with it the exact MessagePack wire
bytes (``codec.encode``); JPEG frames are the one lossy case. ``publish_time`` is the header's ``stamp_ns`` and
``sequence`` its ``seq``; the recorder chooses ``log_time`` (see ``recorder.writer``).
"""

from __future__ import annotations

import functools
import typing
from dataclasses import dataclass
from typing import Any

import cv2
import msgspec
import numpy as np
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from google.protobuf.message import DecodeError as ProtobufDecodeError

from protocol import keys
from protocol.images import frame_image
from protocol.mapping.topics import RUN_ID_METADATA, topic_of_key
from protocol.messages import (
    CameraFrame,
    Header,
    RunMessage,
)

FORMAT_VERSION = "2"  # 2: stable topics (protocol.mapping.topics); 1: topics were the bus keys
KEY_METADATA = "drivebench.key"
TYPE_METADATA = "drivebench.type"
IMAGE_FORMATS = ("raw", "jpeg")

# Messages that travel on run keys and are recorded (the control query/reply pair is not published).
RECORDED_MESSAGES: tuple[type[RunMessage], ...] = typing.get_args(RunMessage)


class RecordFormatError(ValueError):
    """A recorded message that cannot be turned back into a bus message; the text says which field or type."""


@dataclass(frozen=True)
class Schema:
    name: str
    encoding: str  # "protobuf" (binary FileDescriptorSet) or "jsonschema"
    data: bytes


@dataclass(frozen=True)
class ChannelLayout:
    """Everything needed to register one MCAP channel for one bus key."""

    topic: str
    message_encoding: str  # "protobuf" or "json"
    schema: Schema
    metadata: dict[str, str]


def type_tag(message_type: type[msgspec.Struct]) -> str:
    return str(message_type.__struct_config__.tag)


# What a channel's type tag may name: a recording holds only what the recorder records (the control pair has no
# header, and no recording ever held one), so a message read back is a RunMessage, header and all.
_TYPES_BY_TAG = {type_tag(t): t for t in RECORDED_MESSAGES}


def channel_layout(key: str, message_type: type[msgspec.Struct], *, image_format: str = "raw") -> ChannelLayout:
    """The MCAP channel for messages of ``message_type`` published on bus key ``key``: its stable topic
    (``protocol.mapping.topics``), with the key, type and run id in its metadata."""
    metadata = {KEY_METADATA: key, TYPE_METADATA: type_tag(message_type), RUN_ID_METADATA: keys.run_of_key(key)}
    topic = topic_of_key(key)
    if message_type is CameraFrame:
        check_image_format(image_format)
        return ChannelLayout(
            topic=topic, message_encoding="protobuf", schema=_image_schema(image_format), metadata=metadata
        )
    return ChannelLayout(topic=topic, message_encoding="json", schema=_json_schema(message_type), metadata=metadata)


def check_image_format(image_format: str) -> str:
    if image_format not in IMAGE_FORMATS:
        raise ValueError(f"image format must be one of {', '.join(IMAGE_FORMATS)}, got {image_format!r}")
    return image_format


# What a recording's fields hold: MCAP times and sequences are unsigned, the image's episode is a uint32, and log
# times add one second per episode to the stamps (``EpisodeClock``), so stamps keep far below 2**64.
_HEADER_RANGES = (("episode", 2**32), ("seq", 2**63), ("stamp_ns", 2**62))


def check_recordable(message: msgspec.Struct) -> None:
    """Raise :class:`RecordFormatError` for a bus message a recording cannot hold as it is (a client's bad input
    that decoded: a negative stamp, a frame whose size does not match its bytes), before anything is written."""
    header: Header = getattr(message, "header")
    for name, end in _HEADER_RANGES:
        if not 0 <= getattr(header, name) < end:
            raise RecordFormatError(f"header.{name} must be within 0..{end - 1}, got {getattr(header, name)}")
    if not isinstance(message, CameraFrame):
        return
    if message.data:
        try:
            frame_image(message)
        except ValueError as error:
            raise RecordFormatError(str(error)) from None
    elif not (0 <= message.width_px < 2**32 and 0 <= message.height_px < 2**32):  # a dropped frame keeps its size
        raise RecordFormatError(f"camera frame of {message.width_px}x{message.height_px}: a size must be >= 0")


def to_record(message: msgspec.Struct, *, image_format: str = "raw", jpeg_quality: int = 90) -> bytes:
    """The MCAP message data for one bus message (the channel's layout comes from :func:`channel_layout`)."""
    if isinstance(message, CameraFrame):
        return _image_record(message, image_format=image_format, jpeg_quality=jpeg_quality)
    return msgspec.json.encode(message)


def record_stamps(message: msgspec.Struct) -> tuple[int, int]:
    """(publish_time_ns, sequence) for the MCAP Message record of a bus message: its header stamp and seq."""
    header: Header = getattr(message, "header")  # every bus message has one; Struct itself does not say so
    return header.stamp_ns, header.seq & 0xFFFFFFFF


def from_record(data: bytes, *, schema_name: str, metadata: dict[str, str]) -> RunMessage:
    """The bus message stored in one MCAP message of a channel with ``metadata`` (from :func:`channel_layout`)."""
    tag = metadata.get(TYPE_METADATA)
    message_type = _TYPES_BY_TAG.get(tag or "")
    if message_type is None:
        raise RecordFormatError(f"channel has no known {TYPE_METADATA} (got {tag!r})")
    if message_type is CameraFrame:
        return _frame_from_record(data, schema_name=schema_name)
    try:
        return msgspec.json.decode(data, type=message_type)
    except (msgspec.DecodeError, msgspec.ValidationError) as error:
        raise RecordFormatError(f"not a valid {message_type.__name__}: {error}") from None


def is_bus_channel(metadata: dict[str, str]) -> bool:
    """Channels that hold bus messages (others are views for viewers, e.g. the car pose as a transform)."""
    return KEY_METADATA in metadata and TYPE_METADATA in metadata


# -- JSON ------------------------------------------------------------------------------------------------------------


@functools.cache
def _json_schema(message_type: type[msgspec.Struct]) -> Schema:
    schema = msgspec.json.schema(message_type)
    # Viewers read field names from the root object; msgspec puts the root behind a "$ref", so inline every ref
    # (the message types are not recursive).
    inlined = _inline_refs(schema, schema.get("$defs", {}))
    inlined.pop("$defs", None)
    inlined["$schema"] = "https://json-schema.org/draft/2020-12/schema"
    return Schema(name=type_tag(message_type), encoding="jsonschema", data=msgspec.json.encode(inlined))


def _inline_refs(node: Any, defs: dict[str, Any]) -> Any:
    if isinstance(node, dict):
        ref = node.get("$ref")
        if isinstance(ref, str) and ref.startswith("#/$defs/"):
            return _inline_refs(defs[ref.removeprefix("#/$defs/")], defs)
        return {k: _inline_refs(v, defs) for k, v in node.items() if k != "$defs"}
    if isinstance(node, list):
        return [_inline_refs(v, defs) for v in node]
    return node


# -- images ----------------------------------------------------------------------------------------------------------

# Extra fields on Foxglove's image schemas: numbered far above Foxglove's own (1-7) so they never collide.
_EXTRA_FIELDS = (
    ("drivebench_run_id", 1000, descriptor_pb2.FieldDescriptorProto.TYPE_STRING),
    ("drivebench_episode", 1001, descriptor_pb2.FieldDescriptorProto.TYPE_UINT32),
    ("drivebench_seq", 1002, descriptor_pb2.FieldDescriptorProto.TYPE_UINT64),
    ("drivebench_dropped", 1003, descriptor_pb2.FieldDescriptorProto.TYPE_BOOL),
)


@functools.cache
def _image_types(image_format: str) -> tuple[Schema, type]:
    """The extended Foxglove image schema (FileDescriptorSet) and a message class built from it."""
    from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
    from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
    from google.protobuf import timestamp_pb2

    stock = RawImage if image_format == "raw" else CompressedImage
    timestamp_file = descriptor_pb2.FileDescriptorProto()
    timestamp_pb2.Timestamp.DESCRIPTOR.file.CopyToProto(timestamp_file)
    image_file = descriptor_pb2.FileDescriptorProto()
    stock.DESCRIPTOR.file.CopyToProto(image_file)
    image_file.name = f"drivebench/{stock.DESCRIPTOR.name}.proto"  # not Foxglove's file: it has more fields
    for name, number, field_type in _EXTRA_FIELDS:
        image_file.message_type[0].field.add(
            name=name, number=number, type=field_type, label=descriptor_pb2.FieldDescriptorProto.LABEL_OPTIONAL
        )
    # A private pool: the stock foxglove.RawImage lives in the default pool under the same full name.
    pool = descriptor_pool.DescriptorPool()
    pool.Add(timestamp_file)
    pool.Add(image_file)
    message_class = message_factory.GetMessageClass(pool.FindMessageTypeByName(stock.DESCRIPTOR.full_name))
    data = descriptor_pb2.FileDescriptorSet(file=[timestamp_file, image_file]).SerializeToString()
    return Schema(name=stock.DESCRIPTOR.full_name, encoding="protobuf", data=data), message_class


def _image_schema(image_format: str) -> Schema:
    return _image_types(image_format)[0]


def _image_record(frame: CameraFrame, *, image_format: str, jpeg_quality: int) -> bytes:
    _, message_class = _image_types(check_image_format(image_format))
    image = message_class()
    image.timestamp.seconds, image.timestamp.nanos = divmod(frame.header.stamp_ns, 1_000_000_000)
    image.frame_id = "camera"
    image.drivebench_run_id = frame.header.run_id
    image.drivebench_episode = frame.header.episode
    image.drivebench_seq = frame.header.seq
    image.drivebench_dropped = frame.dropped
    if image_format == "raw":
        image.width, image.height, image.encoding = frame.width_px, frame.height_px, frame.encoding
        image.step = frame.width_px * 3 if frame.data else 0
        image.data = frame.data
    else:
        image.format = "jpeg"
        image.data = _jpeg(frame, quality=jpeg_quality) if frame.data else b""
    return image.SerializeToString()


def _jpeg(frame: CameraFrame, *, quality: int) -> bytes:
    rgb = np.frombuffer(frame.data, np.uint8).reshape(frame.height_px, frame.width_px, 3)
    ok, encoded = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise RecordFormatError("JPEG encoding failed")
    return encoded.tobytes()


def _frame_from_record(data: bytes, *, schema_name: str) -> CameraFrame:
    image_format = {"foxglove.RawImage": "raw", "foxglove.CompressedImage": "jpeg"}.get(schema_name)
    if image_format is None:
        raise RecordFormatError(f"a camera channel with schema {schema_name!r} (expected a Foxglove image)")
    image = _image_types(image_format)[1]()
    try:
        image.ParseFromString(data)
    except ProtobufDecodeError as error:
        raise RecordFormatError(f"not a valid {schema_name}: {error}") from None
    header = Header(
        run_id=image.drivebench_run_id,
        episode=image.drivebench_episode,
        seq=image.drivebench_seq,
        stamp_ns=image.timestamp.seconds * 1_000_000_000 + image.timestamp.nanos,
    )
    if image_format == "raw":
        return CameraFrame(
            header=header,
            width_px=image.width,
            height_px=image.height,
            encoding=image.encoding,
            data=image.data,
            dropped=image.drivebench_dropped,
        )
    return _frame_from_jpeg(header, image.data, dropped=image.drivebench_dropped)


def _frame_from_jpeg(header: Header, jpeg: bytes, *, dropped: bool) -> CameraFrame:
    if not jpeg:
        return CameraFrame(header=header, width_px=0, height_px=0, data=b"", dropped=dropped)
    bgr = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)
    if bgr is None:
        raise RecordFormatError("a camera image that is not a valid JPEG")
    rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
    return CameraFrame(
        header=header, width_px=rgb.shape[1], height_px=rgb.shape[0], data=rgb.tobytes(), dropped=dropped
    )


# Episodes' stamps restart at 0: each (run, episode) gets a base log time, one gap after the latest time logged.
EPISODE_GAP_NS = 1_000_000_000


class EpisodeClock:
    """Log time for messages whose stamps restart at 0 every episode (recordings and the live view share it,
    so a viewer's clock never runs back)."""

    def __init__(self) -> None:
        self._base_ns: dict[tuple[str, int], int] = {}
        self._latest_ns = -EPISODE_GAP_NS

    def log_time_ns(self, run_id: str, episode: int, stamp_ns: int) -> int:
        base = self._base_ns.get((run_id, episode))
        if base is None:
            base = self._base_ns[(run_id, episode)] = self._latest_ns + EPISODE_GAP_NS if self._base_ns else 0
        log_time = base + max(0, stamp_ns)
        self._latest_ns = max(self._latest_ns, log_time)
        return log_time
