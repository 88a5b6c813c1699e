"""Integration: matrices on a real Ray cluster on this machine (a head with no episode slots plus worker nodes, each
its own raylet, all on 127.0.0.1), against the same matrices run locally.

Ray is the optional extra ``cluster``: skipped without it on a developer's machine, a failure in CI.
"""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import msgspec
import numpy as np
import pytest
import yaml

# Ray resolves a loopback address to the host's outward address unless it believes it runs single-machine, and only
# loopback may be used here: pin every Ray process (this one, the CLI's, the raylets' workers) to 127.0.0.1. Read
# when ray is imported, so before it.
os.environ["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"] = "0"

import needs  # noqa: E402

ray = needs.require("ray")

from mcap_validation import assert_valid_mcap  # noqa: E402
from ray.cluster_utils import Cluster  # noqa: E402
from support.held_brain import MAX_HOLD_S, TARGET, Hold, pythonpath_with_support  # noqa: E402
from support.matrices import (  # noqa: E402
    WALL_CLOCK_METRICS,
    assert_same_trajectory,
    brain_killer,
    finished_rows,
    killing_matrix,
    processes_with,
    results_by_key,
    simulated,
    trajectory,
    write_matrix,
)
from support.waits import wait_for  # noqa: E402

from orchestrator.matrix.executor import read_episode_config  # noqa: E402
from orchestrator.matrix.load import load_matrix  # noqa: E402
from orchestrator.matrix.ray_options import EPISODE_SLOT, RayOptions  # noqa: E402
from orchestrator.matrix.ray_runner import RayMatrixRunner  # noqa: E402
from orchestrator.matrix.results import ResultStore  # noqa: E402
from orchestrator.matrix.runner import MatrixRunner, RunOptions  # noqa: E402

pytestmark = [pytest.mark.integration, pytest.mark.slow]

LOOPBACK = "127.0.0.1"
# Node deaths found in about 2 s rather than Ray's default 15 s.
FAST_HEALTH = {"health_check_period_ms": 500, "health_check_failure_threshold": 4}


def worker_node(cluster: Cluster, *, slots: int, gpus: int = 0):
    return cluster.add_node(num_cpus=1, num_gpus=gpus, resources={EPISODE_SLOT: slots}, node_ip_address=LOOPBACK)


@pytest.fixture(scope="module")
def cluster():
    """A head that runs no episode (no CPUs, no episode_slot) and one worker node with one slot and one GPU (Ray's
    bookkeeping only: nothing here uses it); this process is the driver. Its nodes' processes, and so the brain hosts
    their tasks start, can import the tests' own brains (support.held_brain)."""
    with pytest.MonkeyPatch.context() as patch:  # for the nodes tests add too, and the CLI drivers they start
        patch.setenv("PYTHONPATH", pythonpath_with_support())
        cluster = Cluster(
            initialize_head=True,
            connect=False,
            head_node_args={"num_cpus": 0, "node_ip_address": LOOPBACK, "_system_config": FAST_HEALTH},
        )
        worker_node(cluster, slots=1, gpus=1)
        cluster.wait_for_nodes()
        ray.init(address=cluster.address, logging_level="WARNING", log_to_driver=False)
        yield cluster
        ray.shutdown()
        cluster.shutdown()


def held_explicit(hold: Hold, *, hold_in_episode: int = 0) -> str:
    """A matrix's brains line: the explicit brain, held 1 s (sim) into an episode until the test releases it
    (support.held_brain), so what the test does while it drives provably lands mid-episode."""
    options = hold.options(hold_at_s=1.0, hold_in_episode=hold_in_episode, brain="explicit")
    return f"brains: [{json.dumps({'name': TARGET, 'options': options})}]"


# Long enough for a held brain's answer: the test acts and releases it in seconds, even on a loaded machine.
HELD_TIMEOUT = f"brain_timeout_s: {MAX_HOLD_S + 30}"


def drivebench(*args: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "orchestrator.cli", *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )


# The lock-step part of a trajectory (the simulator's poses); the live-progress samples beside them are taken at a
# wall-clock rate by the scorer, so they differ between any two runs, local or not.
POSE_ARRAYS = ("stamp_s", "x_m", "y_m", "yaw_rad", "speed_mps")


def road_metrics(result) -> dict:
    metrics = msgspec.to_builtins(result.score.metrics)
    return {name: value for name, value in metrics.items() if name not in WALL_CLOCK_METRICS}


