"""A recording as a rosbag2 folder that ``ros2 bag play``, rosbags and Foxglove open: ``metadata.yaml`` beside one
MCAP file whose channels carry ``ros2msg`` schemas (the ``.msg`` text with its dependencies) and ``cdr`` messages.

What becomes which ROS 2 message is ``protocol.ros2.messages``; the bytes are ``protocol.ros2.cdr``; the type hashes
in ``metadata.yaml`` and in channel metadata are computed by ``protocol.ros2.interfaces`` (REP-2016). Times are the
recording's log time: simulated time, continuing across the episodes of the recording.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import yaml
from mcap.writer import CompressionType, Writer

from protocol.mapping.topics import topic_of_key
from protocol.ros2 import cdr, interfaces
from protocol.ros2.messages import RosMessage, ros_messages
from recorder.reading import RecordingError, read_messages, recording_info

METADATA_FILE = "metadata.yaml"
# rosbag2's metadata format 8 (ROS 2 Jazzy): type_description_hash per topic (7) and ros_distro (8).
METADATA_VERSION = 8
ROS_DISTRO = "jazzy"
LIBRARY = "drivebench-ros2bag"
# What rosbag2 writes for a publisher with the default QoS (reliable, volatile, keep last 10), in the YAML form of
# metadata format 8; ``ros2 bag play`` offers the recorded QoS again.
_DEFAULT_QOS = (
    "- history: 1\n  depth: 10\n  reliability: 1\n  durability: 2\n"
    "  deadline:\n    sec: 9223372036\n    nsec: 854775807\n  lifespan:\n    sec: 9223372036\n    nsec: 854775807\n"
    "  liveliness: 1\n  liveliness_lease_duration:\n    sec: 9223372036\n    nsec: 854775807\n"
    "  avoid_ros_namespace_conventions: false\n"
)


class BagExportError(RecordingError):
    """A bag that cannot be written where asked: one line naming the folder and why."""


@dataclass
class BagReport:
    """What :func:`export_ros2` wrote: the folder, its MCAP file, messages and type per topic, and the first and
    last stamp (simulated time, ns)."""

    folder: Path
    mcap: Path
    counts: Counter[str] = field(default_factory=Counter)
    types: dict[str, str] = field(default_factory=dict)
    start_ns: int = 0
    end_ns: int = 0

    @property
    def messages(self) -> int:
        return sum(self.counts.values())


def export_ros2(recording: Path, *, output: Path, overwrite: bool = False) -> BagReport:
    """Write recording ``recording`` as the rosbag2 folder ``output``.

    Raises :class:`RecordingError` for a recording that cannot be read and :class:`BagExportError` for an output
    that already holds a bag (unless ``overwrite``: then its ``metadata.yaml`` and MCAP file are replaced, nothing
    else in the folder is touched) or cannot be written.
    """
    output = Path(output)
    mcap_path = output / f"{output.name}_0.mcap"  # rosbag2's own naming: <folder>_<split index>.mcap
    recording_info(recording)  # a missing or damaged recording fails here, before anything is written
    _check_output(output, mcap_path, overwrite=overwrite)
    report = BagReport(folder=output, mcap=mcap_path)
    try:
        _write_mcap(recording, mcap_path, report)
        (output / METADATA_FILE).write_text(yaml.safe_dump(_metadata(report), sort_keys=False))
    except BaseException:
        mcap_path.unlink(missing_ok=True)  # ours, half written: a bag without its metadata is no bag
        raise
    return report


def _write_mcap(recording: Path, mcap_path: Path, report: BagReport) -> None:
    try:
        stream = open(mcap_path, "wb")
    except OSError as error:
        raise BagExportError(f"{mcap_path}: cannot write ({error.strerror or error})") from None
    with stream:
        writer = _BagWriter(stream)
        for recorded in read_messages(recording):
            for message in ros_messages(topic_of_key(recorded.key), recorded.message, stamp_ns=recorded.log_time_ns):
                writer.write(message)
                _count(report, message)
        writer.finish()


def _check_output(output: Path, mcap_path: Path, *, overwrite: bool) -> None:
    ours = (output / METADATA_FILE, mcap_path)
    if not overwrite and any(path.exists() for path in ours):
        raise BagExportError(f"{output}: already holds a bag; pass --overwrite to replace it")
    if output.exists() and not output.is_dir():
        raise BagExportError(f"{output}: exists and is not a folder")
    try:
        output.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise BagExportError(f"{output}: cannot create the folder ({error.strerror or error})") from None


def _count(report: BagReport, message: RosMessage) -> None:
    if not report.counts:
        report.start_ns = message.stamp_ns
    report.counts[message.topic] += 1
    report.types[message.topic] = message.type_name
    report.start_ns = min(report.start_ns, message.stamp_ns)
    report.end_ns = max(report.end_ns, message.stamp_ns)


class _BagWriter:
    """One MCAP file as rosbag2 writes it: profile ``ros2``, a ``ros2msg`` schema per type, a ``cdr`` channel per
    topic with its QoS and type hash in the channel metadata."""

    def __init__(self, stream) -> None:
        self._writer = Writer(stream, compression=CompressionType.ZSTD)
        self._writer.start(profile="ros2", library=LIBRARY)
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._sequences: Counter[str] = Counter()

    def write(self, message: RosMessage) -> None:
        channel = self._channel(message.topic, message.type_name)
        self._writer.add_message(
            channel,
            log_time=message.stamp_ns,
            publish_time=message.stamp_ns,
            sequence=self._sequences[message.topic],
            data=cdr.encode(message.type_name, message.message),
        )
        self._sequences[message.topic] += 1

    def _channel(self, topic: str, type_name: str) -> int:
        if topic not in self._channels:
            if type_name not in self._schemas:
                self._schemas[type_name] = self._writer.register_schema(
                    name=type_name, encoding="ros2msg", data=interfaces.message_definition(type_name).encode()
                )
            self._channels[topic] = self._writer.register_channel(
                topic=topic,
                message_encoding="cdr",
                schema_id=self._schemas[type_name],
                metadata={"offered_qos_profiles": _DEFAULT_QOS, "topic_type_hash": interfaces.type_hash(type_name)},
            )
        return self._channels[topic]

    def finish(self) -> None:
        self._writer.finish()


def _metadata(report: BagReport) -> dict:
    """``metadata.yaml`` of format 8 (what ``ros2 bag info`` and rosbags read first)."""
    duration = {"nanoseconds": report.end_ns - report.start_ns}
    starting_time = {"nanoseconds_since_epoch": report.start_ns}
    return {
        "rosbag2_bagfile_information": {
            "version": METADATA_VERSION,
            "storage_identifier": "mcap",
            "duration": duration,
            "starting_time": starting_time,
            "message_count": report.messages,
            "topics_with_message_count": [
                {
                    "topic_metadata": {
                        "name": topic,
                        "type": report.types[topic],
                        "serialization_format": "cdr",
                        "offered_qos_profiles": _DEFAULT_QOS,
                        "type_description_hash": interfaces.type_hash(report.types[topic]),
                    },
                    "message_count": count,
                }
                for topic, count in sorted(report.counts.items())
            ],
            "compression_format": "",
            "compression_mode": "",
            "relative_file_paths": [report.mcap.name],
            "files": [
                {
                    "path": report.mcap.name,
                    "starting_time": starting_time,
                    "duration": duration,
                    "message_count": report.messages,
                }
            ],
            "custom_data": {"drivebench.source": "drivebench recorder export --ros2"},
            "ros_distro": ROS_DISTRO,
        }
    }
