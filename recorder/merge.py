"""Comparing runs: several recordings in one MCAP file, each run under its own namespace.

    drivebench recorder merge A.mcap B.mcap -o AB.mcap [--names pilot,memdccp]

Every topic of input *n* goes under ``/<namespace>``: ``/camera/truth`` -> ``/runA/camera/truth``, ``/tf`` ->
``/runA/tf`` (namespaces ``runA``, ``runB``, ... in input order unless ``--names`` gives them: fixed defaults, so
that one shipped layout, ``docs/foxglove/drivebench-compare-layout.json``, shows any merged pair). Coordinate frames
are namespaced too (``car`` -> ``runA/car``, ``camera`` -> ``runA/camera``) except the shared ``world`` frame, so two
brains driving the same circuit play back as two cars on one circuit in one 3D view; each run's car box gets its own
colour. Files recorded before stable topics (run-id topics) are mapped to stable topics first
(``protocol.mapping.topics.stable_topic``).

Log times are kept: each recording's clock starts at 0 at its first episode (simulated time), so the runs play back
aligned from their starts. Messages keep their bytes except the Foxglove geometry and images, whose frame ids are
rewritten. Channel metadata keeps the bus key and run id and adds ``drivebench.namespace``; each input's file
metadata is copied under ``<namespace>/<name>``, and ``drivebench.merge`` lists namespaces, sources and run ids.
Replay and datasets still read a merged file (channels map back to bus keys by metadata) when its runs have different
run ids; when two share one (two compose runs, both ``compose``) they refuse it in one line: use the originals.
"""

from __future__ import annotations

import functools
import heapq
import json
import os
from collections.abc import Iterator, Sequence
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path

from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from google.protobuf.message import DecodeError, Message
from mcap.reader import SeekingReader
from mcap.records import Message as McapMessage
from mcap.writer import CompressionType, Writer

from protocol import keys
from protocol.mapping import topics
from protocol.mapping.views import CAR_FRAME
from recorder.reading import (
    MCAP_ERRORS,
    IndexedReader,
    RecordingError,
    describe_error,
    indexed_reader,
    open_recording,
)
from recorder.writer import CHUNK_SIZE_BYTES, LIBRARY

NAMESPACE_METADATA = topics.NAMESPACE_METADATA
MERGE_METADATA = "drivebench.merge"
_FRAME_FIELDS = frozenset({"frame_id", "parent_frame_id", "child_frame_id"})
# Car box colours (RGBA) per run, in namespace order: the first run keeps the recorder's blue.
_CAR_COLOURS = ((0.1, 0.4, 0.9, 1.0), (0.95, 0.45, 0.05, 1.0), (0.2, 0.75, 0.2, 1.0), (0.75, 0.2, 0.75, 1.0))


class MergeError(RecordingError):
    """Merging cannot start or finish: one line naming the file or option."""


@dataclass(frozen=True)
class MergeReport:
    output: Path
    namespaces: dict[str, str]  # namespace -> source file
    messages: int
    topics: list[str]


def check_namespaces(sources: Sequence[Path], names: Sequence[str] | None) -> list[str]:
    """The namespace of each source: ``names`` when given (one each, distinct), else runA, runB, ..."""
    if names is None:
        if len(sources) > len(topics.DEFAULT_NAMESPACES):
            raise MergeError(f"merge takes at most {len(topics.DEFAULT_NAMESPACES)} recordings without --names")
        return list(topics.DEFAULT_NAMESPACES[: len(sources)])
    if len(names) != len(sources):
        raise MergeError(f"--names gives {len(names)} name(s) for {len(sources)} recording(s)")
    if len(set(names)) != len(names):
        raise MergeError(f"--names must be distinct, got {','.join(names)}")
    for name in names:
        try:
            keys.check_name(name, what="namespace")
        except ValueError as error:
            raise MergeError(f"--names: {error}") from None
    return list(names)