def trajectories(out: Path) -> dict[str, dict[str, bytes]]:
    """Every episode's pose arrays as raw bytes, by episode key."""
    with ResultStore(out, create=False) as store:
        results = store.results()
    arrays = {}
    for result in results:
        with np.load(out / result.trajectory) as data:
            arrays[result.key] = {name: data[name].tobytes() for name in POSE_ARRAYS}
    return arrays


def test_a_matrix_on_the_cluster_gives_the_local_results_bit_for_bit_with_its_recordings(cluster, tmp_path):
    matrix = load_matrix(
        write_matrix(
            tmp_path,
            """
name: same
brains: [explicit, {name: constant, options: {speed_mps: 1.5, yaw_rate_radps: 0.2}}]
circuits: [simple]
limits: {laps: 1, max_sim_seconds: 6}
camera: 96x72
""",
        )
    )
    local = MatrixRunner(matrix, tmp_path / "local", RunOptions(workers=1)).run()
    artifacts = tmp_path / "shared"
    live_seen: list = []  # what the progress lanes showed: live metrics streamed from the tasks

    def watch_lanes(progress) -> None:
        live_seen.extend(worker.live for worker in progress.workers if worker.live is not None)

    # Each episode also asks for half a GPU, as a neural brain would: Ray's own GPU field, not a custom resource.
    remote = RayMatrixRunner(
        matrix,
        tmp_path / "ray",
        RunOptions(record=True),
        on_change=watch_lanes,
        ray_options=RayOptions(address=cluster.address, artifacts=artifacts, resources={EPISODE_SLOT: 1.0, "GPU": 0.5}),
    ).run()
    assert live_seen  # live metrics streamed from the tasks (6 s of sim can pass in under a second with gl)
    assert (local.done, local.failed) == (remote.done, remote.failed) == (2, 0)
    local_arrays, ray_arrays = trajectories(tmp_path / "local"), trajectories(tmp_path / "ray")
    assert local_arrays.keys() == ray_arrays.keys() and len(local_arrays) == 2
    for key, arrays in local_arrays.items():
        assert len(np.frombuffer(arrays["x_m"])) > 50, key  # a real drive, not two empty files
        assert ray_arrays[key] == arrays, f"{key}: the trajectory on Ray differs from the local one"
    with ResultStore(tmp_path / "local", create=False) as store:
        local_results = {r.key: r for r in store.results()}
    with ResultStore(tmp_path / "ray", create=False) as store:
        ray_results = store.results()
    worker = next(node for node in ray.nodes() if node["Alive"] and node["Resources"].get(EPISODE_SLOT))
    for result in ray_results:
        assert road_metrics(result) == road_metrics(local_results[result.key])
        assert result.reason == local_results[result.key].reason
        assert result.node == f"{LOOPBACK}/{worker['NodeID'][:8]}" and result.lost_attempts == ()
        # The small files came back into the output folder; the recording stayed on the shared path.
        folder = tmp_path / "ray" / "episodes" / f"{result.index:04d}"
        assert {"score.json", "config.yaml", "trajectory.npz"} <= {p.name for p in folder.iterdir()}
        assert (folder / "logs" / "simulator.log").stat().st_size > 0
        assert not (folder / "recording.mcap").exists()
        recording = Path(result.recording)
        assert recording == artifacts / "episodes" / f"{result.index:04d}" / "recording.mcap"
        assert recording.stat().st_size > 10_000
    assert_valid_mcap(*(Path(r.recording) for r in ray_results))
    # Each task killed its process group on the way out: nothing of either stack is left.
    assert not [pid for r in ray_results for pid in processes_with(f"--run-id {r.run_id}")]
    assert all(r.node and r.lost_attempts == () for r in local_results.values())


