"""Closed-loop speed: the full multi-process pipeline over Zenoh against the same loop in one process, and where a
pipeline step's time goes, hop by hop.

For each camera size and renderer, the explicit brain drives the simple circuit from the start for a fixed stretch
of simulated time in each configuration, interleaved so all see the same machine load:

  * in-process: EpisodeSim.render -> ExplicitBrain.act -> EpisodeSim.step in one Python loop, no bus;
  * pipeline: ``drivebench run``'s stack (embedded router, simulator, noise injector, brain host and scorer
    processes), lock-step over Zenoh, the scorer scoring live. The brain host drives from the simulator's frames
    when an episode has no noise (``camera: auto``, the default): frame out, command back, two hops a step;
  * via noise: the same stack with the brain host held to the noise injector's frames (``camera=perturbed``): the
    three hops every step took before ``auto`` (what an episode with noise still takes).

Then the bus floor: a bare round trip over the same bus between two processes that do nothing else (a frame-sized
message out, a command back), the least a lock-step step can spend on the bus on this machine.

The pipeline stacks run with ``DRIVEBENCH_TRACE_DIR`` set (``protocol.trace``: a timestamp per message at put, sent,
arrived, decoded and taken), so each hop of a step is measured from the processes' own clocks (one monotonic clock
per machine); the scorer's and the noise injector's CPU time per step come from /proc (Linux).

    .venv/bin/python benchmarks/closed_loop.py [--sim-seconds 10] [--repeats 2] [--sizes 100x50,320x240,640x480]
        [--renderers pybullet,gl]

Not a timed test; machines are shared and noisy, so only the side-by-side ratios are meaningful.
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import statistics
import sys
import tempfile
import time
import uuid
from contextlib import ExitStack
from pathlib import Path
from typing import NamedTuple

import msgspec
from tqdm import tqdm

from brains.base import Observation
from brains.registry import make_brain
from orchestrator.stack.launcher import BrainLaunch, LocalStack
from protocol import codec, keys
from protocol.bus import Bus, BusConfig, Inbox, Traffic
from protocol.episode_spec import CameraSpec, EpisodeSpec
from protocol.images import image_frame
from protocol.messages import CameraFrame, Command, Header
from protocol.trace import TRACE_DIR_ENV, TraceEvent, read_traces
from services.simulator.episode import EpisodeSim, SceneCache

DEFAULT_SIZES = "100x50,320x240,640x480"
PIPELINES = ("pipeline", "via noise")
FLOOR_ROUND_TRIPS = 300

# The hops of a lock-step step, in order: (name, (process, event, stream) from, (process, event, stream) to).
# Streams: "frame" (the camera key the brain drives from), "raw" (the simulator's), "command", "pose".
HOPS = (
    ("frame put", ("simulator", "put", "raw"), ("simulator", "sent", "raw")),
    ("frame to brain", ("simulator", "sent", "raw"), ("brain", "arrived", "frame")),
    ("decode", ("brain", "arrived", "frame"), ("brain", "decoded", "frame")),
    ("to the loop", ("brain", "decoded", "frame"), ("brain", "taken", "frame")),
    ("brain host", ("brain", "taken", "frame"), ("brain", "put", "command")),
    ("command put", ("brain", "put", "command"), ("brain", "sent", "command")),
    ("command to sim", ("brain", "sent", "command"), ("simulator", "arrived", "command")),
    ("to the sim loop", ("simulator", "arrived", "command"), ("simulator", "taken", "command")),
)
POSE_TO_SCORER = (("simulator", "sent", "pose"), ("scorer", "taken", "pose"))

# (role, event, stream, episode, seq): one moment of one stream's message of one step, in the traces.
Moment = tuple[str, str, str, int, int]


class Row(NamedTuple):
    """One camera size and renderer, measured: the medians over the repeats."""

    camera: str  # WxH
    renderer: str
    steps_per_s: dict[str, float]  # per configuration: "in-process", then each of PIPELINES
    stages: dict[str, float]  # seconds per step of each stage (pipeline stages prefixed "<pipeline>:")
    step_s: float  # the simulated seconds of one step


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


def cpu_s(pid: int) -> float:
    """User + system CPU seconds of a process so far (Linux /proc)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def pipeline_steps_per_s(spec: EpisodeSpec, stack: LocalStack, stages: dict[str, float] | None = None) -> float:
    """Steps per second of one episode on ``stack``; ``stages`` gets the step, the round trip the simulator
    measured (p50), and the scorer's and the noise injector's CPU seconds per step."""
    watched = {child.role: child.process.pid for child in stack.children if child.role in ("scorer", "noise")}
    before = {role: cpu_s(pid) for role, pid in watched.items()}
    score = stack.run_episode(spec)
    steps = score.metrics.steps
    if stages is not None:
        stages["pipeline_step"] = score.metrics.wall_time_s / steps
        stages["round_trip"] = (score.metrics.command_latency_p50_ms or 0.0) / 1e3
        for role, pid in watched.items():
            stages[f"{role}_cpu"] = (cpu_s(pid) - before[role]) / steps
    return steps / score.metrics.wall_time_s