def merge(
    sources: Sequence[Path], *, output: Path, names: Sequence[str] | None = None, overwrite: bool = False
) -> MergeReport:
    """Write ``output`` holding every message of ``sources``, each source under its own namespace."""
    sources = [Path(s) for s in sources]
    output = Path(output)
    if len(sources) < 2:
        raise MergeError("merge needs at least two recordings")
    namespaces = check_namespaces(sources, names)
    if output.suffix != ".mcap":
        raise MergeError(f"merge output must end in .mcap, got {output}")
    if any(output.resolve() == s.resolve() for s in sources):
        raise MergeError(f"{output} is one of the inputs")
    if output.exists() and not overwrite:
        raise MergeError(f"{output} already exists (remove it or pass --overwrite)")
    temporary = output.with_name(output.name + ".merging")
    with ExitStack() as files:
        readers = [indexed_reader(files.enter_context(open_recording(s)), s) for s in sources]
        with open(temporary, "wb") as sink:
            try:
                report = _write(readers, sources, namespaces, sink, output)
            except BaseException:
                temporary.unlink(missing_ok=True)
                raise
            sink.flush()
            os.fsync(sink.fileno())
    os.replace(temporary, output)
    return report


def _write(readers: list[IndexedReader], sources: list[Path], namespaces: list[str], sink, output: Path) -> MergeReport:
    writer = Writer(
        sink, chunk_size=CHUNK_SIZE_BYTES, compression=CompressionType.ZSTD, enable_crcs=True, enable_data_crcs=True
    )
    writer.start(profile="", library=LIBRARY)
    schema_ids: dict[tuple[str, str, bytes], int] = {}
    channels: dict[tuple[int, int], tuple[int, _Rewrite | None]] = {}  # (source, channel id) -> (new id, rewrite)
    run_ids: dict[str, list[str]] = {}
    for index, (indexed, source, namespace) in enumerate(zip(readers, sources, namespaces, strict=True)):
        summary = indexed.summary
        for channel in summary.channels.values():
            schema = summary.schemas.get(channel.schema_id)
            schema_id = 0
            if schema is not None:
                schema_key = (schema.name, schema.encoding, schema.data)
                if schema_key not in schema_ids:
                    schema_ids[schema_key] = writer.register_schema(schema.name, schema.encoding, schema.data)
                schema_id = schema_ids[schema_key]
            metadata = {**channel.metadata, NAMESPACE_METADATA: namespace}
            run_id = _channel_run_id(dict(channel.metadata))
            if run_id:
                metadata[topics.RUN_ID_METADATA] = run_id
                run_ids.setdefault(namespace, [])
                if run_id not in run_ids[namespace]:
                    run_ids[namespace].append(run_id)
            new_id = writer.register_channel(
                _namespaced_topic(channel.topic, namespace), channel.message_encoding, schema_id, metadata
            )
            rewrite = (
                _Rewrite(schema.name, schema.data, namespace, index)
                if schema is not None and schema.encoding == "protobuf"
                else None
            )
            channels[(index, channel.id)] = (new_id, rewrite)
        _copy_metadata(indexed.reader, source, namespace, writer)
    messages = 0
    for index, channel_id, record in _in_log_time_order(readers, sources):
        new_id, rewrite = channels[(index, channel_id)]
        data = rewrite(record.data) if rewrite is not None else record.data
        writer.add_message(
            new_id, log_time=record.log_time, data=data, publish_time=record.publish_time, sequence=record.sequence
        )
        messages += 1
    writer.add_metadata(
        MERGE_METADATA,
        {
            "namespaces": json.dumps(namespaces),
            "sources": json.dumps([s.name for s in sources]),
            "run_ids": json.dumps(run_ids, sort_keys=True),
        },
    )
    writer.finish()
    merged_topics = sorted(
        {
            _namespaced_topic(c.topic, ns)
            for indexed, ns in zip(readers, namespaces, strict=True)
            for c in indexed.summary.channels.values()
        }
    )
    return MergeReport(
        output=output,
        namespaces=dict(zip(namespaces, [str(s) for s in sources], strict=True)),
        messages=messages,
        topics=merged_topics,
    )


def _namespaced_topic(topic: str, namespace: str) -> str:
    try:
        return topics.namespaced(topic, namespace)
    except ValueError:  # not a drivebench topic (another tool's channel): namespaced as it is
        return f"/{namespace}/{topic.lstrip('/')}"


def _channel_run_id(metadata: dict[str, str]) -> str:
    if topics.RUN_ID_METADATA in metadata:
        return metadata[topics.RUN_ID_METADATA]
    try:
        return keys.run_of_key(metadata.get("drivebench.key", ""))  # format 1 files: only in the key
    except ValueError:
        return ""


