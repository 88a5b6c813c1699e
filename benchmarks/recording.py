"""Recorder throughput: nothing dropped at full rate, and what it costs.

A publisher (this process, which also hosts the router) sends what a lock-step run at 20 Hz sends per step: the
simulator's 640x480 raw frame, the perturbed frame, the pose, the brain's command, and every 10th step live metrics,
for ``--seconds``. A real recorder process (``python -m recorder``) records it. Afterwards every channel's count in
the MCAP file is compared with what was published, and the recorder's CPU use (user + system time from /proc) is
reported as a share of one core, side by side for each image case:

* ``rendered``: real PyBullet frames of the ``simple`` circuit (compress well: the easy case);
* ``noisy``: the same frames with Gaussian noise sigma 6 (what the noise injector makes: the worst case for zstd);
* ``jpeg``: rendered frames recorded with ``image_format=jpeg``.

    .venv/bin/python benchmarks/recording.py [--seconds 20] [--rate-hz 20] [--camera 640x480]
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import msgspec
import numpy as np
from tqdm import tqdm

from orchestrator.stack.launcher import free_loopback_port
from protocol import keys
from protocol.bus import Bus, BusConfig, Publisher, Traffic
from protocol.episode_spec import CameraSpec, EpisodeSpec
from protocol.images import image_frame
from protocol.messages import CameraFrame, Command, EpisodeEvent, EventKind, Header, LiveMetrics, Pose
from recorder.reading import read_messages
from recorder.standalone import RecorderStartError, start_recorder

ROOT = Path(__file__).resolve().parents[1]
CASES = (("rendered", "raw", False), ("noisy", "raw", True), ("jpeg", "jpeg", False))


def rendered_frames(width: int, height: int, count: int = 20) -> list[np.ndarray]:
    """Frames along the start of the simple circuit, rendered by the simulator's scene."""
    from services.simulator.episode import EpisodeSim, SceneCache

    spec = EpisodeSpec(camera=CameraSpec(width_px=width, height_px=height))
    sim = EpisodeSim(spec, scenes=SceneCache())
    frames = []
    for _ in range(count):
        frames.append(sim.render())
        for _ in range(4):
            sim.step(speed_mps=3.0, yaw_rate_radps=0.0)
    return frames


def cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def run_case(
    name: str, image_format: str, images: list[np.ndarray], *, seconds: float, rate_hz: float, folder: Path
) -> dict:
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    run_id = f"bench-{name}"
    output = folder / f"{name}.mcap"
    with Bus(BusConfig(mode="router", listen=[endpoint]), name="bench") as bus:
        try:
            recorder = start_recorder(
                endpoint=endpoint,
                bus=bus,
                run_id=run_id,
                output=output,
                extra_args=("--set", f"image_format={image_format}"),
                cwd=ROOT,
            )
        except RecorderStartError as error:
            raise SystemExit(f"{name}: {error}") from None
        cpu_before = cpu_seconds(recorder.pid)  # start-up (imports) is not recording
        published = publish(bus, run_id, images, seconds=seconds, rate_hz=rate_hz, desc=name)
        time.sleep(1.0)  # let the recorder drain before it is stopped
        cpu = cpu_seconds(recorder.pid) - cpu_before
        recorder.send_signal(signal.SIGTERM)
        recorder.wait(timeout=60)
    recorded: dict[str, int] = {}
    for item in read_messages(output):
        recorded[item.key] = recorded.get(item.key, 0) + 1
    missing = {key: count - recorded.get(key, 0) for key, count in published.items()}
    return {
        "case": name,
        "published": sum(published.values()),
        "missing": sum(missing.values()),
        "missing_by_key": {k.split("/", 3)[3]: v for k, v in missing.items() if v},
        "cpu_share": cpu / seconds,
        "mb_per_s": output.stat().st_size / seconds / 1e6,
        "frames": published[keys.camera_raw(run_id)],
    }


