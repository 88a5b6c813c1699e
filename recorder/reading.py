"""Reading recordings back as bus messages."""

from __future__ import annotations

import fnmatch
import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import zstandard
from mcap.exceptions import McapError
from mcap.reader import SeekingReader
from mcap.stream_reader import CRCValidationError
from mcap.summary import Summary

from protocol import keys
from protocol.mapping.recording import KEY_METADATA, RecordFormatError, from_record, is_bus_channel
from protocol.mapping.topics import NAMESPACE_METADATA, RUN_ID_METADATA, VIEW_METADATA
from protocol.messages import RunMessage
from recorder.writer import PART_SUFFIX

# What the mcap package raises on damaged input (it has no single base class for all of them).
MCAP_ERRORS = (
    McapError,
    CRCValidationError,
    struct.error,
    EOFError,
    ValueError,
    KeyError,
    IndexError,
    zlib.error,
    UnicodeDecodeError,
    MemoryError,
    zstandard.ZstdError,
)


class RecordingError(RuntimeError):
    """A recording that cannot be read: one line naming the file and what is wrong with it."""


@dataclass(frozen=True)
class Recorded:
    """One bus message read back from a recording.

    key: the bus key it was published on (``protocol.keys``), e.g. ``drivebench/run/r1/noise/camera``.
    message: the decoded bus message (``CameraFrame``, ``Pose``, ``Command``, ``EpisodeEvent``, ``LiveMetrics``,
        ``EpisodeScore``), equal to what was published.
    log_time_ns: the recording's clock: simulated time, continuing across the episodes of one recording.
    """

    key: str
    message: RunMessage
    log_time_ns: int


def read_messages(path: Path, *, keys_glob: str | None = None) -> Iterator[Recorded]:
    """The bus messages of a recording in log-time order (``keys_glob``: only keys matching this fnmatch pattern).

    Raises :class:`RecordingError` (one line, naming the file) for a missing, truncated or corrupted recording;
    viewer-only channels are skipped.
    """
    path = Path(path)
    with open_recording(path) as stream:
        indexed = indexed_reader(stream, path)
        reader, summary = indexed.reader, indexed.summary
        # Selected by bus key (channel metadata), not topic: topics are stable names shared by every run
        # (protocol.mapping.topics), and files recorded before them used the key as topic; both read the same way.
        selected = {
            c.id
            for c in summary.channels.values()
            if is_bus_channel(dict(c.metadata))
            and (keys_glob is None or fnmatch.fnmatchcase(c.metadata[KEY_METADATA], keys_glob))
        }
        if not selected:
            return
        _check_keys_unique(path, [summary.channels[i] for i in selected])
        topics = sorted({summary.channels[i].topic for i in selected})
        try:
            for schema, channel, record in reader.iter_messages(topics=topics, log_time_order=True):
                if channel.id not in selected:
                    continue  # another run's channel of the same topic, outside keys_glob
                yield Recorded(
                    key=channel.metadata[KEY_METADATA],
                    message=_decode(record.data, schema, channel, path, record.sequence),
                    log_time_ns=record.log_time,
                )
        except MCAP_ERRORS as error:
            raise RecordingError(
                f"{path}: corrupted ({describe_error(error)}); try `drivebench recorder repair {path}`"
            ) from None


@dataclass(frozen=True)
class ChannelInfo:
    """One channel of a recording. topic: its name in viewers (stable, ``protocol.mapping.topics``, in files recorded
    since format 2; the bus key before). key: the bus key it holds ("" for a view). run_id: "" where the file does not
    say. view: a channel the recorder made for viewers; neither bus nor view: another tool's channel."""

    topic: str
    schema: str
    message_encoding: str
    messages: int
    bus_key: bool
    key: str = ""
    run_id: str = ""
    view: bool = False


@dataclass(frozen=True)
class RecordingInfo:
    path: Path
    messages: int
    start_ns: int
    end_ns: int
    channels: list[ChannelInfo]
    metadata: dict[str, dict[str, str]]

    @property
    def duration_s(self) -> float:
        return (self.end_ns - self.start_ns) / 1e9 if self.messages else 0.0