# -- the bus floor --


def _echo(endpoint: str, run_id: str) -> None:
    """The far end of the floor measurement: answer every frame with a command, nothing else."""
    with Bus(BusConfig(mode="peer", connect=[endpoint]), name="echo", env={}) as bus:
        frames = bus.subscribe(keys.camera_raw(run_id), CameraFrame, keep_last=8)
        commands = bus.publisher(keys.command(run_id, "echo"), Command, Traffic.COMMANDS)
        bus.declare_alive(keys.alive(run_id, "brain", "echo"))
        while (received := frames.recv(timeout_s=10.0)) is not None:
            header = received.message.header
            if header.episode == 1:  # the end of the measurement
                return
            commands.publish(
                Command(header=header, brain="echo", frame_seq=header.seq, speed_mps=1.0, yaw_rate_radps=0.0)
            )


def bus_round_trip_s(endpoint: str, *, width_px: int, height_px: int, count: int = FLOOR_ROUND_TRIPS) -> float:
    """Median seconds from a frame's put to its command's arrival, between this process and one echo process."""
    run_id = f"floor{uuid.uuid4().hex[:6]}"
    echo = multiprocessing.get_context("spawn").Process(target=_echo, args=(endpoint, run_id), daemon=True)
    echo.start()
    image = bytes(width_px * height_px * 3)
    times = []
    with Bus(BusConfig(mode="peer", connect=[endpoint]), name="floor", env={}) as bus:
        inbox = Inbox()
        bus.subscribe(keys.command(run_id, "echo"), Command, inbox=inbox)
        frames = bus.publisher(keys.camera_raw(run_id), CameraFrame, Traffic.FRAMES_LOSSLESS)
        bus.watch_alive(keys.alive(run_id, "brain", "echo")).wait_for(
            {keys.alive(run_id, "brain", "echo")}, timeout_s=30.0
        )
        while not frames.has_subscribers():
            time.sleep(0.01)
        for seq in range(count + 21):  # the first 20 warm up; the last (episode 1) ends the echo
            episode = int(seq == count + 20)
            header = Header(run_id=run_id, episode=episode, seq=seq, stamp_ns=seq)
            frame = CameraFrame(header=header, width_px=width_px, height_px=height_px, data=image)
            started = time.perf_counter()
            frames.publish(frame)
            if episode == 1:
                break
            if inbox.recv(timeout_s=10.0) is None:
                raise RuntimeError(f"the echo process did not answer frame {seq} (exit code {echo.exitcode})")
            if seq >= 20:
                times.append(time.perf_counter() - started)
    echo.join(timeout=10.0)
    return statistics.median(times)


# -- hops, from the traces --


def _stream_keys(run_id: str, *, via_noise: bool) -> dict[str, str]:
    frame = keys.camera_perturbed(run_id) if via_noise else keys.camera_raw(run_id)
    return {
        "frame": frame,
        "raw": keys.camera_raw(run_id),
        "command": keys.command(run_id, "explicit"),
        "pose": keys.pose(run_id),
    }


def _first_times(events: list[TraceEvent], stream_keys: dict[str, str]) -> dict[Moment, int]:
    """(role, event, stream, episode, seq) -> the first time it happened (a resent frame counts once)."""
    stream_of: dict[str, list[str]] = {}  # key -> the streams it carries
    for stream, key in stream_keys.items():
        stream_of.setdefault(key, []).append(stream)
    first: dict[Moment, int] = {}
    for e in events:
        role = e.process.split("-", 1)[0]
        for stream in stream_of.get(e.key, ()):
            first.setdefault((role, e.event, stream, e.episode, e.seq), e.ns)
    return first


