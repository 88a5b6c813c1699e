"""Closed-loop speed: the full multi-process pipeline over Zenoh against the same loop in one process.

For each camera size, the explicit brain drives the simple circuit from the start for a fixed stretch of simulated
time, twice in each configuration, interleaved so both see the same machine load:

  * in-process: EpisodeSim.render -> ExplicitBrain.act -> EpisodeSim.step in one Python loop, no bus;
  * pipeline: ``drivebench run``'s stack: embedded router, simulator, brain host and scorer processes, lock-step
    over Zenoh (frame out, command back, every step), with the scorer scoring live.

Prints sim steps per second and real-time factor (simulated seconds per wall second) for both, and their ratio:
the cost of the process split. Not a timed test; machines are shared and noisy, so only the side-by-side ratio
is meaningful.

    .venv/bin/python benchmarks/closed_loop.py [--sim-seconds 10] [--repeats 2] [--sizes 100x50,200x66,...]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
import uuid
from pathlib import Path

from tqdm import tqdm

from brains.base import Observation
from brains.registry import make_brain
from orchestrator.launcher import BrainLaunch, LocalStack
from protocol.messages import CameraSpec, EpisodeSpec
from services.simulator.episode import EpisodeSim, SceneCache

DEFAULT_SIZES = "100x50,200x66,320x240,640x480"


def in_process_steps_per_s(spec: EpisodeSpec, scenes: SceneCache) -> float:
    sim = EpisodeSim(spec, scenes=scenes)
    brain = make_brain("explicit")
    brain.reset(seed=spec.seed)
    started = time.perf_counter()
    while True:
        image = sim.render()
        action = brain.act(Observation(image_rgb=image, stamp_ns=sim.stamp_ns, seq=sim.seq))
        result = sim.step(speed_mps=action.speed_mps, yaw_rate_radps=action.yaw_rate_radps)
        if result.end is not None:
            break
    return sim.seq / (time.perf_counter() - started)


def pipeline_steps_per_s(spec: EpisodeSpec, stack: LocalStack) -> float:
    score = stack.run_episode(spec)
    return score.metrics.steps / score.metrics.wall_time_s


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sim-seconds", type=float, default=10.0, help="simulated seconds per measurement")
    parser.add_argument("--repeats", type=int, default=2, help="measurements per size and configuration")
    parser.add_argument("--sizes", default=DEFAULT_SIZES, help=f"camera sizes (default {DEFAULT_SIZES})")
    args = parser.parse_args()
    sizes = [tuple(int(v) for v in size.split("x")) for size in args.sizes.split(",")]
    scenes = SceneCache()
    rows = []
    with tempfile.TemporaryDirectory() as tmp, \
            LocalStack(run_id=f"bench{uuid.uuid4().hex[:6]}", run_dir=Path(tmp),
                       brains=[BrainLaunch("explicit")]) as stack:
        progress = tqdm(total=len(sizes) * args.repeats * 2, desc="closed loop", file=sys.stderr, unit="run")
        for width, height in sizes:
            spec = EpisodeSpec(circuit="simple", max_sim_seconds=args.sim_seconds,
                               camera=CameraSpec(width_px=width, height_px=height))
            in_process_steps_per_s(EpisodeSpec(max_sim_seconds=0.5, camera=spec.camera), scenes)  # warm caches
            local, piped = [], []
            for _ in range(args.repeats):
                local.append(in_process_steps_per_s(spec, scenes))
                progress.update()
                piped.append(pipeline_steps_per_s(spec, stack))
                progress.update()
            rows.append((f"{width}x{height}", statistics.median(local), statistics.median(piped), spec.step_s))
        progress.close()
    scenes.close()
    print(f"closed loop, explicit brain, simple circuit, {args.sim_seconds:g} s sim per run, median of "
          f"{args.repeats}, lock-step at {1 / rows[0][3]:.0f} Hz control")
    print()
    print("| camera | in-process steps/s | in-process RTF | pipeline steps/s | pipeline RTF | pipeline / in-process "
          "| cost of the process split |")
    print("|---|---|---|---|---|---|---|")
    for size, local, piped, step_s in rows:
        print(f"| {size} | {local:.1f} | {local * step_s:.2f}x | {piped:.1f} | {piped * step_s:.2f}x | "
              f"{piped / local:.2f} | {100 * (1 - piped / local):.0f} % |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
