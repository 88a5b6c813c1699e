"""What issue 20's Foxglove pieces cost, side by side in one run.

* **Live view gate** (``services/viz/gate.py``): the same noisy 320x240 JPEGs (~70 kB each) to one viewer that reads
  everything, straight from foxglove-sdk's server and through the gate (viewer cap + byte backlog). Wall time until
  the viewer has them all, and CPU seconds of this process (bridge, gate and the viewer's client all live here).
* **Merge** (``recorder/merge.py``): two recordings of ``--steps`` steps (two raw 320x240 cameras, pose, command,
  views) merged into one; messages and MB of raw frames per second.

    .venv/bin/python benchmarks/foxglove_view.py [--frames 300] [--repeats 3] [--steps 300]

Needs ``websockets`` (the test extra).
"""

from __future__ import annotations

import argparse
import json
import resource
import struct
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
from websockets.sync.client import connect
from websockets.typing import Subprotocol

from protocol import keys
from protocol.episode_spec import EpisodeSpec
from protocol.episodes import start_event
from protocol.mapping import topics
from protocol.messages import CameraFrame, Command, Header, Pose
from recorder.merge import merge
from recorder.writer import RecordingWriter
from services.viz.bridge import SUBPROTOCOL, LiveBridge


def cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def header(seq: int, run_id: str = "r") -> Header:
    return Header(run_id=run_id, episode=0, seq=seq, stamp_ns=seq * 50_000_000)


def noisy(seq: int) -> CameraFrame:
    pixels = np.random.default_rng(seq).integers(0, 256, (240, 320, 3), dtype=np.uint8)
    return CameraFrame(header=header(seq), width_px=320, height_px=240, data=pixels.tobytes())


class Viewer:
    """Subscribes to /camera/truth and counts the bytes of the messages it receives, on a thread."""

    def __init__(self, port: int):
        self.ws = connect(f"ws://127.0.0.1:{port}", subprotocols=[Subprotocol(SUBPROTOCOL)], max_size=None)
        self.received, self.bytes = 0, 0
        self.subscribed = threading.Event()
        threading.Thread(target=self._run, daemon=True).start()

    def _run(self) -> None:
        try:
            for message in self.ws:
                if isinstance(message, str):
                    body = json.loads(message)
                    wanted = [c for c in body.get("channels", []) if c["topic"] == topics.CAMERA_TRUTH]
                    if body["op"] == "advertise" and wanted:
                        self.ws.send(
                            json.dumps({"op": "subscribe", "subscriptions": [{"id": 0, "channelId": wanted[0]["id"]}]})
                        )
                        self.subscribed.set()
                elif message[0] == 1 and struct.unpack_from("<I", message, 1)[0] == 0:
                    self.received += 1
                    self.bytes += len(message)
        except Exception:  # closed at the end
            pass


def gate_case(frames: list[CameraFrame], *, gated: bool) -> tuple[float, float, float]:
    """(wall s, CPU s, MB) to deliver ``frames`` to one reading viewer."""
    # Gated: limits so loose that nothing is dropped, to measure the forwarding; no limits: no gate at all.
    bridge = LiveBridge(
        run_id="r",
        host="127.0.0.1",
        port=0,
        backlog=100_000,
        max_viewers=4 if gated else None,
        backlog_bytes=1 << 30 if gated else None,
    )
    try:
        viewer = Viewer(bridge.port)
        assert viewer.subscribed.wait(10)
        time.sleep(0.5)  # the subscription reaches the server
        cpu0, start = cpu_s(), time.perf_counter()
        for frame in frames:
            bridge.publish_frame(keys.camera_raw("r"), frame)
        while viewer.received < len(frames):
            time.sleep(0.002)
        wall, used = time.perf_counter() - start, cpu_s() - cpu0
        viewer.ws.close()
        return wall, used, viewer.bytes / 1e6
    finally:
        bridge.close()


def recording(path: Path, run_id: str, steps: int) -> Path:
    y, x = np.mgrid[0:240, 0:320]
    with RecordingWriter(path) as writer:
        writer.write(keys.events(run_id), start_event(run_id, 0, EpisodeSpec(circuit="simple")))
        for seq in range(steps):
            pixels = np.stack([(x + seq) % 256, (2 * y) % 256, np.full_like(x, 90)], -1).astype(np.uint8).tobytes()
            for key in (keys.camera_raw(run_id), keys.camera_perturbed(run_id)):
                writer.write(key, CameraFrame(header=header(seq, run_id), width_px=320, height_px=240, data=pixels))
            writer.write(keys.pose(run_id), Pose(header=header(seq, run_id), x_m=0.1 * seq, y_m=0.0, yaw_rad=0.0))
            writer.write(
                keys.command(run_id, "explicit"),
                Command(header=header(seq, run_id), brain="explicit", frame_seq=seq, speed_mps=2.0, yaw_rate_radps=0.1),
            )
    return path


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--steps", type=int, default=300)
    args = parser.parse_args()

    frames = [noisy(seq) for seq in range(args.frames)]
    for repeat in range(args.repeats):
        direct, gate = gate_case(frames, gated=False), gate_case(frames, gated=True)
        print(
            f"gate, run {repeat + 1}: {args.frames} JPEGs, {direct[2]:.1f} MB; direct {direct[0]:.2f} s wall, "
            f"{direct[1]:.2f} s CPU; through the gate {gate[0]:.2f} s wall ({gate[0] / direct[0]:.2f}x), "
            f"{gate[1]:.2f} s CPU ({gate[1] / direct[1]:.2f}x)"
        )

    with tempfile.TemporaryDirectory() as folder:
        sources = [recording(Path(folder) / f"{run}.mcap", run, args.steps) for run in ("a", "b")]
        start = time.perf_counter()
        report = merge(sources, output=Path(folder) / "ab.mcap")
        wall = time.perf_counter() - start
        raw_mb = 2 * 2 * args.steps * 320 * 240 * 3 / 1e6
        print(
            f"merge: {report.messages} messages ({raw_mb:.0f} MB of raw frames, "
            f"{sum(s.stat().st_size for s in sources) / 1e6:.1f} MB of zstd files) in {wall:.2f} s: "
            f"{report.messages / wall:.0f} messages/s, {raw_mb / wall:.0f} MB/s of frames"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