def recording_info(path: Path) -> RecordingInfo:
    """What a recording holds, from its summary (fast: no message is read)."""
    path = Path(path)
    with open_recording(path) as stream:
        indexed = indexed_reader(stream, path)
        reader, summary = indexed.reader, indexed.summary
        statistics = summary.statistics
        counts = statistics.channel_message_counts if statistics else {}
        channels = [
            ChannelInfo(
                topic=c.topic,
                schema=summary.schemas[c.schema_id].name if c.schema_id else "",
                message_encoding=c.message_encoding,
                messages=counts.get(c.id, 0),
                bus_key=is_bus_channel(dict(c.metadata)),
                key=c.metadata.get(KEY_METADATA, ""),
                run_id=_run_id(dict(c.metadata)),
                view=VIEW_METADATA in c.metadata,
            )
            for c in summary.channels.values()
        ]
        try:
            metadata = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
        except MCAP_ERRORS as error:
            raise RecordingError(f"{path}: corrupted metadata ({describe_error(error)})") from None
        return RecordingInfo(
            path=path,
            messages=statistics.message_count if statistics else 0,
            start_ns=statistics.message_start_time if statistics else 0,
            end_ns=statistics.message_end_time if statistics else 0,
            channels=channels,
            metadata=metadata,
        )


def _check_keys_unique(path: Path, channels) -> None:
    """A merged file (``recorder.merge``) whose runs share a run id holds one bus key in two namespaces: their
    messages would interleave on one key, so replay and datasets refuse it."""
    namespaces: dict[str, str] = {}
    for channel in channels:
        key, namespace = channel.metadata[KEY_METADATA], channel.metadata.get(NAMESPACE_METADATA, "")
        if namespaces.setdefault(key, namespace) != namespace:
            raise RecordingError(
                f"{path}: a merged file whose runs /{namespaces[key]} and /{namespace} share the run "
                f"id {keys.run_of_key(key)!r}; replay or build datasets from the original recordings"
            )


def _run_id(metadata: dict[str, str]) -> str:
    if RUN_ID_METADATA in metadata:
        return metadata[RUN_ID_METADATA]
    try:
        return keys.run_of_key(metadata.get(KEY_METADATA, ""))  # files of format 1 name it only in the key
    except ValueError:
        return ""


def open_recording(path: Path):
    """The recording's file opened for reading; :class:`RecordingError` (one line) for a ``.part``, a missing or an
    unreadable file."""
    if path.name.endswith(PART_SUFFIX):
        raise RecordingError(f"{path}: an unfinished recording (.part); run `drivebench recorder repair {path}`")
    try:
        return open(path, "rb")
    except FileNotFoundError:
        raise RecordingError(f"{path}: no such recording") from None
    except OSError as error:
        raise RecordingError(f"{path}: cannot open ({error.strerror})") from None


@dataclass(frozen=True)
class IndexedReader:
    """An MCAP reader with the summary it checked (the reader's own ``get_summary()`` may say None)."""

    reader: SeekingReader
    summary: Summary


def indexed_reader(stream, path: Path) -> IndexedReader:
    """An MCAP reader over ``stream`` that has checked the file's summary; :class:`RecordingError` when it is not
    an indexed MCAP file."""
    try:
        reader = SeekingReader(stream, validate_crcs=True)
    except MCAP_ERRORS as error:
        raise RecordingError(f"{path}: not an MCAP file ({describe_error(error)})") from None
    try:
        summary = reader.get_summary()
    except MCAP_ERRORS as error:
        summary = None
        detail = describe_error(error)
    else:
        detail = "no summary"
    if summary is None:
        # A recorder killed before it finished: the data is there, the index is not.
        raise RecordingError(
            f"{path}: incomplete or truncated ({detail}); recover it with `drivebench recorder repair {path}`"
        )
    return IndexedReader(reader=reader, summary=summary)


def _decode(data: bytes, schema, channel, path: Path, sequence: int):
    try:
        return from_record(data, schema_name=schema.name if schema else "", metadata=dict(channel.metadata))
    except RecordFormatError as error:
        raise RecordingError(f"{path}: message {sequence} on {channel.topic}: {error}") from None


def describe_error(error: Exception) -> str:
    text = str(error).strip().splitlines()[0] if str(error).strip() else ""
    return f"{type(error).__name__}: {text}" if text else type(error).__name__
