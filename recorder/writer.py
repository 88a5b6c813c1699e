"""Crash-safe MCAP writing of bus messages (``reference/recording.md`` §1-3).

* The file is written as ``<name>.mcap.part`` and renamed to ``<name>.mcap`` only once complete (summary, indexes,
  footer, fsync), so a ``.mcap`` file is always whole and a ``.part`` file always means "needs repair".
* Zstd chunks of 1 MiB, chunk and data-section CRCs on.
* ``flush_if_due`` closes the open chunk every ~1 s of wall time *or* of simulated time, whichever comes first, so
  a recorder killed with SIGKILL loses at most the last second of either (lock-step runs several times faster
  than real time); ``recorder.repair`` rebuilds a complete file from what was flushed.
* Topics are stable (``protocol.mapping.topics``: ``/camera/truth``, ``/car/pose``, ...), the same in every run; the bus
  key and run id of each channel are in its metadata.
* Log time is the simulated time of each message on one clock for the whole file: episode n's stamps are offset
  to start one second after the last message of episode n-1, so episodes follow each other on the timeline.
"""

from __future__ import annotations

import fcntl
import json
import logging
import os
import time
from collections import Counter
from pathlib import Path

from mcap.writer import CompressionType, Writer

from protocol.mapping.recording import (
    FORMAT_VERSION,
    ChannelLayout,
    EpisodeClock,
    Schema,
    channel_layout,
    check_image_format,
    check_recordable,
    record_stamps,
    to_record,
)
from protocol.mapping.topics import RUN_ID_METADATA, VIEW_METADATA
from protocol.mapping.views import ViewMaker, ViewMessage
from protocol.messages import RunMessage

log = logging.getLogger("drivebench.recorder")

CHUNK_SIZE_BYTES = 1 << 20
PART_SUFFIX = ".part"
LIBRARY = "drivebench-recorder"


def part_path(path: Path) -> Path:
    """Where a recording is written until it is complete."""
    return path.with_name(path.name + PART_SUFFIX)


