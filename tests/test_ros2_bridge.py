"""Integration: ``drivebench run --ros2 --brain ros2`` on rmw_zenoh's keys, seen and driven by a plain Zenoh session
in the test playing a ROS 2 node (real processes, real Zenoh on loopback, no ROS 2 install).

The test joins the run's router, subscribes to everything of ROS 2 domain 7 and to the liveliness tokens under
``@ros2_lv``, and answers every image the ``ros2`` brain publishes with a Twist that rosbags' serializer wrote, on
``/cmd_vel``'s key. What it checks is written from the design document and ROS 2's published type hashes
(``test_ros2_interfaces.ROS2_HASHES``), not from drivebench's key builders.
"""

from __future__ import annotations

import json
import os
import queue
import re
import struct
import subprocess
import sys
import threading
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import pytest
from needs import require
from support.waits import wait_for_file
from test_ros2_interfaces import ROS2_HASHES

ROOT = Path(__file__).resolve().parent.parent
DOMAIN = 7  # not the default 0: the flag must reach every key and token
WIDTH_PX, HEIGHT_PX = 80, 60
SIM_SECONDS = 2.0
STEPS = 40  # 2 s of sim at the simulator's 20 Hz
SPEED_MPS, YAW_RATE_RADPS = 2.0, 0.05
IMAGE_DDS = "sensor_msgs::msg::dds_::Image_"
TWIST_DDS = "geometry_msgs::msg::dds_::Twist_"
ODOM_DDS = "nav_msgs::msg::dds_::Odometry_"
CLOCK_DDS = "rosgraph_msgs::msg::dds_::Clock_"
STRING_DDS = "std_msgs::msg::dds_::String_"
BRAIN_IMAGE_KEY = f"{DOMAIN}/camera/brain/image_raw/{IMAGE_DDS}/{ROS2_HASHES['sensor_msgs/msg/Image']}"
CMD_VEL_KEY = f"{DOMAIN}/cmd_vel/{TWIST_DDS}/{ROS2_HASHES['geometry_msgs/msg/Twist']}"
TEST_GID = bytes(range(16))


@dataclass
class Seen:
    """What the test's ROS 2 side saw: samples by key (payload, attachment) and liveliness tokens."""

    samples: dict[str, list[tuple[bytes, bytes | None]]] = field(default_factory=lambda: defaultdict(list))
    tokens: set[str] = field(default_factory=set)
    images: queue.Queue = field(default_factory=queue.Queue)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def on_sample(self, sample) -> None:
        key = str(sample.key_expr)
        attachment = sample.attachment.to_bytes() if sample.attachment is not None else None
        with self.lock:
            self.samples[key].append((sample.payload.to_bytes(), attachment))
        if key == BRAIN_IMAGE_KEY:
            self.images.put(sample.payload.to_bytes())

    def on_token(self, sample) -> None:
        with self.lock:
            self.tokens.add(str(sample.key_expr))


@dataclass
class Ros2Run:
    seen: Seen
    score: dict
    answered: int
    typestore: object


def _twist_cdr(typestore) -> bytes:
    vector = typestore.types["geometry_msgs/msg/Vector3"]
    twist = typestore.types["geometry_msgs/msg/Twist"](
        linear=vector(x=SPEED_MPS, y=0.0, z=0.0), angular=vector(x=0.0, y=0.0, z=YAW_RATE_RADPS)
    )
    return bytes(typestore.serialize_cdr(twist, "geometry_msgs/msg/Twist"))


def _answer_images(session, seen: Seen, run: subprocess.Popen, twist: bytes) -> int:
    """A Twist on /cmd_vel for every image of the ros2 brain, until the run exits; how many were sent."""
    publisher = session.declare_publisher(CMD_VEL_KEY)
    answered = 0
    while run.poll() is None:
        try:
            seen.images.get(timeout=0.2)
        except queue.Empty:
            continue
        answered += 1  # rmw_zenoh's attachment: sequence, source time, GID length and GID
        publisher.put(twist, attachment=struct.pack("<qqB", answered, 0, 16) + TEST_GID)
    return answered


