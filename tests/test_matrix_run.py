"""Integration: matrices run end to end on real stacks (real processes, one real Zenoh router, real PyBullet)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from support.held_brain import MAX_HOLD_S, TARGET, Hold, pythonpath_with_support
from support.matrices import brain_killer, finished_rows, killing_matrix, write_matrix
from support.waits import wait_for

from orchestrator.matrix.load import load_matrix
from orchestrator.matrix.results import ResultStore
from orchestrator.matrix.runner import MatrixRunner, RunOptions

pytestmark = pytest.mark.integration

SHORT = "limits: {laps: 1, max_sim_seconds: 4}\ncamera: 96x72\n"


def drivebench(*args: str, **options) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "orchestrator.cli", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        **options,
    )


def started_by(launcher_pid: int) -> list[int]:
    """Live processes a launcher started (the launcher passes its pid in their environment)."""
    marker = f"DRIVEBENCH_PARENT_PID={launcher_pid}".encode()
    pids = []
    for entry in Path("/proc").iterdir():
        try:
            if entry.name.isdigit() and marker in (entry / "environ").read_bytes().split(b"\0"):
                if (entry / "stat").read_text().split(") ", 1)[1][0] != "Z":
                    pids.append(int(entry.name))
        except OSError:
            continue
    return pids


def test_two_episodes_of_different_brains_run_side_by_side_on_one_router(tmp_path):
    matrix = load_matrix(
        write_matrix(
            tmp_path,
            """
name: pair
brains: [explicit, {name: constant, options: {speed_mps: 1.0, yaw_rate_radps: 0.5}}]
circuits: [simple]
limits: {laps: 1, max_sim_seconds: 8}
camera: 96x72
""",
        )
    )
    progress = MatrixRunner(matrix, tmp_path / "out", RunOptions(workers=2)).run()
    assert (progress.done, progress.failed) == (2, 0)
    with ResultStore(tmp_path / "out", create=False) as store:
        results = {result.brain: result for result in store.results()}
    explicit, constant = results["explicit"], results["constant"]
    # They ran at the same time, on different run ids, and neither saw the other's commands.
    assert explicit.started_at < constant.ended_at and constant.started_at < explicit.ended_at
    assert explicit.run_id != constant.run_id
    assert explicit.score.brain == "explicit" and constant.score.brain == "constant"
    # The explicit brain drove its 8 s undisturbed; the constant brain circled at 1 m/s into a wall.
    assert explicit.reason == "time_limit" and explicit.score.metrics.steps == 160
    assert explicit.score.metrics.completed_distance_m > 15
    assert constant.reason == "crash"
    constant_m = constant.score.metrics
    assert constant_m.completed_distance_m == pytest.approx(1.0 * constant_m.sim_time_s, abs=0.1)
    assert explicit.score.metrics.command_rate_hz == pytest.approx(20.0, rel=0.05)


@pytest.mark.slow
def test_small_matrix_end_to_end_writes_results_and_report(tmp_path):
    path = write_matrix(
        tmp_path,
        f"""
name: small
brains: [explicit, {{name: constant, options: {{speed_mps: 2.0}}}}]
circuits: [simple, many_curves]
variations: {{line: [red, white]}}
{SHORT}""",
    )
    out = tmp_path / "out"
    run = drivebench("matrix", str(path), "-o", str(out), "--workers", "2")
    stdout, stderr = run.communicate(timeout=400)
    assert run.returncode == 0, stderr
    rows = finished_rows(out / "results.sqlite")
    assert len(rows) == 8 and {row[3] for row in rows} == {"done"}
    with ResultStore(out, create=False) as store:
        results = store.results()
    assert {(r.brain, r.circuit, r.variation) for r in results} == {
        (brain, circuit, f"line={line}")
        for brain in ("explicit", "constant")
        for circuit in ("simple", "many_curves")
        for line in ("red", "white")
    }
    for result in results:
        assert result.score.spec.world.line == result.variation.removeprefix("line=")
        assert (out / result.trajectory).is_file()
        assert (out / "episodes" / f"{result.index:04d}" / "score.json").is_file()
    report = (out / "report.md").read_text()
    assert "explicit" in report and "constant" in report and "many_curves" in report
    assert (out / "report.html").is_file() and (out / "episodes.csv").is_file()
    assert "8 episode(s) run (8 done, 0 failed)" in stderr


def test_resume_after_sigkill_reruns_only_what_did_not_finish(tmp_path):
    # The warm stack's brain drives two episodes, then holds the third 1 s (sim) into it until the test releases it:
    # the kill lands with exactly two finished, however fast the machine (the matrix once could finish between the
    # test's look at the results and its kill).
    hold = Hold(tmp_path)
    brain = {"name": TARGET, "options": hold.options(hold_at_s=1.0, hold_in_episode=2, brain="constant", speed_mps=1.0)}
    path = write_matrix(
        tmp_path,
        f"""
