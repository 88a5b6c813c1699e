"""Closed-loop speed: the full multi-process pipeline over Zenoh against the same loop in one process.

For each camera size, the explicit brain drives the simple circuit from the start for a fixed stretch of simulated
time, twice in each configuration, interleaved so both see the same machine load:

  * in-process: EpisodeSim.render -> ExplicitBrain.act -> EpisodeSim.step in one Python loop, no bus;
  * pipeline: ``drivebench run``'s stack: embedded router, simulator, brain host and scorer processes, lock-step
    over Zenoh (frame out, command back, every step), with the scorer scoring live.

Each configuration runs with every renderer asked for (``--renderers pybullet,gl``), side by side in one run.
Prints sim steps per second and real-time factor (simulated seconds per wall second) for both, and their ratio:
the cost of the process split; then where a step's time goes (ms per step): in-process render, frame encode
(CameraFrame + MessagePack), brain, physics step; in the pipeline, the whole step and the command round trip the
simulator measured (frame out -> command back: the hops through the noise injector and the brain host, and the
brain). Not a timed test; machines are shared and noisy, so only the side-by-side ratios are meaningful.

    .venv/bin/python benchmarks/closed_loop.py [--sim-seconds 10] [--repeats 2] [--sizes 100x50,200x66,...]
        [--renderers pybullet,gl]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
import uuid
from pathlib import Path

import msgspec
from tqdm import tqdm

from brains.base import Observation
from brains.registry import make_brain
from orchestrator.launcher import BrainLaunch, LocalStack
from protocol import codec
from protocol.images import image_frame
from protocol.messages import CameraSpec, EpisodeSpec, Header
from services.simulator.episode import EpisodeSim, SceneCache

DEFAULT_SIZES = "100x50,200x66,320x240,640x480"


def in_process_steps_per_s(spec: EpisodeSpec, scenes: SceneCache, stages: dict[str, float] | None = None) -> float:
    """Steps per second of the loop in one process; ``stages`` (if given) gets the seconds per step of each stage."""
    sim = EpisodeSim(spec, scenes=scenes)
    brain = make_brain("explicit")
    brain.reset(seed=spec.seed)
    spent = dict.fromkeys(("render", "encode", "brain", "step"), 0.0)
    started = time.perf_counter()
    while True:
        t0 = time.perf_counter()
        image = sim.render()
        t1 = time.perf_counter()
        # What the simulator does before a frame goes out (the bus's own copy is not counted).
        codec.encode(image_frame(Header(run_id="bench", episode=0, seq=sim.seq, stamp_ns=sim.stamp_ns), image))
        t2 = time.perf_counter()
        action = brain.act(Observation(image_rgb=image, stamp_ns=sim.stamp_ns, seq=sim.seq))
        t3 = time.perf_counter()
        result = sim.step(speed_mps=action.speed_mps, yaw_rate_radps=action.yaw_rate_radps)
        t4 = time.perf_counter()
        for name, seconds in zip(spent, (t1 - t0, t2 - t1, t3 - t2, t4 - t3)):
            spent[name] += seconds
        if result.end is not None:
            break
    steps_per_s = sim.seq / (time.perf_counter() - started)
    if stages is not None:
        stages.update({name: seconds / sim.seq for name, seconds in spent.items()})
    return steps_per_s


def pipeline_steps_per_s(spec: EpisodeSpec, stack: LocalStack, stages: dict[str, float] | None = None) -> float:
    score = stack.run_episode(spec)
    if stages is not None:
        stages["pipeline_step"] = score.metrics.wall_time_s / score.metrics.steps
        stages["round_trip"] = (score.metrics.command_latency_p50_ms or 0.0) / 1e3
    return score.metrics.steps / score.metrics.wall_time_s


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sim-seconds", type=float, default=10.0, help="simulated seconds per measurement")
    parser.add_argument("--repeats", type=int, default=2, help="measurements per size and configuration")
    parser.add_argument("--sizes", default=DEFAULT_SIZES, help=f"camera sizes (default {DEFAULT_SIZES})")
    parser.add_argument("--renderers", default="pybullet,gl", help="renderers side by side (default pybullet,gl)")
    args = parser.parse_args()
    sizes = [tuple(int(v) for v in size.split("x")) for size in args.sizes.split(",")]
    renderers = args.renderers.split(",")
    scenes = SceneCache()
    rows = []
    with (
        tempfile.TemporaryDirectory() as tmp,
        LocalStack(run_id=f"bench{uuid.uuid4().hex[:6]}", run_dir=Path(tmp), brains=[BrainLaunch("explicit")]) as stack,
    ):
        progress = tqdm(
            total=len(sizes) * len(renderers) * args.repeats * 2, desc="closed loop", file=sys.stderr, unit="run"
        )
        for width, height in sizes:
            base = EpisodeSpec(
                circuit="simple", max_sim_seconds=args.sim_seconds, camera=CameraSpec(width_px=width, height_px=height)
            )
            measured = {renderer: ([], [], []) for renderer in renderers}  # in-process, pipeline, stages
            for renderer in renderers:  # warm caches (scene build, GL context) outside the measurement
                spec = msgspec.structs.replace(base, renderer=renderer)
                in_process_steps_per_s(msgspec.structs.replace(spec, max_sim_seconds=0.5), scenes)
                pipeline_steps_per_s(msgspec.structs.replace(spec, max_sim_seconds=0.5), stack)
            for _ in range(args.repeats):
                for renderer in renderers:  # interleaved, so that every renderer sees the same machine load
                    spec = msgspec.structs.replace(base, renderer=renderer)
                    local, piped, stages = measured[renderer]
                    stage = {}
                    local.append(in_process_steps_per_s(spec, scenes, stage))
                    progress.update()
                    piped.append(pipeline_steps_per_s(spec, stack, stage))
                    progress.update()
                    stages.append(stage)
            for renderer, (local, piped, stages) in measured.items():
                median_stages = {name: statistics.median(stage[name] for stage in stages) for name in stages[0]}
                rows.append(
                    (
                        f"{width}x{height}",
                        renderer,
                        statistics.median(local),
                        statistics.median(piped),
                        base.step_s,
                        median_stages,
                    )
                )
        progress.close()
    scenes.close()
    print(
        f"closed loop, explicit brain, simple circuit, {args.sim_seconds:g} s sim per run, median of "
        f"{args.repeats}, lock-step at {1 / rows[0][4]:.0f} Hz control"
    )
    print()
    print(
        "| camera | renderer | in-process steps/s | in-process RTF | pipeline steps/s | pipeline RTF "
        "| pipeline / in-process | cost of the process split |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for size, renderer, local, piped, step_s, _ in rows:
        print(
            f"| {size} | {renderer} | {local:.1f} | {local * step_s:.2f}x | {piped:.1f} | {piped * step_s:.2f}x | "
            f"{piped / local:.2f} | {100 * (1 - piped / local):.0f} % |"
        )
    print()
    print(
        "ms per step: in-process stages; pipeline step and command round trip (p50), and the rest of a pipeline "
        "step (pipeline step - render - encode - round trip: publishing, scoring's share of the CPU, waits)"
    )
    print()
    print("| camera | renderer | render | encode | brain | physics | pipeline step | round trip | rest |")
    print("|---|---|---|---|---|---|---|---|---|")
    for size, renderer, _, _, _, stage in rows:
        ms = {name: 1e3 * seconds for name, seconds in stage.items()}
        rest = ms["pipeline_step"] - ms["render"] - ms["encode"] - ms["round_trip"]
        print(
            f"| {size} | {renderer} | {ms['render']:.2f} | {ms['encode']:.2f} | {ms['brain']:.2f} | "
            f"{ms['step']:.2f} | {ms['pipeline_step']:.2f} | {ms['round_trip']:.2f} | {rest:.2f} |"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
