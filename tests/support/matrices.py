"""Matrix files written for a test, the finished rows of a results database, processes found by command line, and
what two runs of a matrix must have in common (the simulated metrics, the trajectories)."""

from __future__ import annotations

import json
import os
import signal
import sqlite3
from pathlib import Path

import numpy as np

from orchestrator.matrix.results import ResultStore
from protocol.messages import EpisodeScore
from support.held_brain import MAX_HOLD_S, TARGET, Hold


def write_matrix(folder: Path, body: str) -> Path:
    path = folder / "m.yaml"
    path.write_text(body)
    return path


def processes_with(text: str) -> list[int]:
    """Pids of live processes whose command line contains ``text`` (real /proc, no mocks)."""
    pids = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            cmdline = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
            state = (entry / "stat").read_text().split(") ", 1)[1][0]
        except OSError:
            continue
        if text in cmdline and state != "Z" and int(entry.name) != os.getpid():
            pids.append(int(entry.name))
    return pids


def finished_rows(database: Path) -> list[tuple]:
    if not database.exists():
        return []
    try:
        with sqlite3.connect(database, timeout=5) as db:
            return db.execute("SELECT key, run_id, started_at, status FROM episodes ORDER BY idx").fetchall()
    except sqlite3.OperationalError:  # created but no table yet
        return []


def results_by_key(out: Path) -> dict:
    with ResultStore(out, create=False) as store:
        return {result.key: result for result in store.results()}


# Score metrics measured in wall-clock time (how fast the machine was), not on the road: every comparison of two runs
# of one episode leaves these out (one list, so a new wall-clock metric is added once).
WALL_CLOCK_METRICS = frozenset(
    {
        "wall_time_s",
        "real_time_factor",
        "command_rate_hz",
        "command_latency_p50_ms",
        "command_latency_p95_ms",
        "inference_p50_ms",
        "inference_p95_ms",
        "mean_inference_time_s",
        "mean_brain_iterations_real_time_s",
        "brain_iterations_frequency_real_time_hz",
        "target_brain_iterations_simulated_time_hz",  # BM's: divided by the real-time factor
        "bm_mean_inference_time_s",
    }
)


# What the simulation alone decides (the rest of EpisodeMetrics measures wall time: latency, inference, rates).
SIMULATED = (
    "sim_time_s",
    "steps",
    "completed_distance_m",
    "average_speed_mps",
    "percentage_completed",
    "bm_lap_seconds",
    "position_deviation_mae",
    "position_deviation_total_err",
    "suddenness_distance",
    "progress_m",
    "progress_laps",
    "completed_laps",
    "lap_times_s",
    "cross_track_mean_m",
    "cross_track_rms_m",
    "cross_track_max_m",
    "cross_track_p95_m",
    "off_track_events",
)
TRAJECTORY = ("stamp_s", "x_m", "y_m", "yaw_rad", "speed_mps")


def simulated(score: EpisodeScore) -> dict:
    return {"reason": score.reason, "spec": score.spec, **{f: getattr(score.metrics, f) for f in SIMULATED}}


def trajectory(path: Path) -> dict[str, np.ndarray]:
    with np.load(path) as data:
        return {name: data[name] for name in TRAJECTORY}


def assert_same_trajectory(one: dict[str, np.ndarray], other: dict[str, np.ndarray], *, what: str) -> None:
    for name in TRAJECTORY:
        assert one[name].shape == other[name].shape and np.array_equal(one[name], other[name]), f"{what}: {name}"


def killing_matrix(hold: Hold) -> str:
    """One brain that drives slowly for up to 30 s (sim), twice; the first brain holds its episode 2 s into it until
    ``hold`` is released (:class:`~support.held_brain.HeldBrain`), so a kill provably lands inside the episode. The
    brain timeout is long enough for a loaded machine's kill to come before the simulator gives up on the answer."""
    brain = {"name": TARGET, "options": hold.options(hold_at_s=2.0, brain="constant", speed_mps=0.5)}
    return f"""
name: killing
brains: [{json.dumps(brain)}]
circuits: [simple]
repetitions: 2
limits: {{laps: 1, max_sim_seconds: 30, brain_timeout_s: {MAX_HOLD_S + 30}}}
camera: 96x72
"""


def brain_killer(hold: Hold, killed: list[int]):
    """A matrix ``on_change`` callback that SIGKILLs the brain host of the first episode while it holds that episode
    (2 s of sim time into it), once, appending the pid to ``killed``; then releases the hold, so the next episode's
    brain drives through."""

    def kill_the_first_brain_while_it_holds_its_episode(progress) -> None:
        del progress  # the hold, not the progress shown, says the episode is under way and cannot end yet
        if killed or (pid := hold.held_pid()) is None:
            return
        os.kill(pid, signal.SIGKILL)
        killed.append(pid)
        hold.release()

    return kill_the_first_brain_while_it_holds_its_episode