def test_warm_episode_slots_give_the_results_of_a_fresh_stack_per_episode(cluster, tmp_path):
    """Warm (the default on Ray): a long-lived actor per episode slot keeps its stack across episodes; the same matrix
    with --fresh-stacks (a task and a new stack per episode) gives the same trajectories and simulated metrics."""
    matrix = load_matrix(
        write_matrix(
            tmp_path,
            """
name: slots
brains: [explicit, {name: noisy, options: {burst_probability: 0.2, steering_noise_radps: 0.8}}]
circuits: [simple, many_curves]
limits: {laps: 1, max_sim_seconds: 3}
camera: 96x72
""",
        )
    )
    ray_options = RayOptions(address=cluster.address)
    fresh = RayMatrixRunner(matrix, tmp_path / "fresh", RunOptions(fresh_stacks=True), ray_options=ray_options).run()
    warm = RayMatrixRunner(matrix, tmp_path / "warm", RunOptions(), ray_options=ray_options).run()
    assert (fresh.done, fresh.failed, warm.done, warm.failed) == (4, 0, 4, 0)
    fresh_results, warm_results = results_by_key(tmp_path / "fresh"), results_by_key(tmp_path / "warm")
    assert fresh_results.keys() == warm_results.keys()
    # Fresh: a stack per episode. Warm: the one slot (one node, one episode_slot) ran all four on one stack, both
    # episodes of a brain one after the other, so its brain host changed once.
    assert len({result.run_id for result in fresh_results.values()}) == 4
    (run_id,) = {result.run_id for result in warm_results.values()}
    in_order = sorted(warm_results.values(), key=lambda result: result.started_at)
    assert [result.score.header.episode for result in in_order] == [0, 1, 2, 3]
    assert in_order[0].brain == in_order[1].brain != in_order[2].brain == in_order[3].brain
    for key, result in warm_results.items():
        other = fresh_results[key]
        assert simulated(result.score) == simulated(other.score), key
        warm_path, fresh_path = tmp_path / "warm" / result.trajectory, tmp_path / "fresh" / other.trajectory
        assert_same_trajectory(trajectory(warm_path), trajectory(fresh_path), what=key)
        assert len(trajectory(warm_path)["x_m"]) == result.score.metrics.steps + 1  # its own poses only
        assert (tmp_path / "warm" / result.logs / "simulator.log").stat().st_size > 0
    # The noisy brain's bursts did change the driving, so the equality above is not a trivial one.
    assert len({round(r.score.metrics.completed_distance_m, 6) for r in warm_results.values()}) == 4
    # The matrix closed its slot: no process of the stack is left, and the slot's resources are free again.
    assert not processes_with(f"--run-id {run_id}")
    wait_for(lambda: ray.available_resources().get(EPISODE_SLOT) == 1.0, timeout_s=30, what="the episode slot freed")


def test_a_slot_whose_brain_died_mid_episode_replaces_its_stack_and_the_episode_is_not_retried(cluster, tmp_path):
    hold = Hold(tmp_path)
    matrix = load_matrix(write_matrix(tmp_path, killing_matrix(hold)))
    killed: list[int] = []

    progress = RayMatrixRunner(
        matrix,
        tmp_path / "out",
        RunOptions(),
        ray_options=RayOptions(address=cluster.address),
        on_change=brain_killer(hold, killed),
    ).run()
    assert killed, "the brain process of the first episode was never found"
    assert (progress.done, progress.failed) == (1, 1)
    with ResultStore(tmp_path / "out", create=False) as store:
        first, second = store.results()
    assert first.status == "failed" and first.failure_kind == "brain_died", first.failure
    assert first.lost_attempts == () == second.lost_attempts  # the episode's own failure: a result, not retried
    assert second.status == "done" and second.reason == "time_limit"
    assert second.run_id != first.run_id and second.node == first.node  # the same slot, on a new stack


@pytest.mark.parametrize("fresh_stacks", [False, True], ids=["warm_slots", "fresh_tasks"])
def test_a_worker_node_removed_mid_matrix_loses_nothing(cluster, tmp_path, fresh_stacks):
    second = worker_node(cluster, slots=1)
    cluster.wait_for_nodes()
    # Every brain holds its first episode 1 s (sim) in until the node is gone: neither can end before both drive.
    hold = Hold(tmp_path)
    matrix = load_matrix(
        write_matrix(
            tmp_path,
            f"""
name: dying
{held_explicit(hold)}
circuits: [simple]
repetitions: 3
limits: {{laps: 1, max_sim_seconds: 600, {HELD_TIMEOUT}}}
camera: 96x72
""",
        )
    )
    removed = threading.Event()

    def remove_the_second_node_once_both_drive(progress) -> None:
        driving = [worker for worker in progress.workers if worker.episode is not None and worker.live is not None]
        if not removed.is_set() and not progress.done and len(driving) == 2:  # both stacks up, both cars moving
            cluster.remove_node(second, allow_graceful=False)
            removed.set()
            hold.release()

    progress = RayMatrixRunner(
        matrix,
        tmp_path / "out",
        RunOptions(fresh_stacks=fresh_stacks),
        ray_options=RayOptions(address=cluster.address),
        on_change=remove_the_second_node_once_both_drive,
    ).run()
    assert removed.is_set(), "the second node was never removed mid-matrix"
    assert (progress.done, progress.failed) == (3, 0)
    with ResultStore(tmp_path / "out", create=False) as store:
        results = store.results()
    assert [r.status for r in results] == ["done"] * 3  # one row each: nothing lost, nothing counted twice
    lost = [r for r in results if r.lost_attempts]
    assert len(lost) == 1, [(r.key, r.lost_attempts) for r in results]
    second_label = f"{LOOPBACK}/{second.node_id[:8]}"
    assert lost[0].node != second_label  # it ran again on the node that lives
    assert lost[0].lost_attempts[0].node == second_label
    # An episode slot's stream says so first (ActorUnavailableError); a task's (--fresh-stacks) names the node.
    lost_errors = ("ActorUnavailableError", "ActorDiedError", "NodeDiedError", "WorkerCrashedError")
    assert lost[0].lost_attempts[0].error.startswith(lost_errors)
    assert {r.node for r in results} == {lost[0].node}
    # The report's episode table says where each ran and what was lost on the way.
    from orchestrator.report.matrix import write_report

    write_report(tmp_path / "out")
    with open(tmp_path / "out" / "episodes.csv", newline="") as file:
        rows = list(csv.DictReader(file))
    assert sorted(row["lost_attempts"] for row in rows) == ["0", "0", "1"]
    assert {row["node"] for row in rows} == {lost[0].node}


