"""The chaos table: every fault an operator meets, run against real stacks, one row each.

For each fault: what happened to the episode (outcome), the typed reason it was given, how long after the fault
that reason was known, how many processes of that stack were still running two seconds after it closed (orphans),
and what data was lost. Faults: kill -9 of each process mid-episode (brain, simulator, noise injector, scorer,
recorder, an attached driver, a separate router), the router killed and started again under an attached run on
long-lived services (the compose deployment), a flood of garbage on the command and camera keys (with each
process's peak memory), one bad value (a brain answering NaN, malformed camera frames and a NaN pose from a plain
client: refused where they enter, typed, nothing else lost), and bad input on the command line. Not a timed test:
detection times are measured, not asserted; run it to see the table.

    .venv/bin/python benchmarks/faults.py [--flood-seconds 5] [--only brain,recorder,nan_brain,...]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from tqdm import tqdm

# tests/support holds the helpers the tests and the benchmarks share: the attached driver, the environment scrub.
sys.path.append(str(Path(__file__).resolve().parents[1] / "tests"))
from support.attach import attach_driver
from support.env import clean_env

from orchestrator.stack.failures import StackFailure
from orchestrator.stack.launcher import BrainLaunch, LocalStack, free_loopback_port
from protocol import keys
from protocol.bus import Bus, BusError, Inbox, Traffic, probe_router
from protocol.episode_spec import CameraSpec, EpisodeSpec
from protocol.messages import CameraFrame, Command, EpisodeEvent, EpisodeScore, EventKind, Header, Pose
from recorder.reading import read_messages
from recorder.repair import repair
from recorder.writer import part_path

KILL_AFTER_S = 2.0
SMALL_CAMERA = CameraSpec(width_px=64, height_px=48)
ROOT = Path(__file__).resolve().parents[1]


@dataclass
class Row:
    fault: str
    outcome: str
    reason: str
    detected_s: float | None
    orphans: int
    data_lost: str = "-"


def orphans(run_id: str) -> int:
    """Processes still running that carry the run id on their command line, after a moment to exit."""
    time.sleep(2.0)
    found = subprocess.run(["pgrep", "-f", f"--run-id {run_id}"], capture_output=True, text=True).stdout.split()
    return len([pid for pid in found if int(pid) != os.getpid()])


def standing_still() -> BrainLaunch:
    return BrainLaunch("constant", options=("speed_mps=0.0",))  # never ends by itself before the time limit


def kill_child(role: str, name: str, folder: Path, *, fault: str | None = None) -> Row:
    """SIGKILL one process of a stack (the router too: then it runs as a child process) mid-episode."""
    run_id = f"f{uuid.uuid4().hex[:6]}"
    stack = LocalStack(run_id=run_id, run_dir=folder / run_id, brains=[standing_still()], embed_router=role != "router")
    killed_at: list[float] = []
    with stack:
        victim = stack.child(role, name)

        def kill() -> None:
            killed_at.append(time.monotonic())
            os.kill(victim.process.pid, signal.SIGKILL)

        threading.Timer(KILL_AFTER_S, kill).start()
        try:
            score = stack.run_episode(
                EpisodeSpec(active_brain="constant", max_sim_seconds=600, camera=SMALL_CAMERA), wall_timeout_s=120
            )
            outcome, reason = "scored", str(score.reason)
        except StackFailure as failure:
            outcome, reason = "failed, typed", failure.kind
        detected = time.monotonic() - killed_at[0]
    return Row(fault or f"kill -9 {role}", outcome, reason, detected, orphans(run_id))


def kill_recorder(folder: Path) -> Row:
    run_id = f"f{uuid.uuid4().hex[:6]}"
    recording = folder / f"{run_id}.mcap"
    stack = LocalStack(
        run_id=run_id,
        run_dir=folder / run_id,
        brains=[BrainLaunch("explicit")],
        record=recording,
        record_options=("image_format=jpeg",),
    )
    with stack:
        assert stack.bus is not None, "a started stack has its bus"
        poses = Inbox()
        stack.bus.subscribe(keys.pose(run_id), Pose, inbox=poses)
        recorder = stack.child("recorder", "recorder")
        at_kill: list[int] = []
        killed_at: list[float] = []

        def kill() -> None:
            killed_at.append(time.time())
            os.kill(recorder.process.pid, signal.SIGKILL)
            stamps = [received.message.header.stamp_ns for received in poses.drain()]
            at_kill.append(max(stamps))

        threading.Timer(KILL_AFTER_S * 2, kill).start()
        score = stack.run_episode(EpisodeSpec(max_sim_seconds=40, camera=CameraSpec()), wall_timeout_s=120)
    detected = None if stack.recording_failure is None else stack.recording_failure.detected_at_s - killed_at[0]
    repaired = repair(part_path(recording), output=recording).output
    last_ns = max(r.message.header.stamp_ns for r in read_messages(repaired) if r.message.header.run_id == run_id)
    lost_s = (at_kill[0] - last_ns) / 1e9
    reason = f"{score.reason} + recorder_died" if stack.recording_failure is not None else str(score.reason)
    return Row(
        "kill -9 recorder (JPEG, lock-step)",
        "scored, recording flagged",
        reason,
        detected,
        orphans(run_id),
        f"{max(lost_s, 0.0):.2f} s of simulated time",
    )


def drivebench(*args: str, env: dict[str, str], log: Path) -> subprocess.Popen:
    with open(log, "ab") as out:
        return subprocess.Popen(
            [sys.executable, "-m", *args],
            stdout=out,
            stderr=subprocess.STDOUT,
            env=env,
            cwd=ROOT,
            start_new_session=True,
        )


def wait_for(condition, *, timeout_s: float) -> float | None:
    """Seconds until ``condition()`` held, polled every 50 ms; None if it never did within ``timeout_s``."""
    start = time.monotonic()
    while time.monotonic() - start < timeout_s:
        if condition():
            return time.monotonic() - start
        time.sleep(0.05)
    return None


COMPOSE_SERVICES = {
    "simulator": ["services.simulator"],
    "noise": ["services.noise"],
    "scorer": ["services.scorer"],
    "brain": ["brains", "--brain", "constant", "--set", "options.speed_mps=0.0"],
}


def restart_router(folder: Path) -> Row:
    """compose's deployment: a router and services that outlive episodes. The router is killed (kill -9) under an
    attached run and started again on the same port: the driver must fail typed, the simulator must end the episode,
    and the next attach must run on the same services."""
    run_id = f"f{uuid.uuid4().hex[:6]}"
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    env = clean_env(DRIVEBENCH_ROUTER=endpoint, DRIVEBENCH_RUN_ID=run_id)
    logs = folder / run_id
    logs.mkdir()
    router_argv = ("services.router", "--listen", endpoint)
    processes = {"router": drivebench(*router_argv, env=env, log=logs / "router.log")}
    try:
        wait_for(lambda: _answers(endpoint), timeout_s=30)
        processes |= {
            name: drivebench(*argv, env=env, log=logs / f"{name}.log") for name, argv in COMPOSE_SERVICES.items()
        }
        attach = (
            "orchestrator.cli",
            "run",
            "--attach",
            "--brain",
            "constant",
            "--runs-dir",
            str(logs / "runs"),
            "--camera",
            "64x48",
        )
        driver = drivebench(*attach, "--max-sim-seconds", "600", env=env, log=logs / "driver.log")
        simulator_log = logs / "simulator.log"
        wait_for(lambda: "episode 0 started" in simulator_log.read_text(errors="replace"), timeout_s=90)
        time.sleep(KILL_AFTER_S)
        os.killpg(processes["router"].pid, signal.SIGKILL)
        processes["router"].wait()
        killed_at = time.monotonic()
        processes["router"] = drivebench(*router_argv, env=env, log=logs / "router.log")
        driver.wait(timeout=60)
        driver_failed_s = time.monotonic() - killed_at
        ended_s = wait_for(
            lambda: "episode 0 ended: driver_lost" in simulator_log.read_text(errors="replace"), timeout_s=30
        )
        failure = json.loads(next((logs / "runs").glob("*/failure.json")).read_text())["failure"]
        again = drivebench(*attach, "--max-sim-seconds", "4", env=env, log=logs / "driver.log").wait(timeout=120)
        services_kept = all(processes[name].poll() is None for name in COMPOSE_SERVICES)
    finally:
        for process in processes.values():
            if process.poll() is None:
                os.killpg(process.pid, signal.SIGTERM)
        for process in processes.values():
            process.wait(timeout=30)
    next_run = "next attach scored" if again == 0 else f"next attach exited {again}"
    ended = "episode ended driver_lost" if ended_s is not None else "EPISODE STILL RUNNING"
    kept = "services kept" if services_kept else "A SERVICE DIED"
    return Row(
        "router kill -9 + restart under an attached run (compose services)",
        f"driver failed typed; {ended}; {next_run}; {kept}",
        f"{failure} + driver_lost",
        driver_failed_s,
        sum(process.poll() is None for process in processes.values()),
    )


def _answers(endpoint: str) -> bool:
    try:
        probe_router(endpoint, timeout_s=0.5)
        return True
    except BusError:
        return False


def kill_driver(folder: Path) -> Row:
    run_id = f"f{uuid.uuid4().hex[:6]}"
    with LocalStack(run_id=run_id, run_dir=folder / run_id, brains=[standing_still()]) as stack:
        assert stack.bus is not None, "a started stack has its bus"
        events = Inbox()
        stack.bus.subscribe(keys.events(run_id), EpisodeEvent, inbox=events)
        driver = attach_driver(
            endpoint=stack.endpoint,
            run_id=run_id,
            out=folder / f"{run_id}-driver",
            args=("--max-sim-seconds", "600", "--realtime"),
            output=subprocess.DEVNULL,
        )
        reason, detected = "none", None
        deadline = time.monotonic() + 60
        while (received := events.recv(timeout_s=1.0)) is None or received.message.kind != EventKind.START:
            if time.monotonic() > deadline:
                break
        time.sleep(KILL_AFTER_S)
        os.killpg(driver.pid, signal.SIGKILL)
        killed_at = time.monotonic()
        while (received := events.recv(timeout_s=20)) is not None:
            if received.message.kind == EventKind.END:
                reason, detected = str(received.message.reason), time.monotonic() - killed_at
                break
        driver.wait()
    return Row("kill -9 attached driver", "ended by the simulator", reason, detected, orphans(run_id))


def flood(folder: Path, seconds: float) -> Row:
    """Garbage on the command and camera keys while the explicit brain laps: does anything change?"""
    results = []
    for flooded in (False, True):
        run_id = f"f{uuid.uuid4().hex[:6]}"
        with LocalStack(run_id=run_id, run_dir=folder / run_id, brains=[BrainLaunch("explicit")]) as stack:
            bus = stack.bus
            assert bus is not None, "a started stack has its bus"
            stop = threading.Event()
            sent = [0]

            def spam() -> None:
                publishers = [
                    bus.publisher(keys.command(run_id, "explicit"), Pose, Traffic.COMMANDS),
                    bus.publisher(keys.camera_perturbed(run_id), Pose, Traffic.FRAMES),
                ]
                deadline = time.monotonic() + seconds
                while not stop.is_set() and time.monotonic() < deadline:
                    for publisher in publishers:
                        publisher.publish_bytes(os.urandom(64))
                        sent[0] += 1

            thread = threading.Thread(target=spam, daemon=True)
            if flooded:
                thread.start()
            score = stack.run_episode(EpisodeSpec(max_sim_seconds=20, camera=CameraSpec()), wall_timeout_s=120)
            stop.set()
            peaks = {f"{child.role}/{child.name}": peak_rss_mb(child.process.pid) for child in stack.children}
            results.append((score, sent[0], run_id, peaks))
    (clean, _, _, clean_peaks), (noisy, count, run_id, noisy_peaks) = results
    same = (clean.metrics.progress_m, clean.metrics.cross_track_mean_m) == (
        noisy.metrics.progress_m,
        noisy.metrics.cross_track_mean_m,
    )
    growth = {name: noisy_peaks[name] - clean_peaks[name] for name in noisy_peaks if name in clean_peaks}
    worst = max(growth, key=growth.__getitem__)
    outcome = "scored" if same else "scored, DIFFERENT"
    return Row(
        f"flood: {count:,} garbage messages in {seconds:g} s",
        f"{outcome}; peak memory +{max(growth[worst], 0):.0f} MB at most ({worst}, {noisy_peaks[worst]:.0f} MB)",
        str(noisy.reason),
        None,
        orphans(run_id),
        "none (identical trajectory)" if same else "trajectory changed",
    )


# -- one bad value: it must be refused where it enters, typed, and cost nothing else -----------------------------------

NAN_BRAIN = """
from brains.base import Action


