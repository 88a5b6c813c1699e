"""The gazebo look's cost beside the flat look's: frame cost and closed-loop real-time factor, both renderers.

For each camera size and circuit (simple: no shadows; montreal: the sun's shadow map), each (renderer, look) that
can be drawn is measured side by side, interleaved so that all see the same machine load:

  * frame: the median time of one ``render`` over poses spread round the circuit (``parity_poses``);
  * in-process: EpisodeSim.render -> ExplicitBrain.act -> EpisodeSim.step in one Python loop (real-time factor);
  * pipeline: ``drivebench run``'s stack (router, simulator, noise injector, brain host, scorer processes),
    lock-step over Zenoh (real-time factor), twice: the simulator rendering with one llvmpipe thread (as each stack
    of a matrix with as many workers as cores does), and with this machine's cores (as ``drivebench run`` does:
    in lock-step the other processes wait for the frame).

The pybullet renderer cannot draw the gazebo look: its row says so (the line a user gets). The last columns are the
frame cost over the flat look's on the same renderer (gl), in wall time and in CPU time (this process's, which a
shared machine's load moves far less).

    .venv/bin/python benchmarks/looks.py [--sim-seconds 10] [--repeats 2] [--sizes 320x240,640x480]
        [--circuits simple,montreal]

Not a timed test; machines are shared and noisy, so only the side-by-side ratios are meaningful.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
import uuid
from contextlib import ExitStack
from pathlib import Path

import msgspec
from closed_loop import in_process_steps_per_s, pipeline_steps_per_s
from tqdm import tqdm

from circuits import load_circuit
from orchestrator.stack.launcher import BrainLaunch, LocalStack, render_threads_for
from protocol.episode_spec import CameraSpec, EpisodeSpec
from protocol.variations import VariationError, apply_variation, check_look
from services.simulator.episode import SceneCache
from services.simulator.parity import parity_poses

LOOKS = (("pybullet", "flat"), ("pybullet", "gazebo"), ("gl", "flat"), ("gl", "gazebo"))
FRAME_POSES = 24


def frame_s(spec: EpisodeSpec, scenes: SceneCache) -> tuple[float, float]:
    """Median wall and CPU seconds of one frame over poses spread round the circuit (the scene built beforehand).

    CPU: this process's, llvmpipe's rendering thread included (it runs in the process); on a shared machine it
    moves far less with the load than the wall time does."""
    circuit = load_circuit(spec.circuit)
    scene = scenes.get(circuit, spec.world, renderer=spec.renderer)
    wall, cpu = [], []
    for car in parity_poses(circuit, count=FRAME_POSES):
        started, started_cpu = time.perf_counter(), time.process_time()
        scene.render(car, spec.camera)
        wall.append(time.perf_counter() - started)
        cpu.append(time.process_time() - started_cpu)
    return statistics.median(wall), statistics.median(cpu)


def specs_for(args, size: tuple[int, int], circuit: str) -> tuple[dict[tuple[str, str], EpisodeSpec], list[str]]:
    """The drawable (renderer, look) specs, and the table cells (the refusal) of each that is not."""
    base = EpisodeSpec(
        circuit=circuit, max_sim_seconds=args.sim_seconds, camera=CameraSpec(width_px=size[0], height_px=size[1])
    )
    specs, refused = {}, []
    for renderer, look in LOOKS:
        spec = apply_variation(msgspec.structs.replace(base, renderer=renderer), f"look={look}")
        try:
            check_look(spec)
        except VariationError as error:
            refused.append(f"| {renderer} | {look} | refused: `{str(error).split(' (')[0]}` | | | | | |")
            continue
        specs[(renderer, look)] = spec
    return specs, refused


def measure(args, scenes: SceneCache, stacks: dict[str, LocalStack], specs: dict, progress) -> dict:
    """(renderer, look) -> median frame seconds, in-process and pipeline steps per second (one per stack)."""
    results: dict = {key: {"frame": [], "frame cpu": [], "in-process": [], **{n: [] for n in stacks}} for key in specs}
    for spec in specs.values():  # warm: scene build, GL context, textures
        warm = msgspec.structs.replace(spec, max_sim_seconds=0.5)
        in_process_steps_per_s(warm, scenes)
        for stack in stacks.values():
            pipeline_steps_per_s(warm, stack)
    for _ in range(args.repeats):
        for key, spec in specs.items():  # interleaved
            wall_s, cpu_s = frame_s(spec, scenes)
            results[key]["frame"].append(wall_s)
            results[key]["frame cpu"].append(cpu_s)
            results[key]["in-process"].append(in_process_steps_per_s(spec, scenes))
            for name, stack in stacks.items():
                results[key][name].append(pipeline_steps_per_s(spec, stack))
            progress.update()
    return {key: {name: statistics.median(values) for name, values in row.items()} for key, row in results.items()}


def print_rows(size: tuple[int, int], circuit: str, measured: dict, refused: list[str], step_s: float) -> None:
    flat_gl = measured.get(("gl", "flat"), {})
    for (renderer, look), row in measured.items():
        ratios = "- | -"
        if flat_gl and renderer == "gl":
            ratios = f"{row['frame'] / flat_gl['frame']:.2f} | {row['frame cpu'] / flat_gl['frame cpu']:.2f}"
        print(
            f"| {size[0]}x{size[1]} | {circuit} | {renderer} | {look} | {1e3 * row['frame']:.2f} | "
            f"{1e3 * row['frame cpu']:.2f} | {row['in-process'] * step_s:.2f}x | {row['pipeline'] * step_s:.2f}x | "
            f"{row['pipeline, run'] * step_s:.2f}x | "
            f"{ratios} |"
        )
    for cells in refused:
        print(f"| {size[0]}x{size[1]} | {circuit} {cells} |")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sim-seconds", type=float, default=10.0, help="simulated seconds per closed-loop run")
    parser.add_argument("--repeats", type=int, default=2, help="measurements per configuration")
    parser.add_argument("--sizes", default="320x240,640x480", help="camera sizes (default 320x240,640x480)")
    parser.add_argument("--circuits", default="simple,montreal", help="circuits (default simple,montreal)")
    args = parser.parse_args()
    sizes = [(int(w), int(h)) for w, h in (size.split("x") for size in args.sizes.split(","))]
    circuits = args.circuits.split(",")
    scenes = SceneCache(capacity=8)
    plan = [(size, circuit, *specs_for(args, size, circuit)) for size in sizes for circuit in circuits]
    total = sum(len(specs) for _, _, specs, _ in plan) * args.repeats
    results = []
    threads = render_threads_for(stacks=1)
    with tempfile.TemporaryDirectory() as tmp, ExitStack() as closing:
        stacks = {
            name: closing.enter_context(
                LocalStack(
                    run_id=f"looks{uuid.uuid4().hex[:6]}",
                    run_dir=Path(tmp) / name.replace(", ", "-"),
                    brains=[BrainLaunch("explicit")],
                    render_threads=render_threads,
                )
            )
            for name, render_threads in (("pipeline", 1), ("pipeline, run", threads))
        }
        with tqdm(total=total, desc="looks", file=sys.stderr, unit="run") as progress:
            for size, circuit, specs, refused in plan:
                results.append((size, circuit, measure(args, scenes, stacks, specs, progress), refused))
    scenes.close()
    step_s = EpisodeSpec().step_s
    print(
        f"looks, explicit brain, {args.sim_seconds:g} s sim per closed-loop run, median of {args.repeats}; frame: "
        f"median render over {FRAME_POSES} poses, one llvmpipe thread; lock-step at {1 / step_s:.0f} Hz; pipeline: "
        f"1 llvmpipe thread, pipeline (run): {threads}, as drivebench run here"
    )
    print()
    print(
        "| camera | circuit | renderer | look | frame ms | frame CPU ms | in-process RTF | pipeline RTF "
        "| pipeline (run) RTF | frame / gl flat | frame CPU / gl flat |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for size, circuit, measured, refused in results:
        print_rows(size, circuit, measured, refused, step_s)
    return 0


if __name__ == "__main__":
    sys.exit(main())