def hop_times_s(trace_dir: Path, run_id: str, *, via_noise: bool) -> dict[str, float]:
    """Median seconds of each hop of HOPS (and the pose's trip to the scorer) over every traced step."""
    first = _first_times(read_traces(trace_dir), _stream_keys(run_id, via_noise=via_noise))
    steps = {(episode, seq) for (role, event, stream, episode, seq) in first if stream == "command" and seq >= 0}
    medians = {}
    for name, start, end in HOPS + (("pose to scorer", *POSE_TO_SCORER),):
        spans = [
            first[(*end, *step)] - first[(*start, *step)]
            for step in steps
            if (*start, *step) in first and (*end, *step) in first
        ]
        medians[name] = statistics.median(spans) / 1e9 if spans else float("nan")
    return medians


# -- the run --


def measure_size(
    args: argparse.Namespace,
    scenes: SceneCache,
    stacks: dict[str, LocalStack],
    size: tuple[int, int],
    renderers: list[str],
    progress: tqdm,
) -> list[Row]:
    """One row per renderer."""
    width, height = size
    base = EpisodeSpec(
        circuit="simple", max_sim_seconds=args.sim_seconds, camera=CameraSpec(width_px=width, height_px=height)
    )
    configurations = ("in-process",) + PIPELINES
    # renderer -> (steps/s of each repeat per configuration, the stages of each repeat)
    measured: dict[str, tuple[dict[str, list[float]], list[dict[str, float]]]] = {
        renderer: ({c: [] for c in configurations}, []) for renderer in renderers
    }
    for renderer in renderers:  # warm caches (scene build, GL context) outside the measurement
        warm = msgspec.structs.replace(base, renderer=renderer, max_sim_seconds=0.5)
        in_process_steps_per_s(warm, scenes)
        for name in PIPELINES:
            pipeline_steps_per_s(warm, stacks[name])
    for _ in range(args.repeats):
        for renderer in renderers:  # interleaved, so that every configuration sees the same machine load
            spec = msgspec.structs.replace(base, renderer=renderer)
            rates, stages = measured[renderer]
            stage: dict[str, float] = {}
            rates["in-process"].append(in_process_steps_per_s(spec, scenes, stage))
            progress.update()
            for name in PIPELINES:
                pipe_stage: dict[str, float] = {}
                rates[name].append(pipeline_steps_per_s(spec, stacks[name], pipe_stage))
                stage.update({f"{name}:{k}": v for k, v in pipe_stage.items()})
                progress.update()
            stages.append(stage)
    rows = []
    for renderer, (rates, stages) in measured.items():
        median_stages = {name: statistics.median(stage[name] for stage in stages) for name in stages[0]}
        median_rates = {name: statistics.median(values) for name, values in rates.items()}
        rows.append(Row(f"{width}x{height}", renderer, median_rates, median_stages, base.step_s))
    return rows