def is_being_written(part: Path) -> bool:
    """True while a live recorder holds ``part`` (its writer keeps an exclusive lock on it)."""
    with open(part, "rb") as probe:
        try:
            fcntl.flock(probe.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            return True
        fcntl.flock(probe.fileno(), fcntl.LOCK_UN)
        return False


class RecordingWriter:
    """Writes bus messages (plus their viewer channels) to one MCAP file. Only one thread may use it.

    path: the final ``.mcap`` path; image_format: "raw" (lossless ``foxglove.RawImage``) or "jpeg"
    (``foxglove.CompressedImage``); views: add the Foxglove pose / transform / track channels.
    """

    def __init__(
        self,
        path: Path,
        *,
        image_format: str = "raw",
        jpeg_quality: int = 90,
        views: bool = True,
        flush_interval_s: float = 1.0,
    ):
        self.path = Path(path)
        self.image_format = check_image_format(image_format)
        self.jpeg_quality = jpeg_quality
        self.flush_interval_s = flush_interval_s
        self.counts: Counter[str] = Counter()  # messages written per bus key
        # Sequence numbers run 0, 1, 2... per key and episode: a jump means messages that never reached us.
        self.missing: Counter[str] = Counter()
        self._last_seq: dict[tuple[str, str, int], int] = {}
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = open(part_path(self.path), "wb")
        # Held while writing: a recorder starting on the same folder repairs only .part files nobody holds.
        fcntl.flock(self._file.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        self._writer = Writer(
            self._file,
            chunk_size=CHUNK_SIZE_BYTES,
            compression=CompressionType.ZSTD,
            enable_crcs=True,
            enable_data_crcs=True,
        )
        # Profile "" on purpose: "ros1"/"ros2" are the only well-known profiles and tools key on them.
        self._writer.start(profile="", library=LIBRARY)
        self._schemas: dict[tuple[str, str], int] = {}
        self._channels: dict[str, int] = {}
        self._clock = EpisodeClock()
        self._views: dict[str, ViewMaker] = {}
        self._with_views = views
        self._last_flush = time.monotonic()
        # Simulated time too: in lock-step at 4x real time a wall-clock second alone held 4 s of the episode.
        self._newest_log_ns = 0  # log time of the newest message written
        self._flushed_log_ns = 0  # log time of the newest message at the last flush
        self._closed = False

    # -- writing --

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        self._writer.add_metadata(name, {k: str(v) for k, v in data.items()})

    def write(self, key: str, message: RunMessage) -> int:
        """Write one bus message published on ``key``; returns its log time (ns). A message the file cannot hold
        raises :class:`~protocol.mapping.recording.RecordFormatError` before anything is written (the file stays
        whole)."""
        check_recordable(message)
        header = message.header
        log_time = self._clock.log_time_ns(header.run_id, header.episode, header.stamp_ns)
        channel = self._channel(
            channel_layout(key, type(message), image_format=self.image_format) if key not in self._channels else None,
            key,
        )
        publish_time, sequence = record_stamps(message)
        data = to_record(message, image_format=self.image_format, jpeg_quality=self.jpeg_quality)
        self._writer.add_message(channel, log_time=log_time, data=data, publish_time=publish_time, sequence=sequence)
        self._newest_log_ns = max(self._newest_log_ns, log_time)
        self.counts[key] += 1
        self._check_sequence(key, header)
        if self._with_views:
            maker = self._views.setdefault(header.run_id, ViewMaker(header.run_id))
            for view in maker.on_message(message, log_time_ns=log_time):
                self._write_view(view)
        return log_time

    def _check_sequence(self, key: str, header) -> None:
        stream = (key, header.run_id, header.episode)
        last = self._last_seq.get(stream, -1)
        if header.seq > last + 1:
            self.missing[key] += header.seq - last - 1
            log.warning(
                "%s episode %d: %d message(s) missing before seq %d (never received)",
                key,
                header.episode,
                header.seq - last - 1,
                header.seq,
            )
        self._last_seq[stream] = max(last, header.seq)

    def _write_view(self, view: ViewMessage) -> None:
        # One channel per run and view: the topic is the same in every run (protocol.mapping.topics).
        channel_key = f"{view.run_id}:{view.topic}"
        if channel_key not in self._channels:
            layout = ChannelLayout(
                topic=view.topic,
                message_encoding="protobuf",
                schema=view.schema,
                metadata={VIEW_METADATA: "1", RUN_ID_METADATA: view.run_id},
            )
            self._channel(layout, channel_key)
        self._writer.add_message(
            self._channels[channel_key],
            log_time=view.log_time_ns,
            data=view.message.SerializeToString(),
            publish_time=view.log_time_ns,
        )

    def _channel(self, layout: ChannelLayout | None, topic: str) -> int:
        if layout is not None:
            schema_id = self._schema(layout.schema)
            self._channels[topic] = self._writer.register_channel(
                topic=layout.topic,
                message_encoding=layout.message_encoding,
                schema_id=schema_id,
                metadata=layout.metadata,
            )
        return self._channels[topic]

    def _schema(self, schema: Schema) -> int:
        key = (schema.name, schema.encoding)
        if key not in self._schemas:
            self._schemas[key] = self._writer.register_schema(
                name=schema.name, encoding=schema.encoding, data=schema.data
            )
        return self._schemas[key]

    # -- durability --

    def flush_if_due(self) -> bool:
        """Close the open chunk and hand it to the kernel when ``flush_interval_s`` has passed since the last, in
        wall time or in the recording's (simulated) time, whichever comes first: a SIGKILL loses at most that much
        of either."""
        now = time.monotonic()
        wall_due = now - self._last_flush >= self.flush_interval_s
        sim_due = self._newest_log_ns - self._flushed_log_ns >= self.flush_interval_s * 1e9
        if not (wall_due or sim_due):
            return False
        self._writer.flush()
        self._last_flush = now
        self._flushed_log_ns = self._newest_log_ns
        return True

    def close(self) -> Path:
        """Finish the file (summary, indexes, footer), fsync it and rename it into place; returns the path."""
        if self._closed:
            return self.path
        self._closed = True
        self.add_metadata(
            "drivebench.recording",
            {
                "format": FORMAT_VERSION,
                "counts": json.dumps(dict(self.counts), sort_keys=True),
                "missing": json.dumps(dict(self.missing), sort_keys=True),
            },
        )
        self._writer.finish()
        self._file.flush()
        os.fsync(self._file.fileno())
        self._file.close()
        os.replace(part_path(self.path), self.path)
        log.info("recorded %d messages on %d keys to %s", sum(self.counts.values()), len(self.counts), self.path)
        return self.path

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()