class NanAfter:
    \"\"\"Stands still, then answers NaN from frame ``after`` on.\"\"\"
    def __init__(self, *, after=20):
        self.after = after
    def reset(self, *, seed):
        pass
    def act(self, observation):
        return Action(speed_mps=float("nan") if observation.seq >= self.after else 0.0, yaw_rate_radps=0.0)
"""
NAN_AFTER_FRAMES = 20


def missing_in_recording(path: Path, run_id: str, score: EpisodeScore) -> str:
    """What the recording of a one-episode run lacks: the frames and poses of every step, the driver's answer to every
    frame it drove, the END event and the score."""
    frames: dict[str, set[int]] = {}  # per key: the frame numbers its messages belong to
    ended = False
    for recorded in read_messages(path):
        message = recorded.message
        if message.header.run_id == run_id:
            frame = message.frame_seq if isinstance(message, Command) else message.header.seq
            frames.setdefault(recorded.key, set()).add(frame)
            ended |= isinstance(message, EpisodeEvent) and message.kind == EventKind.END
    last_pose = score.metrics.steps  # poses 0..steps; the last one has no frame (nobody would answer it)
    expected = {
        "frames": (keys.camera_raw(run_id), set(range(last_pose))),
        "poses": (keys.pose(run_id), set(range(last_pose + 1))),
        "commands": (keys.command(run_id, score.brain), set(range(last_pose))),
        "scores": (keys.score(run_id), {0}),
    }
    lost = [f"{len(want - frames.get(key, set()))} {what}" for what, (key, want) in expected.items()]
    lost = [text for text in lost if not text.startswith("0 ")] + ([] if ended else ["the END event"])
    kept = ", ".join(f"{len(frames.get(key, set()))} {what}" for what, (key, _) in expected.items())
    return f"LOST {', '.join(lost)}" if lost else f"none ({kept}, END)"


def bad_value_run(
    folder: Path,
    *,
    fault: str,
    brain: BrainLaunch,
    active_brain: str,
    inject: Callable[[Bus, str], None] | None = None,
) -> Row:
    """One recorded episode with a bad value in it: the brain's own, or ``inject(bus, run_id)`` from a plain client
    once the episode has started. The row says how it ended, which processes dropped the bad message (each must say
    so once, and go on), how long from a refused answer to the episode's end, and what the recording lacks."""
    run_id = f"f{uuid.uuid4().hex[:6]}"
    recording = folder / f"{run_id}.mcap"
    with LocalStack(run_id=run_id, run_dir=folder / run_id, brains=[brain], record=recording) as stack:
        assert stack.bus is not None, "a started stack has its bus"
        seen = Inbox()
        stack.bus.subscribe(keys.commands_all(run_id), Command, inbox=seen)
        stack.bus.subscribe(keys.events(run_id), EpisodeEvent, inbox=seen)
        injector = threading.Thread(target=_inject_after_start, args=(stack.bus, run_id, inject), daemon=True)
        injector.start()
        spec = EpisodeSpec(active_brain=active_brain, max_sim_seconds=5, camera=SMALL_CAMERA)
        score = stack.run_episode(spec, wall_timeout_s=120)
        injector.join(timeout=30)
        recorded = "recording complete" if stack.recording_failure is None else "RECORDER DIED"
        alive = all(child.process.poll() is None for child in stack.children)
        logs = {child.role: child.log_path for child in stack.children}
    arrivals = seen.drain()
    refused = [r.arrival_ns for r in arrivals if isinstance(r.message, Command) and r.message.invalid]
    ends = [r.arrival_ns for r in arrivals if isinstance(r.message, EpisodeEvent) and r.message.kind == EventKind.END]
    detected = (ends[0] - refused[0]) / 1e9 if refused and ends else None
    # "dropped bad message" (at decode, or the recorder's: once per key) or "dropped bad camera frame" (a brain host's
    # image check: once)
    said_by = {role: log.read_text().count("dropped bad ") for role, log in logs.items()}
    droppers = [role if n == 1 else f"{role} (once on each of {n} keys)" for role, n in sorted(said_by.items()) if n]
    said = f"; dropped and logged once by {', '.join(droppers)}" if droppers else ""
    outcome = f"scored{said}; {recorded}; {'every process ran on' if alive else 'A PROCESS DIED'}"
    reason = f"{score.reason} ({score.detail})" if score.detail else str(score.reason)
    return Row(fault, outcome, reason, detected, orphans(run_id), missing_in_recording(recording, run_id, score))