@pytest.mark.parametrize(
    ("argv", "env", "message"),
    [
        (["--ros2", "--ros-domain-id", "999"], {}, "--ros-domain-id 999: a ROS 2 domain id is an integer 0..232"),
        (["--ros2"], {"ROS_DOMAIN_ID": "abc"}, "ROS_DOMAIN_ID: a ROS 2 domain id is an integer 0..232, got 'abc'"),
        (["--brain", "ros2"], {"ROS_DOMAIN_ID": "-1"}, "ROS_DOMAIN_ID: a ROS 2 domain id is an integer 0..232"),
        (["--ros2", "--ros2-option", "camera_topc=/x"], {}, "unknown key 'camera_topc' .*did you mean 'camera_topic'"),
        (["--ros2", "--ros2-option", "command_topic=/cmd"], {}, "command_topic must contain {brain}"),
        (["--ros2-option", "node=x"], {}, "--ros2-option needs --ros2"),
        (["--attach", "--ros2"], {}, "--ros2 cannot be used with --attach"),
    ],
)
def test_ros2_mistakes_are_one_line_before_anything_starts(argv, env, message, tmp_path):
    result = subprocess.run(
        [sys.executable, "-m", "orchestrator.cli", "run", *argv, "--out", str(tmp_path / "run")],
        cwd=ROOT,
        env={**os.environ, **env},
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 2, result.stderr
    (line,) = result.stderr.strip().splitlines()
    assert re.search(message, line), line
    assert not (tmp_path / "run" / "logs").exists()  # nothing started


def _start_run(argv: list[str], *, out: Path, env: dict[str, str]) -> subprocess.Popen:
    command = [sys.executable, "-m", "orchestrator.cli", "run", *argv, "--out", str(out), "--json"]
    return subprocess.Popen(command, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _join(zenoh, run: subprocess.Popen, *, out: Path):
    """A plain Zenoh client session on the router of the run writing to ``out``, once its stack is up."""
    stack = wait_for_file(out / "stack.json", timeout_s=120, alive=lambda: _exited(run))
    config = zenoh.Config()
    config.insert_json5("mode", '"client"')
    config.insert_json5("connect/endpoints", json.dumps([json.loads(stack)["router"]]))
    config.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(config)


def _finish(run: subprocess.Popen) -> dict:
    """The run's score, once it exits (killed if it does not within a minute)."""
    try:
        stdout, stderr = run.communicate(timeout=60)
    finally:
        if run.poll() is None:
            run.kill()
            run.wait()
    assert run.returncode == 0, stderr[-3000:]
    return json.loads(stdout)


@pytest.fixture(scope="module")
def ros2_run(tmp_path_factory) -> Ros2Run:
    zenoh = require("zenoh")
    typesys = require("rosbags.typesys")
    typestore = typesys.get_typestore(typesys.Stores.ROS2_JAZZY)
    out = tmp_path_factory.mktemp("ros2") / "run"
    argv = ["--ros2", "--ros-domain-id", str(DOMAIN), "--brain", "ros2", "--camera", f"{WIDTH_PX}x{HEIGHT_PX}"]
    argv += ["--max-sim-seconds", str(SIM_SECONDS), "--brain-timeout", "60"]
    run = _start_run(argv, out=out, env={**os.environ, "ROS_DOMAIN_ID": "3"})  # the flag wins over the variable
    try:
        seen = Seen()
        with _join(zenoh, run, out=out) as session:
            # History: the tokens declared before the test joined (the bridge's and the brain's, at start-up).
            tokens = session.liveliness().declare_subscriber(f"@ros2_lv/{DOMAIN}/**", seen.on_token, history=True)
            data = session.declare_subscriber(f"{DOMAIN}/**", seen.on_sample)
            answered = _answer_images(session, seen, run, _twist_cdr(typestore))
            tokens.undeclare()
            data.undeclare()
    finally:
        score = _finish(run)
    return Ros2Run(seen=seen, score=score, answered=answered, typestore=typestore)


def _exited(run: subprocess.Popen) -> str | None:
    return None if run.poll() is None else f"drivebench run exited with {run.returncode}: {run.stderr.read()[-2000:]}"


@pytest.mark.integration
def test_a_ros2_node_drives_the_car_one_twist_per_frame(ros2_run):
    score = ros2_run.score
    assert score["brain"] == "ros2" and score["reason"] == "time_limit"
    assert score["metrics"]["steps"] == STEPS
    assert ros2_run.answered == STEPS  # lock-step: one image out, one Twist back, for every frame
    assert score["metrics"]["progress_m"] > 0
    assert score["metrics"]["average_speed_mps"] > 0


@pytest.mark.integration
def test_the_keys_carry_ros2s_hashes_and_decode_in_rosbags(ros2_run):
    samples, typestore = ros2_run.seen.samples, ros2_run.typestore
    bridge_camera = f"{DOMAIN}/camera/image_raw/{IMAGE_DDS}/{ROS2_HASHES['sensor_msgs/msg/Image']}"
    odom = f"{DOMAIN}/odom/{ODOM_DDS}/{ROS2_HASHES['nav_msgs/msg/Odometry']}"
    clock = f"{DOMAIN}/clock/{CLOCK_DDS}/{ROS2_HASHES['rosgraph_msgs/msg/Clock']}"
    commands = f"{DOMAIN}/brain/ros2/cmd_vel/{TWIST_DDS}/{ROS2_HASHES['geometry_msgs/msg/Twist']}"
    assert {bridge_camera, BRAIN_IMAGE_KEY, odom, clock, commands, CMD_VEL_KEY} <= set(samples)
    assert len(samples[BRAIN_IMAGE_KEY]) == STEPS

    for key in (bridge_camera, BRAIN_IMAGE_KEY):
        image = typestore.deserialize_cdr(samples[key][-1][0], "sensor_msgs/msg/Image")
        assert (image.width, image.height, image.encoding, image.step) == (WIDTH_PX, HEIGHT_PX, "rgb8", WIDTH_PX * 3)
        assert len(image.data) == WIDTH_PX * HEIGHT_PX * 3
    twists = [typestore.deserialize_cdr(payload, "geometry_msgs/msg/Twist") for payload, _ in samples[commands]]
    assert {(t.linear.x, t.angular.z) for t in twists} == {(SPEED_MPS, YAW_RATE_RADPS)}  # the node's, passed on
    ticks = [typestore.deserialize_cdr(payload, "rosgraph_msgs/msg/Clock").clock for payload, _ in samples[clock]]
    stamps_ns = [tick.sec * 1_000_000_000 + tick.nanosec for tick in ticks]
    assert stamps_ns == sorted(stamps_ns) and stamps_ns[-1] == int(SIM_SECONDS * 1e9)  # simulated time, in order
    odometry = typestore.deserialize_cdr(samples[odom][-1][0], "nav_msgs/msg/Odometry")
    assert (odometry.header.frame_id, odometry.child_frame_id) == ("world", "car")
    events = f"{DOMAIN}/episode/events/std_msgs::msg::dds_::String_/{ROS2_HASHES['std_msgs/msg/String']}"
    texts = [typestore.deserialize_cdr(payload, "std_msgs/msg/String").data for payload, _ in samples[events]]
    assert json.loads(texts[0])["kind"] == "start"  # drivebench's JSON, as the bags carry it


@pytest.mark.integration
def test_every_put_carries_rmw_zenohs_attachment(ros2_run):
    for key, puts in ros2_run.seen.samples.items():
        if key == CMD_VEL_KEY:
            continue  # the test's own
        sequences, gids = [], set()
        for _, attachment in puts:
            assert attachment is not None and len(attachment) == 33, key  # int64, int64, GID length, 16-byte GID
            sequence, stamp_ns, gid_length = struct.unpack_from("<qqB", attachment)
            assert gid_length == 16 and stamp_ns > 1_700_000_000 * 10**9, key  # source time: ns since the epoch
            sequences.append(sequence)
            gids.add(attachment[17:])
        # Each publisher counts its own puts, one by one (the bridge's first ones may precede the test's subscription).
        assert sequences == list(range(sequences[0], sequences[0] + len(puts))), key
        assert len(gids) == 1, key


@pytest.mark.integration
def test_liveliness_tokens_announce_the_nodes_and_every_topic(ros2_run):
    tokens = ros2_run.seen.tokens
    entities = [token.split("/") for token in tokens]
    for token in entities:
        assert token[:2] == ["@ros2_lv", str(DOMAIN)] and token[6:8] == ["%", "%"], token  # no enclave, no namespace
    nodes = {token[8] for token in entities if token[5] == "NN"}
    assert nodes == {"drivebench_bridge", "drivebench_brain"}
    endpoints = {(token[5], token[8], token[9], token[10], token[11]) for token in entities if len(token) > 9}
    image_hash, twist_hash = ROS2_HASHES["sensor_msgs/msg/Image"], ROS2_HASHES["geometry_msgs/msg/Twist"]
    expected = {
        ("MP", "drivebench_bridge", "%camera%image_raw", IMAGE_DDS, image_hash),
        ("MP", "drivebench_bridge", "%odom", ODOM_DDS, ROS2_HASHES["nav_msgs/msg/Odometry"]),
        ("MP", "drivebench_bridge", "%clock", CLOCK_DDS, ROS2_HASHES["rosgraph_msgs/msg/Clock"]),
        ("MP", "drivebench_bridge", "%brain%ros2%cmd_vel", TWIST_DDS, twist_hash),
        ("MP", "drivebench_bridge", "%episode%events", STRING_DDS, ROS2_HASHES["std_msgs/msg/String"]),
        ("MP", "drivebench_brain", "%camera%brain%image_raw", IMAGE_DDS, image_hash),
        ("MS", "drivebench_brain", "%cmd_vel", TWIST_DDS, twist_hash),
    }
    assert expected <= endpoints
    # Beyond those, only the JSON topics whose first message may or may not come before the run stops.
    later = {("MP", "drivebench_bridge", topic, STRING_DDS) for topic in ("%metrics%live", "%episode%score")}
    assert {endpoint[:4] for endpoint in endpoints - expected} <= later


@pytest.mark.integration
def test_a_ros2_node_that_does_not_answer_ends_the_episode_with_the_brain_timeout(tmp_path):
    zenoh = require("zenoh")
    env = {key: value for key, value in os.environ.items() if key != "ROS_DOMAIN_ID"}  # ROS 2's default: domain 0
    argv = ["--brain", "ros2", "--camera", "64x48", "--max-sim-seconds", "5", "--brain-timeout", "1"]
    run = _start_run(argv, out=tmp_path / "run", env=env)
    images: queue.Queue = queue.Queue()
    try:
        with _join(zenoh, run, out=tmp_path / "run") as session:
            image_key = f"0/camera/brain/image_raw/{IMAGE_DDS}/{ROS2_HASHES['sensor_msgs/msg/Image']}"
            subscriber = session.declare_subscriber(image_key, lambda sample: images.put(str(sample.key_expr)))
            run.wait(timeout=120)  # the test never answers: the simulator's brain timeout ends the episode
            subscriber.undeclare()
    finally:
        score = _finish(run)
    assert score["reason"] == "brain_timeout" and score["metrics"]["steps"] == 0
    assert images.qsize() == 1  # frame 0 went out, and nothing after it: lock-step waited for its answer
