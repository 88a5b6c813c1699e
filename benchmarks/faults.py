"""The chaos table: every fault an operator meets, run against real stacks, one row each.

For each fault: what happened to the episode (outcome), the typed reason it was given, how long after the fault
that reason was known, how many processes of that stack were still running two seconds after it closed (orphans),
and what data was lost. Faults: kill -9 of each process mid-episode (brain, simulator, noise injector, scorer,
recorder, an attached driver, a separate router), the router killed and started again under an attached run on
long-lived services (the compose deployment), a flood of garbage on the command and camera keys (with each
process's peak memory), and bad input on the command line. Not a timed test: detection times are measured, not
asserted; run it to see the table.

    .venv/bin/python benchmarks/faults.py [--flood-seconds 5] [--only brain,recorder,...]
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from dataclasses import dataclass
from pathlib import Path

from tqdm import tqdm

from orchestrator.launcher import BrainLaunch, LocalStack, StackFailure, free_loopback_port
from protocol import keys
from protocol.bus import BusError, Inbox, Traffic, probe_router
from protocol.messages import CameraSpec, EpisodeEvent, EpisodeSpec, EventKind, Pose
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


def clean_env(**variables: str) -> dict[str, str]:
    return {k: v for k, v in os.environ.items() if not k.startswith("DRIVEBENCH_")} | variables


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
        events = Inbox()
        stack.bus.subscribe(keys.events(run_id), EpisodeEvent, inbox=events)
        env = {k: v for k, v in os.environ.items() if not k.startswith("DRIVEBENCH_")}
        driver = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "orchestrator.cli",
                "run",
                "--attach",
                "--router",
                stack.endpoint,
                "--run-id",
                run_id,
                "--max-sim-seconds",
                "600",
                "--realtime",
                "--camera",
                "64x48",
                "--out",
                str(folder / f"{run_id}-driver"),
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            env=env,
            start_new_session=True,
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
            stop = threading.Event()
            sent = [0]

            def spam() -> None:
                publishers = [
                    stack.bus.publisher(keys.command(run_id, "explicit"), Pose, Traffic.COMMANDS),
                    stack.bus.publisher(keys.camera_perturbed(run_id), Pose, Traffic.FRAMES),
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
    worst = max(growth, key=growth.get)
    outcome = "scored" if same else "scored, DIFFERENT"
    return Row(
        f"flood: {count:,} garbage messages in {seconds:g} s",
        f"{outcome}; peak memory +{max(growth[worst], 0):.0f} MB at most ({worst}, {noisy_peaks[worst]:.0f} MB)",
        str(noisy.reason),
        None,
        orphans(run_id),
        "none (identical trajectory)" if same else "trajectory changed",
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
        "router, router_restart, flood, input (default: all)",
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