def _inject_after_start(bus: Bus, run_id: str, inject: Callable[[Bus, str], None] | None) -> None:
    if inject is None:
        return
    events = Inbox()
    subscription = bus.subscribe(keys.events(run_id), EpisodeEvent, inbox=events)
    while (received := events.recv(timeout_s=60)) is not None and received.message.kind != EventKind.START:
        pass
    subscription.close()
    inject(bus, run_id)


def nan_brain(folder: Path) -> Row:
    """A user's brain that answers NaN mid-episode: its host refuses it, the simulator ends the episode
    brain_invalid."""
    (folder / "nan_brain.py").write_text(NAN_BRAIN)
    brain = BrainLaunch("nan_brain:NanAfter", options=(f"after={NAN_AFTER_FRAMES}",))
    with contextlib.chdir(folder):  # the brain host imports nan_brain from its working folder, as a user's would
        return bad_value_run(folder, fault="a brain answers NaN (lock-step)", brain=brain, active_brain="NanAfter")


def malformed_frame(folder: Path) -> Row:
    """A client publishes camera frames of width -1 (and one whose size does not match its bytes) on the simulator's
    camera key: the recorder, the brain host and the noise injector each drop them."""

    def inject(bus: Bus, run_id: str) -> None:
        header = Header(run_id=run_id, episode=0, seq=3, stamp_ns=150_000_000)
        frames = bus.publisher(keys.camera_raw(run_id), CameraFrame, Traffic.FRAMES_LOSSLESS)
        for width_px in (-1, 640):
            frames.publish(CameraFrame(header=header, width_px=width_px, height_px=48, data=bytes(64 * 48 * 3)))

    return bad_value_run(
        folder,
        fault="malformed camera frames from a client (width -1, wrong size)",
        brain=standing_still(),
        active_brain="constant",
        inject=inject,
    )


