"""Recovering what a killed recorder left behind (``reference/recording.md`` §3, recipe step 5).

A recorder killed with SIGKILL leaves ``<name>.mcap.part``: the header, every flushed chunk and their message
indexes, but no summary or footer. Stream-read it with CRC checks, copy every schema, channel, message, metadata and
attachment that reads cleanly into a fresh file, stop at the first damaged or torn record, and finish that file.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

from mcap.records import Attachment, Channel, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from recorder.reading import MCAP_ERRORS, RecordingError, describe_error
from recorder.writer import CHUNK_SIZE_BYTES, LIBRARY, PART_SUFFIX, is_being_written

log = logging.getLogger("drivebench.recorder")


@dataclass(frozen=True)
class RepairReport:
    source: Path
    output: Path
    messages: int
    stopped_at: str  # "" when the source read to its end, else what stopped the copy


def repaired_path(source: Path) -> Path:
    """``x.mcap.part`` -> ``x.mcap``; ``x.mcap`` (truncated) -> ``x.repaired.mcap``."""
    if source.name.endswith(PART_SUFFIX):
        return source.with_name(source.name.removesuffix(PART_SUFFIX))
    return source.with_name(source.stem + ".repaired" + (source.suffix or ".mcap"))


def repair(source: Path, *, output: Path | None = None, overwrite: bool = False) -> RepairReport:
    """Write a complete, indexed copy of everything readable in ``source``; a ``.part`` source is removed after."""
    source = Path(source)
    output = Path(output) if output is not None else repaired_path(source)
    if not source.is_file():
        raise RecordingError(f"{source}: no such recording")
    if output.exists() and not overwrite:
        raise RecordingError(f"{output} already exists (remove it or pass --overwrite)")
    temporary = output.with_name(output.name + ".repairing")
    with open(source, "rb") as stream, open(temporary, "wb") as sink:
        writer = Writer(
            sink, chunk_size=CHUNK_SIZE_BYTES, compression=CompressionType.ZSTD, enable_crcs=True, enable_data_crcs=True
        )
        writer.start(profile="", library=LIBRARY)
        messages, stopped_at = _copy(StreamReader(stream, validate_crcs=True), writer)
        writer.finish()
        sink.flush()
        os.fsync(sink.fileno())
    if messages == 0 and stopped_at:
        temporary.unlink()
        raise RecordingError(f"{source}: nothing recoverable ({stopped_at})")
    os.replace(temporary, output)
    if source.name.endswith(PART_SUFFIX):
        source.unlink()
    log.info(
        "repaired %s -> %s: %d messages%s",
        source,
        output,
        messages,
        f" (stopped at {stopped_at})" if stopped_at else "",
    )
    return RepairReport(source=source, output=output, messages=messages, stopped_at=stopped_at)


def _copy(reader: StreamReader, writer: Writer) -> tuple[int, str]:
    schema_ids: dict[int, int] = {}
    channel_ids: dict[int, int] = {}
    messages = 0
    try:
        for record in reader.records:
            if isinstance(record, Schema) and record.id not in schema_ids:
                schema_ids[record.id] = writer.register_schema(record.name, record.encoding, record.data)
            elif isinstance(record, Channel) and record.id not in channel_ids:
                channel_ids[record.id] = writer.register_channel(
                    record.topic, record.message_encoding, schema_ids.get(record.schema_id, 0), dict(record.metadata)
                )
            elif isinstance(record, Message) and record.channel_id in channel_ids:
                writer.add_message(
                    channel_ids[record.channel_id],
                    log_time=record.log_time,
                    data=record.data,
                    publish_time=record.publish_time,
                    sequence=record.sequence,
                )
                messages += 1
            elif isinstance(record, Metadata):
                writer.add_metadata(record.name, dict(record.metadata))
            elif isinstance(record, Attachment):
                writer.add_attachment(record.create_time, record.log_time, record.name, record.media_type, record.data)
    except MCAP_ERRORS as error:
        return messages, describe_error(error)
    return messages, ""


def repair_leftovers(directory: Path) -> list[RepairReport]:
    """Repair every ``*.mcap.part`` in ``directory`` that no live recorder is writing (a recorder starting up cleans
    up after a killed one)."""
    reports = []
    for source in sorted(Path(directory).glob(f"*.mcap{PART_SUFFIX}")):
        try:
            if is_being_written(source):
                continue
            reports.append(repair(source))
        except (RecordingError, OSError) as error:
            log.warning("could not repair %s", error)
    return reports