def publish(
    bus: Bus, run_id: str, images: list[np.ndarray], *, seconds: float, rate_hz: float, desc: str
) -> dict[str, int]:
    # One publisher per key, of the key's own message type: a mapping of them holds publishers of several types.
    out: dict[str, Publisher[Any]] = {
        keys.camera_raw(run_id): bus.publisher(keys.camera_raw(run_id), CameraFrame, Traffic.FRAMES_LOSSLESS),
        keys.camera_perturbed(run_id): bus.publisher(
            keys.camera_perturbed(run_id), CameraFrame, Traffic.FRAMES_LOSSLESS
        ),
        keys.pose(run_id): bus.publisher(keys.pose(run_id), Pose, Traffic.EVENTS),
        keys.command(run_id, "explicit"): bus.publisher(keys.command(run_id, "explicit"), Command, Traffic.COMMANDS),
        keys.live_metrics(run_id): bus.publisher(keys.live_metrics(run_id), LiveMetrics, Traffic.METRICS),
        keys.events(run_id): bus.publisher(keys.events(run_id), EpisodeEvent, Traffic.EVENTS),
    }
    counts = dict.fromkeys(out, 0)

    def send(key: str, message: msgspec.Struct) -> None:
        out[key].publish(message)
        counts[key] += 1

    steps = int(seconds * rate_hz)
    send(
        keys.events(run_id),
        EpisodeEvent(
            header=Header(run_id=run_id, episode=0, seq=0, stamp_ns=0), kind=EventKind.START, spec=EpisodeSpec()
        ),
    )
    start = time.monotonic()
    for seq in tqdm(range(steps), desc=desc, unit="step", file=sys.stderr, leave=False):
        header = Header(run_id=run_id, episode=0, seq=seq, stamp_ns=seq * 50_000_000)
        frame = image_frame(header, images[seq % len(images)])
        send(keys.camera_raw(run_id), frame)
        send(keys.camera_perturbed(run_id), frame)
        send(keys.pose(run_id), Pose(header=header, x_m=0.1 * seq, y_m=0.0, yaw_rad=0.0, speed_mps=2.0))
        send(
            keys.command(run_id, "explicit"),
            Command(header=header, brain="explicit", frame_seq=seq, speed_mps=2.0, yaw_rate_radps=0.1),
        )
        if seq % 10 == 0:
            send(
                keys.live_metrics(run_id),
                LiveMetrics(
                    header=Header(run_id=run_id, episode=0, seq=seq // 10, stamp_ns=header.stamp_ns),
                    progress_laps=0.0,
                    laps_target=1,
                    completed_laps=0,
                    sim_time_s=seq * 0.05,
                    real_time_factor=1.0,
                    cross_track_m=0.0,
                    speed_mps=2.0,
                ),
            )
        time.sleep(max(0.0, start + (seq + 1) / rate_hz - time.monotonic()))
    return counts


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--rate-hz", type=float, default=20.0)
    parser.add_argument("--camera", default="640x480")
    args = parser.parse_args()
    width, height = (int(v) for v in args.camera.split("x"))
    clean = rendered_frames(width, height)
    rng = np.random.default_rng(0)
    noisy = [np.clip(f + rng.normal(0, 6, f.shape), 0, 255).astype(np.uint8) for f in clean]
    rows = []
    with tempfile.TemporaryDirectory() as folder:
        for name, image_format, with_noise in CASES:
            rows.append(
                run_case(
                    name,
                    image_format,
                    noisy if with_noise else clean,
                    seconds=args.seconds,
                    rate_hz=args.rate_hz,
                    folder=Path(folder),
                )
            )
    print(
        f"\nrecorder, {width}x{height} frames on 2 camera keys + pose, command, metrics at {args.rate_hz:g} Hz, "
        f"{args.seconds:g} s per case\n"
    )
    print("| images | messages published | missing | recorder CPU (share of one core) | file MB/s |")
    print("|---|---|---|---|---|")
    for row in rows:
        print(
            f"| {row['case']} | {row['published']} | {row['missing']} | {100 * row['cpu_share']:.0f} % | "
            f"{row['mb_per_s']:.1f} |"
        )
    if any(row["missing"] for row in rows):
        print("\nmissing per key:", {row["case"]: row["missing_by_key"] for row in rows if row["missing"]})


if __name__ == "__main__":
    main()