def nan_pose(folder: Path) -> Row:
    """A client publishes a Pose with x = y = NaN among the simulator's: dropped at decode by every subscriber (the
    scorer's splines died on it at the episode's end)."""

    def inject(bus: Bus, run_id: str) -> None:
        # For a frame still to come: it arrives before the simulator's own pose of that frame, so a scorer that took
        # it would have it in its splines (the simulator's pose 99 is then a repeat, ignored).
        header = Header(run_id=run_id, episode=0, seq=99, stamp_ns=99 * 50_000_000)
        bus.publisher(keys.pose(run_id), Pose, Traffic.EVENTS).publish(
            Pose(header=header, x_m=math.nan, y_m=math.nan, yaw_rad=0.0)
        )

    return bad_value_run(
        folder, fault="a pose of NaN from a client", brain=standing_still(), active_brain="constant", inject=inject
    )


def peak_rss_mb(pid: int) -> float:
    """The process's peak resident memory (VmHWM), in MB; 0 if it is gone."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return 0.0
    line = next((line for line in status.splitlines() if line.startswith("VmHWM:")), "VmHWM: 0 kB")
    return int(line.split()[1]) / 1024


BAD_INPUTS = [
    ["run", "--circuit", "nowhere"],
    ["run", "--brain", "hal"],
    ["run", "--camera", "big"],
    ["run", "--noise", "salt_pepper=lots"],
    ["run", "--variation", "line=purple"],
    ["run", "--laps", "0"],
    ["run", "--brain", "explicit", "--weights", "README.md"],
    ["run", "--brain", "memdccp", "--weights", "README.md"],
    ["run", "--brain", "constant", "--brain-option", "warp=9"],
    ["run", "--brain", "no_module:Brain"],
    ["run", "--brain", "missing_file.py"],
    ["matrix", "nowhere.yaml"],
    ["replay", "nowhere.mcap"],
    ["dataset", "build", "nowhere.mcap", "-o", "x"],
    ["train", "--model", "resnet", "--data", "x", "-o", "y"],
    ["brains", "check", "hal"],
    ["swap", "explicit", "--run", "nothing-running"],
]


def bad_inputs(folder: Path) -> Row:
    clean = 0
    for args in BAD_INPUTS:
        result = subprocess.run(
            [sys.executable, "-m", "orchestrator.cli", *args], capture_output=True, text=True, cwd=folder, timeout=120
        )
        last = result.stderr.strip().splitlines()[-1] if result.stderr.strip() else ""
        clean += (
            result.returncode in (1, 2) and "Traceback" not in result.stderr and ("error" in last or "failed" in last)
        )
    return Row(
        f"bad input: {len(BAD_INPUTS)} command lines",
        f"{clean} of {len(BAD_INPUTS)} end in one line naming the mistake",
        "exit 2 (usage) or 1",
        None,
        0,
    )


def table(rows: list[Row]) -> str:
    lines = ["| fault | outcome | typed reason | detected after | orphans | data lost |", "|---|---|---|---|---|---|"]
    for row in rows:
        detected = "-" if row.detected_s is None else f"{row.detected_s:.2f} s"
        lines.append(f"| {row.fault} | {row.outcome} | {row.reason} | {detected} | {row.orphans} | {row.data_lost} |")
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--flood-seconds", type=float, default=5.0, help="how long the flood lasts (default 5)")
    parser.add_argument(
        "--only",
        help="comma-separated faults: brain, simulator, noise, scorer, recorder, driver, "
        "router, router_restart, flood, nan_brain, bad_frame, nan_pose, input (default: all)",
    )
    args = parser.parse_args()
    faults = {
        "brain": lambda f: kill_child("brain", "constant", f),
        "simulator": lambda f: kill_child("simulator", "sim", f),
        "noise": lambda f: kill_child("noise", "noise", f),
        "scorer": lambda f: kill_child("scorer", "scorer", f),
        "recorder": kill_recorder,
        "driver": kill_driver,
        "router": lambda f: kill_child("router", "router", f, fault="kill -9 router (separate process)"),
        "router_restart": restart_router,
        "flood": lambda f: flood(f, args.flood_seconds),
        "nan_brain": nan_brain,
        "bad_frame": malformed_frame,
        "nan_pose": nan_pose,
        "input": bad_inputs,
    }
    chosen = args.only.split(",") if args.only else list(faults)
    unknown = set(chosen) - set(faults)
    if unknown:
        parser.error(f"unknown fault(s) {', '.join(sorted(unknown))} (known: {', '.join(faults)})")
    rows = []
    with tempfile.TemporaryDirectory(prefix="drivebench-faults-") as folder:
        for name in tqdm(chosen, desc="faults", unit="fault", file=sys.stderr):
            rows.append(faults[name](Path(folder)))
    print(table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
