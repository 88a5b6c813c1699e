"""The live view: real Foxglove WebSocket clients (``websockets``, subprotocol ``foxglove.sdk.v1``) on a real stack.

Messages are parsed the way a viewer does: text ops (``serverInfo``, ``advertise``), binary ``messageData`` frames
(opcode 1, uint32 subscription id, uint64 log time in ns, payload), protobuf decoded with foxglove_schemas_protobuf,
JPEG with OpenCV, JSON with ``json``.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest
from support.env import clean_env
from support.recordings import expected_schemas
from support.viewers import StuckClient, foxglove_client
from support.waits import wait_for

from orchestrator.stack.launcher import free_loopback_port
from protocol import keys
from protocol.bus import Bus, BusConfig, Inbox
from protocol.episode_spec import CameraSpec, EpisodeSpec, SaltPepper
from protocol.mapping import topics
from protocol.messages import CameraFrame, Command, ControlRequest, EndReason, Header

ROOT = Path(__file__).resolve().parents[1]
CAMERA = CameraSpec(width_px=320, height_px=240)


# -- a Foxglove WebSocket client -------------------------------------------------------------------------------------


# -- the viz process -------------------------------------------------------------------------------------------------


@dataclass
class Viz:
    process: subprocess.Popen
    port: int
    log_path: Path

    def rss_mb(self) -> float:
        for line in Path(f"/proc/{self.process.pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
        raise AssertionError("no VmRSS")

    def cpu_s(self) -> float:
        """User + system CPU seconds the process has used."""
        fields = Path(f"/proc/{self.process.pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")

    def log(self) -> str:
        return self.log_path.read_text(errors="replace")


@contextmanager
def viz_process(stack, *extra: str):
    port = free_loopback_port()
    log_path = stack.run_dir / "logs" / "viz.log"
    token = keys.alive(stack.run_id, "viz", "viz")
    watch = stack.bus.watch_alive(token)
    with open(log_path, "ab") as log_file:
        process = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "services.viz",
                "--router",
                stack.endpoint,
                "--run-id",
                stack.run_id,
                "--set",
                f"port={port}",
                *extra,
            ],
            cwd=ROOT,
            stdout=log_file,
            stderr=subprocess.STDOUT,
        )
    viz = Viz(process, port, log_path)
    try:
        missing = watch.wait_for({token}, timeout_s=30, abort=lambda: "dead" if process.poll() is not None else None)
        watch.close()
        assert not missing, f"viz did not come up ({process.poll()}): {viz.log()}"
        yield viz
    finally:
        process.send_signal(signal.SIGTERM)
        try:
            code = process.wait(timeout=20)
            assert code == 128 + signal.SIGTERM, f"exit code {code}: {viz.log()}"
        finally:
            if process.poll() is None:
                process.kill()


def decode_jpeg_image(payload: bytes) -> np.ndarray:
    from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage

    image = CompressedImage()
    image.ParseFromString(payload)  # the stock schema: the drivebench extra fields are skipped as unknown
    assert image.format == "jpeg" and image.frame_id == "camera"
    pixels = cv2.imdecode(np.frombuffer(image.data, np.uint8), cv2.IMREAD_COLOR)
    assert pixels is not None, "not a JPEG"
    return pixels


# -- tests -------------------------------------------------------------------------------------------------------------


@pytest.mark.integration
def test_a_viewer_gets_jpeg_camera_at_the_camera_rate_and_every_channel(make_stack):
    stack = make_stack()
    run = stack.run_id
    views = {name: topics.view_topic(name) for name in ("car_pose", "world_from_car", "track", "episode_log")}
    camera, command = topics.CAMERA_TRUTH, topics.command_topic("explicit")
    # The stable topic set, the same as a recording's (tests/test_topics.py): one layout shows both.
    published = topics.run_topics(brains=("explicit",))
    with viz_process(stack) as viz, foxglove_client(viz.port) as client:
        client.wait_for_channels(published)
        assert set(client.channels) == published
        assert {t: c["schemaName"] for t, c in client.channels.items()} == expected_schemas(published, image="jpeg")
        assert client.server_info["name"] == f"drivebench {run}"
        advertised = client.channels[camera]
        assert (advertised["encoding"], advertised["schemaName"], advertised["schemaEncoding"]) == (
            "protobuf",
            "foxglove.CompressedImage",
            "protobuf",
        )
        assert client.channels[topics.METRICS_LIVE]["schemaEncoding"] == "jsonschema"
        wait_for_viewers(viz, 1)

        frames = Inbox()  # the camera on the bus, as the simulator publishes it
        stack.bus.subscribe(keys.camera_raw(run), CameraFrame, inbox=frames)
        started, cpu_before = time.monotonic(), viz.cpu_s()
        score = stack.run_episode(EpisodeSpec(max_sim_seconds=8.0, camera=CAMERA))
        ended, cpu_used = time.monotonic(), viz.cpu_s() - cpu_before
        on_bus: list = []

        def last_image_arrived() -> bool:
            """The viewer has the score and the image of the last camera frame on the bus (still in flight when
            the episode ended)."""
            on_bus.extend(r for r in frames.drain() if r.message.header.episode == score.header.episode)
            images = client.messages[camera]
            last_on_bus_ns = on_bus[-1].message.header.stamp_ns if on_bus else None
            return bool(client.messages[topics.EPISODE_SCORE] and images and images[-1].log_time_ns == last_on_bus_ns)

        wait_for(last_image_arrived, timeout_s=10.0, what="the score and the last camera image at the viewer")

    assert score.reason == EndReason.TIME_LIMIT
    last_stamp = on_bus[-1].message.header.stamp_ns
    assert [r.message.header.seq for r in on_bus] == list(range(len(on_bus))) and last_stamp >= 7_900_000_000
    images = [m for m in client.messages[camera] if started <= m.arrival <= ended + 1.0]
    seconds = ended - started
    bus_rate, ws_rate = len(on_bus) / seconds, len(images) / seconds
    print(
        f"\ncamera on the bus: {len(on_bus)} frames in {seconds:.2f} s = {bus_rate:.1f} Hz; over the WebSocket: "
        f"{len(images)} images = {ws_rate:.1f} Hz ({100 * ws_rate / bus_rate:.1f} %), "
        f"{sum(len(m.payload) for m in images) / len(images) / 1e3:.1f} kB each; viz CPU {cpu_used:.2f} s "
        f"= {100 * cpu_used / seconds:.0f} % of a core (two cameras encoded)"
    )
    assert ws_rate >= 0.9 * bus_rate
    for image in images:
        assert decode_jpeg_image(image.payload).shape == (CAMERA.height_px, CAMERA.width_px, 3)
    # Log time = sim time (the run's first episode starts at 0): every image on the 50 ms step grid, in order.
    stamps = [image.log_time_ns for image in images]
    assert stamps == sorted(stamps) and all(stamp % 50_000_000 == 0 for stamp in stamps)
    assert stamps[-1] == last_stamp

    # The car on the circuit: pose, transform, and the track drawn once for the episode.
    from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
    from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
    from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate

    poses = [json.loads(m.payload) for m in client.messages[topics.CAR_STATE]]
    assert len(poses) >= 0.9 * len(on_bus) and {"x_m", "y_m", "yaw_rad", "header"} <= set(poses[-1])
    car = PoseInFrame.FromString(client.messages[views["car_pose"]][-1].payload)
    transform = FrameTransform.FromString(client.messages[views["world_from_car"]][-1].payload)
    assert car.frame_id == "world" and (transform.parent_frame_id, transform.child_frame_id) == ("world", "car")
    assert (car.pose.position.x, car.pose.position.y) == pytest.approx((poses[-1]["x_m"], poses[-1]["y_m"]))
    assert (
        client.messages[views["car_pose"]][-1].log_time_ns
        == poses[-1]["header"]["stamp_ns"]
        == car.timestamp.seconds * 1_000_000_000 + car.timestamp.nanos
    )
    tracks = [SceneUpdate.FromString(m.payload) for m in client.messages[views["track"]]]
    assert 1 <= len(tracks) <= 2  # once for the episode (and once more if the subscription came after it)
    assert [entity.id for entity in tracks[-1].entities] == ["track", "car"] and len(tracks[-1].entities[0].lines) >= 2

    # Commands of the brain, live metrics, events and the score: JSON a viewer can plot.
    commands = [json.loads(m.payload) for m in client.messages[command]]
    assert len(commands) >= 0.9 * len(on_bus) and commands[-1]["brain"] == "explicit" and "speed_mps" in commands[-1]
    live = [json.loads(m.payload) for m in client.messages[topics.METRICS_LIVE]]
    assert live and live[-1]["real_time_factor"] > 0 and live[-1]["laps_target"] == 1
    events = [json.loads(m.payload) for m in client.messages[topics.EPISODE_EVENTS]]
    assert [event["kind"] for event in events] == ["start", "end"] and events[0]["spec"]["circuit"] == "simple"
    from foxglove_schemas_protobuf.Log_pb2 import Log

    log_lines = [Log.FromString(m.payload).message for m in client.messages[views["episode_log"]]]
    assert log_lines[0].startswith("episode 0: start circuit simple") and "end reason time_limit" in log_lines[-1]
    scores = [json.loads(m.payload) for m in client.messages[topics.EPISODE_SCORE]]
    assert len(scores) == 1 and scores[0]["reason"] == "time_limit"
    perturbed = client.messages[topics.CAMERA_BRAIN]  # the stack's noise injector publishes one
    assert perturbed and decode_jpeg_image(perturbed[-1].payload).shape == (CAMERA.height_px, CAMERA.width_px, 3)


def test_channels_added_while_viewers_connect_reach_them():
    """A brain that comes up while viewers connect gets a command channel they subscribe to at once, as Foxglove
    does. foxglove-sdk 0.30 refuses some of these subscriptions (a few in 30 here); the bridge then advertises the
    channel again, and every viewer gets its messages."""
    from services.viz.bridge import LiveBridge

    bridge = LiveBridge(run_id="r", host="127.0.0.1", port=0, backlog=1000)
    brains = [f"brain{i}" for i in range(30)]
    try:
        with ExitStack() as viewers:
            clients = []
            for brain in brains:  # a viewer connects, and a brain comes up
                clients.append(viewers.enter_context(foxglove_client(bridge.port)))
                bridge.advertise_command(brain)
            deadline, seq = time.monotonic() + 15, 0
            while missing := [b for b in brains if not all(c.messages[topics.command_topic(b)] for c in clients)]:
                assert time.monotonic() < deadline, f"never reached every viewer: {missing}"
                bridge.maintain()
                for brain in brains:
                    bridge.publish(
                        keys.command("r", brain),
                        Command(
                            header=Header(run_id="r", episode=0, seq=seq, stamp_ns=seq * 50_000_000),
                            brain=brain,
                            frame_seq=seq,
                            speed_mps=1.0,
                            yaw_rate_radps=0.0,
                        ),
                    )
                seq += 1
                time.sleep(0.05)
        print(
            f"\n{len(brains)} channels added as {len(clients)} viewers connected; advertised again after a lost "
            f"subscription: {bridge.readvertised}"
        )
    finally:
        bridge.close()


def wait_for_viewers(viz: Viz, count: int) -> None:
    """Until ``count`` viewers have subscribed, as the viz logs it (a viewer's channels are subscribed in one
    request, handled at once, so its first subscription stands for all of them)."""
    wait_for(
        lambda: viz.log().count(" subscribed (first to ") >= count,
        timeout_s=10.0,
        what=f"{count} viewer(s) subscribed at the viz",
        alive=lambda: None if viz.process.poll() is None else f"the viz exited: {viz.log()[-1500:]}",
    )


def episodes_ended(viz: Viz) -> list[int]:
    """Messages the viz had sent when each episode ended, from its log."""
    return [int(n) for n in re.findall(r"episode \d+ ended; so far: (\d+) messages sent", viz.log())]


def sample_rss(viz: Viz, stop: threading.Event, samples: list[float]) -> None:
    while not stop.is_set():
        samples.append(viz.rss_mb())
        stop.wait(0.1)


@pytest.mark.integration
def test_a_viewer_that_never_reads_slows_nothing_and_costs_bounded_memory(make_stack):
    stack = make_stack()
    everything = {
        topics.CAMERA_TRUTH,
        topics.CAMERA_BRAIN,
        topics.CAR_STATE,
        topics.command_topic("explicit"),
        topics.CIRCUIT,
    }
    # Salt and pepper makes the perturbed camera's JPEGs big (~50 kB): an episode then sends far more than the
    # kernel's socket buffers hold (a few MB), so the server's per-client backlog really fills and drops.
    spec = EpisodeSpec(max_sim_seconds=8.0, camera=CAMERA, noise=[SaltPepper(probability=0.2)])
    backlog = 120
    with viz_process(stack, "--set", f"backlog={backlog}") as viz:
        alone = stack.run_episode(spec)  # the viz serves nobody
        with foxglove_client(viz.port) as reader:  # a viewer that keeps up, subscribed to every channel
            reader.wait_for_channels(everything)
            wait_for_viewers(viz, 1)
            reading = stack.run_episode(spec)
        rss_before = viz.rss_mb()

        # The same viewer, but it never reads: its messages pile up in the kernel, then in the server's backlog.
        stuck = StuckClient(viz.port, everything)
        wait_for_viewers(viz, 2)
        samples: list[float] = []
        stop = threading.Event()
        sampler = threading.Thread(target=sample_rss, args=(viz, stop, samples), daemon=True)
        sampler.start()
        with_stuck = stack.run_episode(spec)
        stop.set()
        sampler.join()
        wait_for(lambda: len(episodes_ended(viz)) == 3, timeout_s=10.0, what="the viz's count of the third episode")
        read_late, closed = stuck.drain()  # what the socket buffers and the backlog still held
        stuck.close()
    sent = episodes_ended(viz)
    sent_while_stuck = sent[2] - sent[1]
    rtf = {
        name: score.metrics.real_time_factor
        for name, score in (("alone", alone), ("reading", reading), ("stuck", with_stuck))
    }
    half = len(samples) // 2
    noisy = reader.messages[topics.CAMERA_BRAIN]
    print(
        f"\nreal-time factor: {rtf['alone']:.2f} with no viewer, {rtf['reading']:.2f} with a viewer reading every "
        f"channel, {rtf['stuck']:.2f} with one that never reads ({100 * rtf['stuck'] / rtf['reading']:.0f} % of "
        f"reading, {100 * rtf['stuck'] / rtf['alone']:.0f} % of none); viz RSS {rss_before:.1f} MB before, max "
        f"{max(samples):.1f} MB (first half {max(samples[:half]):.1f}, second half {max(samples[half:]):.1f}); "
        f"sent to the stuck viewer {sent_while_stuck} messages (the reader got {len(noisy)} noisy images, "
        f"{sum(len(m.payload) for m in noisy) / 1e6:.1f} MB), of which it could still read {read_late} "
        f"({stuck.bytes_read / 1e6:.1f} MB) afterwards"
    )
    assert alone.reason == reading.reason == with_stuck.reason == EndReason.TIME_LIMIT
    assert with_stuck.metrics.steps == alone.metrics.steps  # lock-step: nothing lost either
    # Generous: 2 cores shared by simulator, brain, noise, scorer, viz and this test; episodes vary by ~20 %.
    assert rtf["stuck"] >= 0.6 * rtf["reading"]
    assert max(samples) < rss_before + 60  # the backlog: 120 messages, at most ~50 kB each, plus the encoders
    assert max(samples[half:]) < max(samples[:half]) + 15  # flat: it does not grow with the messages sent
    # Still connected; what did not fit its backlog (120 messages in the server, 4 MB in the gate) was dropped.
    assert not closed and read_late < sent_while_stuck
    gate = re.findall(r"(\d+) messages \((\d+) bytes\) dropped for slow viewers; peak backlog (\d+) bytes", viz.log())
    assert int(gate[-1][2]) <= 4_000_000


# -- drivebench view -----------------------------------------------------------------------------------------------


def view(*argv: str) -> int:
    """``drivebench view ARGV...``: its exit code."""
    from orchestrator.cli import main

    return main(["view", *argv])


def one_error_line(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    return err


def test_view_without_a_router_says_so_in_one_line(capsys, monkeypatch):
    monkeypatch.delenv("DRIVEBENCH_ROUTER", raising=False)
    assert view() == 2
    assert "no router" in one_error_line(capsys)
    assert view("--router", "tcp/127.0.0.1:7447", "--port", "70000") == 2
    assert "port" in one_error_line(capsys)
    assert view("--router", "tcp/127.0.0.1:7447", "--max-viewers", "0") == 2
    assert "max_viewers must be within 1..1000, got 0" in one_error_line(capsys)
    assert view("--router", "tcp/127.0.0.1:7447", "--backlog-bytes", "10") == 2
    assert "backlog_bytes must be within" in one_error_line(capsys)


@pytest.mark.integration
def test_view_with_no_run_several_runs_or_no_router_listening_says_so_in_one_line(capsys, monkeypatch):
    monkeypatch.delenv("DRIVEBENCH_RUN_ID", raising=False)
    nobody = f"tcp/127.0.0.1:{free_loopback_port()}"
    assert view("--router", nobody) == 1
    assert f"router {nobody} not reachable" in one_error_line(capsys)

    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    with Bus(BusConfig(mode="router", listen=[endpoint]), name="test-router") as bus:
        monkeypatch.setenv("DRIVEBENCH_ROUTER", endpoint)
        assert view() == 1
        assert "no run is alive" in one_error_line(capsys)
        bus.declare_alive(keys.alive("run-a", "simulator", "sim"))
        bus.declare_alive(keys.alive("run-b", "simulator", "sim"))
        assert view() == 1
        assert "2 runs are alive" in (line := one_error_line(capsys)) and "run-a, run-b" in line


@pytest.mark.integration
def test_view_joins_the_only_run_mid_episode_draws_its_circuit_and_stops_on_sigterm(make_stack):
    from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate

    stack = make_stack()
    run = stack.run_id
    under_way = threading.Event()
    # Real time, many laps: the episode lasts its 600 s of wall time whatever the machine's speed (in lock-step a
    # fast machine drove its lap before the view had joined), until the test stops it.
    spec = EpisodeSpec(laps=100, max_sim_seconds=600.0, realtime=True, camera=CameraSpec(width_px=64, height_px=48))
    episode = threading.Thread(
        target=stack.run_episode, daemon=True, args=(spec,), kwargs={"on_live": lambda live: under_way.set()}
    )
    episode.start()
    # Its first live metrics: the episode is under way, so its START event is gone when the view joins.
    wait_for(under_way.is_set, timeout_s=60, what="the episode's first live metrics")
    port = free_loopback_port()
    env = clean_env()
    view = subprocess.Popen(
        [sys.executable, "-m", "orchestrator.cli", "view", "--router", stack.endpoint, "--port", str(port)],
        cwd=ROOT,
        env=env,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        lines = []
        while not any(line.startswith("drivebench view:") for line in lines):
            line = view.stderr.readline()
            assert line, f"view exited ({view.wait()}): {''.join(lines)}"
            lines.append(line)
        assert f"run {run} via {stack.endpoint}" in lines[-1] and f"ws://127.0.0.1:{port}" in lines[-1]
        with foxglove_client(port) as client:
            wanted = (topics.CIRCUIT, topics.CAMERA_TRUTH, topics.command_topic("explicit"))
            # Generous: with the load at 12 on 2 cores, the first of them once took over 20 s to come.
            wait_for(
                lambda: all(client.messages[topic] for topic in wanted),
                timeout_s=60,
                what=f"messages on each of {wanted} at the viewer",
            )
            track = SceneUpdate.FromString(client.messages[topics.CIRCUIT][0].payload)
            assert track.entities[0].id == "track"  # the circuit, from the spec the simulator gave for episode 0
            assert decode_jpeg_image(client.messages[topics.CAMERA_TRUTH][-1].payload).shape == (48, 64, 3)
        stack._control(ControlRequest(action="stop"))
        episode.join(timeout=30)
        view.send_signal(signal.SIGTERM)
        assert view.wait(timeout=20) == 0
        assert "missed the start of episode 0" in view.stderr.read()
    finally:
        if view.poll() is None:
            view.kill()