def print_tables(
    args: argparse.Namespace, rows: list[Row], floors: dict[str, float], hops: dict[str, dict[str, float]]
) -> None:
    step_s = rows[0].step_s
    print(
        f"closed loop, explicit brain, simple circuit, {args.sim_seconds:g} s sim per run, median of "
        f"{args.repeats}, lock-step at {1 / step_s:.0f} Hz control"
    )
    print()
    print(
        "| camera | renderer | in-process RTF | pipeline RTF | pipeline / in-process | via noise RTF "
        "| via noise / in-process |"
    )
    print("|---|---|---|---|---|---|---|")
    for size, renderer, rates, _, step_s in rows:
        local, piped, noisy = rates["in-process"], rates["pipeline"], rates["via noise"]
        print(
            f"| {size} | {renderer} | {local * step_s:.2f}x | {piped * step_s:.2f}x | {piped / local:.2f} | "
            f"{noisy * step_s:.2f}x | {noisy / local:.2f} |"
        )
    print()
    print(
        "ms per step. In-process: render, encode, brain, physics, and the whole step. Pipeline: the whole step, the "
        "command round trip the simulator measured (p50), the bus floor (a bare frame-out command-back round trip "
        "between two processes), the rest (step - render - encode - round trip), and the CPU the scorer and the "
        "noise injector spent per step (on the other core)"
    )
    print()
    print(
        "| camera | renderer | render | encode | brain | physics | in-process step | pipeline step | round trip "
        "| bus floor | rest | scorer CPU | noise CPU | via noise: step | via noise: round trip |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for size, renderer, rates, stage, _ in rows:
        ms = {name: 1e3 * seconds for name, seconds in stage.items()}
        rest = ms["pipeline:pipeline_step"] - ms["render"] - ms["encode"] - ms["pipeline:round_trip"]
        print(
            f"| {size} | {renderer} | {ms['render']:.2f} | {ms['encode']:.2f} | {ms['brain']:.2f} | "
            f"{ms['step']:.2f} | {1e3 / rates['in-process']:.2f} | {ms['pipeline:pipeline_step']:.2f} | "
            f"{ms['pipeline:round_trip']:.2f} | {1e3 * floors[size]:.2f} | {rest:.2f} | "
            f"{ms['pipeline:scorer_cpu']:.2f} | {ms['pipeline:noise_cpu']:.2f} | "
            f"{ms['via noise:pipeline_step']:.2f} | {ms['via noise:round_trip']:.2f} |"
        )
    print()
    print("Each hop of a pipeline step, ms, median over every traced step of every run at every size and renderer")
    print("(frame to brain = through the noise injector in the via-noise stack); the pose's trip to the scorer")
    print("runs beside the brain, off the step's path")
    print()
    names = [name for name, _, _ in HOPS] + ["pose to scorer"]
    print("| stack | " + " | ".join(names) + " |")
    print("|---|" + "---|" * len(names))
    for stack_name, hop in hops.items():
        print(f"| {stack_name} | " + " | ".join(f"{1e3 * hop[name]:.3f}" for name in names) + " |")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sim-seconds", type=float, default=10.0, help="simulated seconds per measurement")
    parser.add_argument("--repeats", type=int, default=2, help="measurements per size and configuration")
    parser.add_argument("--sizes", default=DEFAULT_SIZES, help=f"camera sizes (default {DEFAULT_SIZES})")
    parser.add_argument("--renderers", default="pybullet,gl", help="renderers side by side (default pybullet,gl)")
    args = parser.parse_args()
    sizes = [(int(width), int(height)) for width, height in (size.split("x") for size in args.sizes.split(","))]
    renderers = args.renderers.split(",")
    scenes = SceneCache()
    rows: list[Row] = []
    floors: dict[str, float] = {}  # camera WxH -> the bus floor's round trip, s
    with tempfile.TemporaryDirectory() as tmp, ExitStack() as closing:
        stacks: dict[str, LocalStack] = {}
        trace_dirs: dict[str, Path] = {}
        for name, host in (("pipeline", ()), ("via noise", ("camera=perturbed",))):
            trace_dirs[name] = Path(tmp) / f"trace-{len(stacks)}"
            trace_dirs[name].mkdir()
            os.environ[TRACE_DIR_ENV] = str(trace_dirs[name])  # the stack's children inherit it
            stack = LocalStack(
                run_id=f"bench{uuid.uuid4().hex[:6]}",
                run_dir=Path(tmp) / f"run-{len(stacks)}",
                brains=[BrainLaunch("explicit", host=host)],
            )
            stacks[name] = closing.enter_context(stack)
            del os.environ[TRACE_DIR_ENV]
        total = len(sizes) * len(renderers) * args.repeats * (1 + len(PIPELINES))
        progress = tqdm(total=total, desc="closed loop", file=sys.stderr, unit="run")
        for size in sizes:
            rows += measure_size(args, scenes, stacks, size, renderers, progress)
            label = f"{size[0]}x{size[1]}"
            floors[label] = bus_round_trip_s(stacks["pipeline"].endpoint, width_px=size[0], height_px=size[1])
        progress.close()
        run_ids = {name: stack.run_id for name, stack in stacks.items()}
        closing.close()  # the processes write their traces as they stop
        hops = {name: hop_times_s(trace_dirs[name], run_ids[name], via_noise=name == "via noise") for name in PIPELINES}
    scenes.close()
    print_tables(args, rows, floors, hops)
    return 0


if __name__ == "__main__":
    sys.exit(main())
