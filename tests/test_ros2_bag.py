"""``drivebench recorder export REC.mcap --ros2 -o DIR``: a real run's recording as a rosbag2 folder, opened by two
readers that are not ours (rosbags, and Foxglove's mcap-ros2-support)."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import pytest
from needs import require
from support.recorder import run_cli

from protocol.mapping import topics
from protocol.mapping.topics import topic_of_key
from protocol.messages import CameraFrame, Command, Pose
from protocol.ros2 import interfaces
from recorder.reading import read_messages

pytestmark = pytest.mark.integration

WIDTH_PX, HEIGHT_PX = 64, 48
EXPECTED_TYPES = {
    "/camera/truth/image_raw": "sensor_msgs/msg/Image",
    "/camera/brain/image_raw": "sensor_msgs/msg/Image",
    "/brain/explicit/cmd_vel": "geometry_msgs/msg/Twist",
    "/odom": "nav_msgs/msg/Odometry",
    "/tf": "tf2_msgs/msg/TFMessage",
    "/clock": "rosgraph_msgs/msg/Clock",
    "/episode/events": "std_msgs/msg/String",
    "/metrics/live": "std_msgs/msg/String",
    "/episode/score": "std_msgs/msg/String",
}


@pytest.fixture(scope="module")
def exported(tmp_path_factory) -> tuple[Path, Path]:
    """A real run of 2 s of simulated time, recorded, then exported: (recording, bag folder)."""
    folder = tmp_path_factory.mktemp("ros2")
    recording = folder / "run.mcap"
    run = run_cli(
        "run",
        "--max-sim-seconds",
        "2",
        "--camera",
        f"{WIDTH_PX}x{HEIGHT_PX}",
        "--record",
        str(recording),
        "--out",
        str(folder / "run"),
        timeout=150,
    )
    assert run.returncode == 0, run.stderr
    bag = folder / "bag"
    export = run_cli("recorder", "export", str(recording), "--ros2", "-o", str(bag))
    assert export.returncode == 0, export.stderr
    assert f"-> {bag}" in export.stderr
    return recording, bag


def _recorded_commands(recording: Path) -> list[Command]:
    return [r.message for r in read_messages(recording) if isinstance(r.message, Command)]


def test_rosbags_opens_the_bag_with_the_standard_types_and_one_twist_per_command(exported):
    recording, bag = exported
    rosbag2 = require("rosbags.rosbag2")
    typesys = require("rosbags.typesys")
    typestore = typesys.get_typestore(typesys.Stores.ROS2_JAZZY)
    with rosbag2.Reader(bag) as reader:
        assert {c.topic: c.msgtype for c in reader.connections} == EXPECTED_TYPES
        assert {c.digest for c in reader.connections if c.msgtype == "geometry_msgs/msg/Twist"} == {
            typestore.hash_rihs01("geometry_msgs/msg/Twist")
        }
        decoded: dict[str, list] = {}
        for connection, stamp_ns, data in reader.messages():
            message = typestore.deserialize_cdr(data, connection.msgtype)
            decoded.setdefault(connection.topic, []).append((stamp_ns, message))
    commands = _recorded_commands(recording)
    twists = [message for _, message in decoded["/brain/explicit/cmd_vel"]]
    assert len(twists) == len(commands) > 10
    assert [(t.linear.x, t.angular.z) for t in twists] == [(c.speed_mps, c.yaw_rate_radps) for c in commands]
    images = [message for _, message in decoded["/camera/truth/image_raw"]]
    truth = [r.message for r in read_messages(recording) if topic_of_key(r.key) == topics.CAMERA_TRUTH]
    assert len(images) == len(truth) and all(isinstance(frame, CameraFrame) for frame in truth)
    assert {(i.width, i.height, i.encoding, i.step) for i in images} == {(WIDTH_PX, HEIGHT_PX, "rgb8", WIDTH_PX * 3)}
    assert images[0].data.tobytes() == truth[0].data
    clock = [stamp for stamp, _ in decoded["/clock"]]
    poses = [r for r in read_messages(recording) if isinstance(r.message, Pose)]
    assert clock == [r.log_time_ns for r in poses] and clock == sorted(clock)  # simulated time, never back
    odometry = decoded["/odom"][-1][1]
    assert odometry.pose.pose.position.x == poses[-1].message.x_m and odometry.child_frame_id == "car"
    assert '"kind":"end"' in decoded["/episode/events"][-1][1].data


def test_mcap_ros2_support_decodes_every_message_from_the_stored_schemas(exported):
    recording, bag = exported
    require("mcap_ros2")
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    counts: Counter[str] = Counter()
    schemas = {}
    with open(bag / f"{bag.name}_0.mcap", "rb") as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        assert reader.get_header().profile == "ros2"
        for schema, channel, _, message in reader.iter_decoded_messages():
            assert (schema.encoding, channel.message_encoding) == ("ros2msg", "cdr")
            assert channel.metadata["topic_type_hash"] == interfaces.type_hash(schema.name)
            counts[channel.topic] += 1
            schemas[channel.topic] = schema.name
            if channel.topic == "/camera/brain/image_raw":
                assert (message.width, message.height, len(message.data)) == (
                    WIDTH_PX,
                    HEIGHT_PX,
                    WIDTH_PX * HEIGHT_PX * 3,
                )
    assert schemas == EXPECTED_TYPES
    assert counts["/brain/explicit/cmd_vel"] == len(_recorded_commands(recording))


def test_metadata_yaml_counts_what_the_mcap_holds(exported):
    import yaml

    _, bag = exported
    info = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    topics = {t["topic_metadata"]["name"]: t for t in info["topics_with_message_count"]}
    assert info["storage_identifier"] == "mcap" and info["relative_file_paths"] == [f"{bag.name}_0.mcap"]
    assert info["message_count"] == sum(t["message_count"] for t in topics.values())
    assert topics["/camera/truth/image_raw"]["topic_metadata"]["type_description_hash"] == (
        "RIHS01_d31d41a9a4c4bc8eae9be757b0beed306564f7526c88ea6a4588fb9582527d47"  # ROS 2's (test_ros2_interfaces)
    )


def test_a_second_export_is_refused_unless_overwrite_and_a_bad_recording_is_one_line(exported, tmp_path):
    recording, bag = exported
    again = run_cli("recorder", "export", str(recording), "--ros2", "-o", str(bag))
    assert (
        again.returncode == 2
        and again.stderr == f"drivebench: error: {bag}: already holds a bag; pass --overwrite to replace it\n"
    )
    missing = run_cli("recorder", "export", str(tmp_path / "nope.mcap"), "--ros2", "-o", str(tmp_path / "b"))
    assert missing.returncode == 2 and "nope.mcap: no such recording" in missing.stderr
    assert len(missing.stderr.strip().splitlines()) == 1 and not (tmp_path / "b").exists()
    replaced = run_cli("recorder", "export", str(recording), "--ros2", "-o", str(bag), "--overwrite")
    assert replaced.returncode == 0, replaced.stderr