def _copy_metadata(reader: SeekingReader, source: Path, namespace: str, writer: Writer) -> None:
    try:
        for record in reader.iter_metadata():
            writer.add_metadata(f"{namespace}/{record.name}", dict(record.metadata))
        for attachment in reader.iter_attachments():
            writer.add_attachment(
                attachment.create_time,
                attachment.log_time,
                f"{namespace}/{attachment.name}",
                attachment.media_type,
                attachment.data,
            )
    except MCAP_ERRORS as error:
        raise MergeError(f"{source}: corrupted metadata ({describe_error(error)})") from None


def _in_log_time_order(readers: list[IndexedReader], sources: list[Path]) -> Iterator[tuple[int, int, McapMessage]]:
    """(source index, channel id, message record) of every source, merged by log time."""

    def stream(index: int) -> Iterator[tuple[int, int, int, McapMessage]]:
        try:
            for _, channel, record in readers[index].reader.iter_messages(log_time_order=True):
                yield record.log_time, index, channel.id, record
        except MCAP_ERRORS as error:
            raise MergeError(
                f"{sources[index]}: corrupted ({describe_error(error)}); "
                f"try `drivebench recorder repair {sources[index]}`"
            ) from None

    for _, index, channel_id, record in heapq.merge(
        *(stream(i) for i in range(len(readers))), key=lambda item: (item[0], item[1])
    ):
        yield index, channel_id, record


# -- frame ids ---------------------------------------------------------------------------------------------------------


@functools.cache
def _message_class(schema_name: str, schema_data: bytes) -> type[Message]:
    """A class for a protobuf schema stored in a file (its FileDescriptorSet), from a private pool: the stored schema
    may extend a stock one under the same name (drivebench images)."""
    pool = descriptor_pool.DescriptorPool()
    pending = list(descriptor_pb2.FileDescriptorSet.FromString(schema_data).file)
    while pending:  # dependencies first, whatever order the set lists them in
        ready = [file for file in pending if all(_has(pool, dependency) for dependency in file.dependency)]
        if not ready:
            raise MergeError(f"protobuf schema {schema_name!r} has unresolvable imports")
        for file in ready:
            pool.Add(file)
            pending.remove(file)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(schema_name))


def _has(pool: descriptor_pool.DescriptorPool, file_name: str) -> bool:
    try:
        pool.FindFileByName(file_name)
    except KeyError:
        return False
    return True


class _Rewrite:
    """Namespaces the frame ids of one protobuf channel's messages (and colours its car box)."""

    def __init__(self, schema_name: str, schema_data: bytes, namespace: str, index: int):
        self._class = _message_class(schema_name, schema_data)
        self._namespace = namespace
        self._colour = _CAR_COLOURS[index % len(_CAR_COLOURS)]
        self._is_scene = schema_name == "foxglove.SceneUpdate"

    def __call__(self, data: bytes) -> bytes:
        message = self._class()
        try:
            message.ParseFromString(data)
        except DecodeError as error:
            raise MergeError(f"a {self._class.DESCRIPTOR.full_name} message that does not decode: {error}") from None
        if self._is_scene:
            for entity in message.entities:
                if entity.frame_id == CAR_FRAME:
                    for cube in entity.cubes:
                        cube.color.r, cube.color.g, cube.color.b, cube.color.a = self._colour
        if not _rename_frames(message, self._namespace):
            return data  # nothing to rename: the original bytes
        return message.SerializeToString()


def _rename_frames(message: Message, namespace: str) -> bool:
    """Namespace every frame id field in ``message`` and its sub-messages; True when one changed."""
    changed = False
    for field, value in message.ListFields():
        if field.type == field.TYPE_MESSAGE:
            for item in value if _repeated(field) else [value]:
                changed |= _rename_frames(item, namespace)
        elif field.name in _FRAME_FIELDS and field.type == field.TYPE_STRING and not _repeated(field):
            renamed = topics.namespaced_frame(value, namespace)
            if renamed != value:
                setattr(message, field.name, renamed)
                changed = True
    return changed


def _repeated(field) -> bool:
    # protobuf 6+ has is_repeated and dropped label; 4.x and 5.x have label.
    return field.is_repeated if hasattr(field, "is_repeated") else field.label == field.LABEL_REPEATED