name: resumable
brains: [{json.dumps(brain)}]
circuits: [simple]
repetitions: 4
limits: {{laps: 1, max_sim_seconds: 4, brain_timeout_s: {MAX_HOLD_S + 30}}}
camera: 96x72
""",
    )
    out = tmp_path / "out"
    env = {**os.environ, "PYTHONPATH": pythonpath_with_support()}  # its brain hosts import support.held_brain
    first = drivebench("matrix", str(path), "-o", str(out), "--no-report", env=env)
    wait_for(
        hold.held_pid,
        timeout_s=120,
        what="the third episode held",
        alive=lambda: None if first.poll() is None else first.communicate()[1],
    )
    first.send_signal(signal.SIGKILL)
    first.wait()
    hold.release()  # the orphaned brain answers again, sees its launcher gone and stops like the rest
    before = finished_rows(out / "results.sqlite")
    assert len(before) == 2
    # Its stacks' processes notice that their launcher is gone and stop by themselves: nothing is orphaned.
    wait_for(
        lambda: not started_by(first.pid),
        timeout_s=10,
        what=f"the stack processes of {first.pid} to stop by themselves",
    )

    resumed = drivebench("matrix", str(path), "-o", str(out), "--resume", "--no-report", env=env)
    _, stderr = resumed.communicate(timeout=200)
    assert resumed.returncode == 0, stderr
    after = finished_rows(out / "results.sqlite")
    assert len(after) == 4 and {row[3] for row in after} == {"done"}
    assert [row for row in after if row[0] in {b[0] for b in before}] == before  # finished ones untouched
    assert f"{4 - len(before)} episode(s) run" in stderr and f"{len(before)} already in the results" in stderr


def test_a_brain_killed_mid_episode_is_a_failed_episode_and_the_matrix_goes_on(tmp_path, monkeypatch):
    monkeypatch.setenv("PYTHONPATH", pythonpath_with_support())  # the stack's brain hosts import support.held_brain
    hold = Hold(tmp_path)
    matrix = load_matrix(write_matrix(tmp_path, killing_matrix(hold)))
    killed: list[int] = []

    runner = MatrixRunner(matrix, tmp_path / "out", RunOptions(workers=1), on_change=brain_killer(hold, killed))
    progress = runner.run()
    assert killed, "the brain process of the first episode was never found"
    assert (progress.done, progress.failed) == (1, 1)
    with ResultStore(tmp_path / "out", create=False) as store:
        first, second = store.results()
    assert first.status == "failed" and first.failure_kind == "brain_died", first.failure
    assert "killed by SIGKILL" in first.failure.detail
    assert first.reason == "brain_lost" and first.score is not None  # scored up to the moment it died
    assert second.status == "done" and second.reason == "time_limit"  # a fresh brain drove the next one
    assert second.run_id != first.run_id  # on a new stack: a warm stack that failed an episode is replaced


def test_a_bad_matrix_file_is_one_line_naming_the_line_and_nothing_starts(tmp_path):
    path = write_matrix(tmp_path, "name: bad\nbrains: [explicit]\ncircuits: [simple, nowhere]\n")
    run = drivebench("matrix", str(path), "-o", str(tmp_path / "out"))
    _, stderr = run.communicate(timeout=60)
    assert run.returncode == 2
    assert len(stderr.strip().splitlines()) == 1 and ":3:" in stderr and "nowhere" in stderr, stderr
    assert not (tmp_path / "out").exists()


def test_a_matrix_name_that_leaves_runs_is_refused_at_its_line_and_nothing_is_written(tmp_path):
    work = tmp_path / "a" / "b" / "work"
    work.mkdir(parents=True)
    path = write_matrix(work, 'name: "x/../../../escaped"\nbrains: [explicit]\ncircuits: [simple]\n' + SHORT)
    run = drivebench("matrix", str(path), "--no-report", cwd=work)
    _, stderr = run.communicate(timeout=120)
    assert run.returncode == 2, stderr
    assert len(stderr.strip().splitlines()) == 1 and f"{path}:1:" in stderr and "matrix name" in stderr, stderr
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["a", "b", "m.yaml", "work"]  # no runs/, no escaped*


def test_resume_refuses_a_changed_matrix_and_takes_one_that_only_adds_episodes(tmp_path):
    base = "name: grows\nbrains: [{name: constant, options: {speed_mps: 1.0}}]\n"
    limits = "limits: {laps: 1, max_sim_seconds: 3}\ncamera: 96x72\n"
    original = base + "circuits: [simple, many_curves]\n" + limits
    path = write_matrix(tmp_path, original)
    out = tmp_path / "out"
    first = drivebench("matrix", str(path), "-o", str(out), "--no-report")
    _, stderr = first.communicate(timeout=300)
    assert first.returncode == 0, stderr
    before = finished_rows(out / "results.sqlite")
    assert len(before) == 2

    changed = {
        "limits": (original.replace("max_sim_seconds: 3", "max_sim_seconds: 2"), "max_sim_seconds 3.0 -> 2.0"),
        "seed": (original + "seed: 7\n", "seed 0 -> 7"),
        "circuit removed": (original.replace("[simple, many_curves]", "[simple]"), "circuits removed: many_curves"),
        "options": (original.replace("speed_mps: 1.0", "speed_mps: 2.0"), "options {'speed_mps': 1.0} -> {'speed"),
    }
    for what, (text, words) in changed.items():
        path.write_text(text)
        resumed = drivebench("matrix", str(path), "-o", str(out), "--resume", "--no-report")
        _, stderr = resumed.communicate(timeout=120)
        assert resumed.returncode == 2, (what, stderr)
        assert len(stderr.strip().splitlines()) == 1 and "matrix file changed" in stderr and words in stderr, stderr
        assert (out / "matrix.yaml").read_text() == original, what  # the folder still says what its results ran
        assert finished_rows(out / "results.sqlite") == before, what

    # Another repetition adds two episodes; expansion order puts one between the two finished ones.
    path.write_text(original + "repetitions: 2\n")
    resumed = drivebench("matrix", str(path), "-o", str(out), "--resume")
    _, stderr = resumed.communicate(timeout=300)
    assert resumed.returncode == 0, stderr
    assert "2 finished episode(s) kept, 2 new" in stderr, stderr
    after = finished_rows(out / "results.sqlite")
    assert len(after) == 4 and {row[3] for row in after} == {"done"}
    assert [row for row in after if row[0] in {b[0] for b in before}] == before  # finished ones untouched
    with ResultStore(out) as store:
        results = store.results()
    folders = [result.logs for result in results]
    assert len(set(folders)) == 4 and all((out / folder).is_dir() for folder in folders)  # none overwritten
    assert sorted(result.index for result in results) == [0, 1, 2, 3]
    assert (out / "matrix.yaml").read_text() == original + "repetitions: 2\n"
    assert "r1" in (out / "report.md").read_text()


def test_ctrl_c_on_a_two_worker_matrix_exits_cleanly_every_time(tmp_path):
    """SIGINT while two stacks run, at different moments: exit 130 with the resume hint every time. It aborted in
    about 1 run in 10 with "FATAL: exception not rethrown": Ctrl-C inside Thread.join() made Python take a running
    worker for stopped, and the interpreter shut down while that worker was still closing its Zenoh session."""
    path = write_matrix(
        tmp_path,
        "name: interrupted\nbrains: [explicit, {name: constant, options: {speed_mps: 1.0}}]\ncircuits: [simple]\n"
        # 12 episodes of up to 40 s, in real time: each lasts its wall time, so the last SIGINT (5 s after both
        # stacks started) finds episodes left to resume however fast the machine (in lock-step a warm stack ran
        # one in about a second, and a fast machine could finish all 12 first).
        "repetitions: 6\nlimits: {laps: 1, max_sim_seconds: 40}\ncamera: 96x72\nrealtime: true\n",
    )
    for attempt, delay_s in enumerate((0.5, 1.0, 2.0, 3.0, 4.0, 5.0, 1.5, 2.5)):
        out = tmp_path / f"out{attempt}"
        run = subprocess.Popen(
            [sys.executable, "-m", "orchestrator.cli", "matrix", str(path), "-o", str(out), "--workers", "2"],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            # SIGINT as a terminal sends it, even where the test runner itself was started with SIGINT ignored.
            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
        )
        wait_for(
            lambda: len(started_by(run.pid)) >= 4,  # both stacks are coming up
            timeout_s=120,
            what="the matrix to start its stacks",
            alive=lambda: None if run.poll() is None else run.communicate()[1],
        )
        time.sleep(delay_s)
        run.send_signal(signal.SIGINT)
        _, stderr = run.communicate(timeout=120)
        assert run.returncode == 130, f"attempt {attempt} (SIGINT after {delay_s} s): rc {run.returncode}\n{stderr}"
        assert "--resume` runs the rest" in stderr and "Traceback" not in stderr and "FATAL" not in stderr, stderr
