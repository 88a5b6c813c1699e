"""Live view limits (``services.viz.gate``): a cap on viewers, and a slow viewer's backlog bounded in bytes, with real
Foxglove WebSocket clients on a real bridge (no bus needed: the bridge is fed directly)."""

from __future__ import annotations

import socket
import time

import cv2
import numpy as np
import pytest
from support.viewers import MESSAGE_DATA, SUBPROTOCOL, StuckClient, foxglove_client
from support.waits import wait_for
from websockets.exceptions import InvalidStatus
from websockets.frames import Opcode
from websockets.sync.client import connect

from protocol import keys
from protocol.mapping import topics
from protocol.messages import CameraFrame, Header
from services.viz.bridge import LiveBridge


def noisy_frame(seq: int) -> CameraFrame:
    """320x240 of noise: a JPEG of ~100 kB, as big as the perturbed camera gets."""
    pixels = np.random.default_rng(seq).integers(0, 256, (240, 320, 3), dtype=np.uint8)
    return CameraFrame(
        header=Header(run_id="r", episode=0, seq=seq, stamp_ns=seq * 50_000_000),
        width_px=320,
        height_px=240,
        data=pixels.tobytes(),
    )


def test_viewers_beyond_the_cap_are_refused_and_let_in_once_one_leaves():
    bridge = LiveBridge(run_id="r", host="127.0.0.1", port=0, backlog=100, max_viewers=2, backlog_bytes=1_000_000)
    try:
        with foxglove_client(bridge.port) as first, foxglove_client(bridge.port) as second:
            for client in (first, second):
                client.wait_for_channels({topics.CAMERA_TRUTH, topics.CIRCUIT})
            with pytest.raises(InvalidStatus) as refused:
                connect(f"ws://127.0.0.1:{bridge.port}", subprotocols=[SUBPROTOCOL], open_timeout=10)
            assert refused.value.response.status_code == 503
            assert b"2 viewers already connected (max_viewers)" in refused.value.response.body
            assert (bridge.gate.stats.viewers, bridge.gate.stats.refused) == (2, 1)
            # The two let in still get their messages.
            bridge.publish_frame(keys.camera_raw("r"), noisy_frame(0))
            wait_for(
                lambda: first.messages[topics.CAMERA_TRUTH] and second.messages[topics.CAMERA_TRUTH],
                timeout_s=10.0,
                what="camera frames at both viewers",
            )
        wait_for(lambda: bridge.gate.stats.viewers == 0, timeout_s=10.0, what="no viewer left at the gate")
        with foxglove_client(bridge.port) as third:
            third.wait_for_channels({topics.CAMERA_TRUTH})
        assert (bridge.gate.stats.served, bridge.gate.stats.refused) == (3, 1)
    finally:
        bridge.close()


def test_a_port_already_taken_is_one_clear_error():
    from services.viz.bridge import BridgeError

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        with pytest.raises(BridgeError, match=rf"cannot serve Foxglove WebSocket on 127.0.0.1:{port}: .*in use"):
            LiveBridge(run_id="r", host="127.0.0.1", port=port, backlog=10, max_viewers=2, backlog_bytes=100_000)


def read_everything(stuck: StuckClient, *, quiet_s: float = 1.0) -> tuple[list[bytes], bool]:
    """The messageData payloads a stuck viewer can still read, parsed as a viewer does; (payloads, closed)."""
    stuck.sock.settimeout(quiet_s)
    payloads, closed = [], False
    stuck.bytes_read = 0
    try:
        while data := stuck.sock.recv(1 << 20):
            stuck.bytes_read += len(data)
            stuck.protocol.receive_data(data)
            payloads += [
                event.data[13:]
                for event in stuck.protocol.events_received()
                if getattr(event, "opcode", None) == Opcode.BINARY and event.data[0] == MESSAGE_DATA
            ]
        closed = True
    except TimeoutError:
        pass
    return payloads, closed


def flood_a_stuck_viewer(*, backlog_bytes: int | None, frames: int = 200) -> tuple[LiveBridge, list[bytes], bool]:
    """Send ``frames`` noisy JPEGs to a viewer that never reads; then read what it was still sent."""
    # backlog (messages) far above the frames sent: only the byte budget (if any) can drop.
    bridge = LiveBridge(run_id="r", host="127.0.0.1", port=0, backlog=100_000, backlog_bytes=backlog_bytes)
    try:
        stuck = StuckClient(bridge.port, {topics.CAMERA_TRUTH})
        # The server attaches a viewer's sink to the channel only after its subscribe callback (see LiveBridge):
        # the channel having a sink is when frames start to reach the viewer.
        camera = bridge._bus_channel(keys.camera_raw("r"), CameraFrame)
        wait_for(camera.has_sinks, timeout_s=10.0, what="the stuck viewer's subscription to the camera")
        for seq in range(frames):
            assert bridge.publish_frame(keys.camera_raw("r"), noisy_frame(seq))
        time.sleep(1.0)
        payloads, closed = read_everything(stuck)
        stuck.close()
    finally:
        bridge.close()
    return bridge, payloads, closed


def test_a_slow_viewers_backlog_is_bounded_in_bytes_and_its_stream_stays_valid():
    budget = 500_000
    frames = 200
    gated, payloads, closed = flood_a_stuck_viewer(backlog_bytes=budget, frames=frames)
    _, unbounded_payloads, _ = flood_a_stuck_viewer(backlog_bytes=None, frames=frames)
    stats = gated.gate.stats
    jpeg_kb = np.mean([len(p) for p in unbounded_payloads]) / 1e3
    print(
        f"\n{frames} JPEGs of {jpeg_kb:.0f} kB to a viewer that never reads: with backlog_bytes {budget}, "
        f"peak backlog {stats.peak_backlog_bytes} bytes, {stats.dropped_messages} dropped "
        f"({stats.dropped_bytes / 1e6:.1f} MB), {len(payloads)} still readable afterwards "
        f"({sum(map(len, payloads)) / 1e6:.1f} MB: the kernel's socket buffers plus the backlog); without the "
        f"byte bound (backlog of 100000 messages) {len(unbounded_payloads)} "
        f"({sum(map(len, unbounded_payloads)) / 1e6:.1f} MB)"
    )
    assert len(unbounded_payloads) == frames  # the message bound alone held every frame for the stuck viewer
    assert 0 < stats.peak_backlog_bytes <= budget
    assert stats.dropped_messages > 0 and len(payloads) + stats.dropped_messages == frames
    assert not closed  # still connected, and every frame it reads is whole: dropping never broke the stream
    from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage

    for payload in payloads:
        jpeg = CompressedImage.FromString(payload).data
        assert cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR).shape == (240, 320, 3)
    assert sum(map(len, payloads)) < sum(map(len, unbounded_payloads)) / 2