def test_past_its_retries_a_node_death_is_a_failed_row_of_kind_node_died(cluster, tmp_path):
    second = worker_node(cluster, slots=1)
    cluster.wait_for_nodes()
    # Both brains hold their episode 1 s (sim) in until the node is gone, so both surely drive at once: two laps
    # each (seconds of wall time) once let the first end before the second's stack was up on a fast machine.
    hold = Hold(tmp_path)
    matrix = load_matrix(
        write_matrix(
            tmp_path,
            f"""
name: unlucky
{held_explicit(hold)}
circuits: [simple]
repetitions: 2
limits: {{laps: 1, max_sim_seconds: 600, {HELD_TIMEOUT}}}
camera: 96x72
""",
        )
    )
    removed = threading.Event()

    def remove_the_second_node_once_both_drive(progress) -> None:
        driving = [worker for worker in progress.workers if worker.episode is not None and worker.live is not None]
        if not removed.is_set() and len(driving) == 2:
            cluster.remove_node(second, allow_graceful=False)
            removed.set()
            hold.release()

    progress = RayMatrixRunner(
        matrix,
        tmp_path / "out",
        RunOptions(),
        ray_options=RayOptions(address=cluster.address, node_retries=0),
        on_change=remove_the_second_node_once_both_drive,
    ).run()
    assert removed.is_set()
    assert (progress.done, progress.failed) == (1, 1)
    with ResultStore(tmp_path / "out", create=False) as store:
        failed = [r for r in store.results() if r.status == "failed"]
    assert len(failed) == 1 and failed[0].failure_kind == "node_died", failed
    assert failed[0].node == failed[0].lost_attempts[0].node == f"{LOOPBACK}/{second.node_id[:8]}"
    assert failed[0].score is None  # never counted as a driven episode
    from orchestrator.report.matrix import write_report

    files = write_report(tmp_path / "out")  # a row with no trajectory and no logs still reports
    assert "node_died" in files.markdown.read_text()


def running_episodes(out: Path) -> list[str]:
    """Run ids of the episodes whose folder is there (config.yaml written) but whose result is not."""
    finished = {row[0] for row in finished_rows(out / "results.sqlite")}
    run_ids = []
    for path in sorted(out.glob("episodes/*/config.yaml")):
        try:
            config = read_episode_config(path)
        except (yaml.YAMLError, msgspec.ValidationError):  # caught half-written
            continue
        if config.key not in finished:
            run_ids.append(config.run_id)
    return run_ids


def test_driver_killed_then_resume_runs_only_what_did_not_finish(cluster, tmp_path):
    # The slot's warm brain drives one episode, then holds the second 1 s (sim) in until the driver is dead: the kill
    # finds exactly one finished and one under way, however fast the machine.
    hold = Hold(tmp_path)
    path = write_matrix(
        tmp_path,
        f"""
name: resumable
{held_explicit(hold, hold_in_episode=1)}
circuits: [simple]
repetitions: 3
limits: {{laps: 1, max_sim_seconds: 3, {HELD_TIMEOUT}}}
camera: 96x72
""",
    )
    out = tmp_path / "out"
    # --artifacts on the output folder (one machine): the episode folders, config.yaml with its run id, land there.
    first = drivebench(
        "matrix", str(path), "-o", str(out), "--ray", cluster.address, "--artifacts", str(out), "--no-report"
    )
    wait_for(
        hold.held_pid,
        timeout_s=120,
        what="the second episode held",
        alive=lambda: None if first.poll() is None else first.communicate()[1],
    )
    first.send_signal(signal.SIGKILL)
    first.wait()
    before = finished_rows(out / "results.sqlite")
    assert len(before) == 1
    # The episode that was running when the driver died: its stack does not outlive it (Ray ends the dead driver's
    # tasks; the stack's processes watch their parent).
    cut_short = running_episodes(out)
    assert cut_short, "no episode was running when the driver was killed"
    deadline = time.monotonic() + 20
    while any(processes_with(f"--run-id {run_id}") for run_id in cut_short):
        assert time.monotonic() < deadline, f"orphaned stack processes of {cut_short}"
        time.sleep(0.2)
    hold.release()  # for the resumed run's brain, which would otherwise hold its second episode too
    resumed = drivebench("matrix", str(path), "-o", str(out), "--ray", cluster.address, "--resume", "--no-report")
    _, stderr = resumed.communicate(timeout=200)
    assert resumed.returncode == 0, stderr
    after = finished_rows(out / "results.sqlite")
    assert len(after) == 3 and {row[3] for row in after} == {"done"}
    assert [row for row in after if row[0] in {b[0] for b in before}] == before  # finished ones untouched
    assert f"{3 - len(before)} episode(s) run" in stderr and f"{len(before)} already in the results" in stderr
    assert "Ray cluster" in stderr


def test_ctrl_c_on_the_driver_kills_the_slots_and_their_stacks(cluster, tmp_path):
    # The first episode holds 1 s (sim) in, never released: the Ctrl-C lands mid-episode however fast the machine.
    hold = Hold(tmp_path)
    path = write_matrix(
        tmp_path,
        f"name: interrupted\n{held_explicit(hold)}\ncircuits: [simple]\nrepetitions: 3\n"
        f"limits: {{laps: 2, max_sim_seconds: 600, {HELD_TIMEOUT}}}\ncamera: 96x72\n",
    )
    out = tmp_path / "out"
    run = subprocess.Popen(
        [sys.executable, "-m", "orchestrator.cli", "matrix", str(path), "-o", str(out), "--ray", cluster.address]
        + ["--artifacts", str(out), "--no-report"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),  # as a terminal sends it
    )
    run_ids = wait_for(
        lambda: hold.held_pid() and [r for r in running_episodes(out) if len(processes_with(f"--run-id {r}")) >= 4],
        timeout_s=120,
        what="an episode held on a slot's stack",
        alive=lambda: None if run.poll() is None else run.communicate()[1],
    )
    run.send_signal(signal.SIGINT)
    _, stderr = run.communicate(timeout=120)
    assert run.returncode == 130, stderr
    assert "Traceback" not in stderr, stderr
    # The slot stopped its episode and killed its stack's process group, then the actor went: nothing is left.
    wait_for(lambda: not processes_with(f"--run-id {run_ids[0]}"), timeout_s=20, what="the slot's stack gone")
    wait_for(lambda: ray.available_resources().get(EPISODE_SLOT) == 1.0, timeout_s=30, what="the episode slot freed")


def test_a_resource_no_node_has_fails_at_once_in_one_line(cluster, tmp_path):
    path = write_matrix(tmp_path, "name: greedy\nbrains: [explicit]\ncircuits: [simple]\n")
    started = time.monotonic()
    run = drivebench(
        "matrix", str(path), "-o", str(tmp_path / "out"), "--ray", cluster.address, "--ray-resource", "GPU=2"
    )
    _, stderr = run.communicate(timeout=60)
    assert run.returncode == 1
    lines = stderr.strip().splitlines()
    assert "no node of the Ray cluster has what one episode asks for (episode_slot=1, GPU=2)" in lines[-1]
    assert "Traceback" not in stderr
    assert time.monotonic() - started < 30
    assert finished_rows(tmp_path / "out" / "results.sqlite") == []


def test_an_address_where_no_cluster_answers_is_one_line_at_once(tmp_path):
    path = write_matrix(tmp_path, "name: alone\nbrains: [explicit]\ncircuits: [simple]\n")
    started = time.monotonic()
    run = drivebench("matrix", str(path), "-o", str(tmp_path / "out"), "--ray", f"{LOOPBACK}:1")
    _, stderr = run.communicate(timeout=60)
    assert run.returncode == 1
    assert stderr.strip().splitlines()[-1] == (
        f"drivebench: the stack could not run: no Ray cluster at "
        f"'{LOOPBACK}:1': nothing answers there (Connection refused)"
    )
    assert time.monotonic() - started < 30
