"""Sandboxed brain hosts (issue 42): ``drivebench run --sandbox`` runs the brain host inside bubblewrap, and each
hostile brain of ``tests/support/hostile/`` is contained (checked from outside), typed in the run's ``--json``
result, and the test process carries on. Real sandboxed processes on a real stack; small limits so each run is
short."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest
from needs import require_bubblewrap

from orchestrator.stack import sandbox
from orchestrator.stack.sandbox import Sandbox

pytestmark = pytest.mark.integration

TESTS = Path(__file__).resolve().parent
SMALL_LIMITS = (
    "memory_bytes=536870912",  # 256 MiB of address space was seen to fail the host's own thread starts
    "max_processes=64",
    "cpu_seconds=4",
    "file_size_bytes=1048576",
    "output_bytes=1048576",
    "start_timeout_s=10",
)


@pytest.fixture(autouse=True)
def _bubblewrap():
    require_bubblewrap()


def uid_processes(uid: int) -> set[int]:
    """The pids of processes running as ``uid`` now."""
    pids = set()
    for entry in Path("/proc").iterdir():
        try:
            status = (entry / "status").read_text()
        except (OSError, ValueError):
            continue
        line = next((line for line in status.splitlines() if line.startswith("Uid:")), "")
        if entry.name.isdigit() and line.split()[1:2] == [str(uid)]:
            pids.add(int(entry.name))
    return pids


def run_sandboxed(tmp_path: Path, brain: str, *options: str, extra: tuple[str, ...] = ()) -> tuple[dict, Path]:
    """``drivebench run --sandbox --json`` of hostile brain ``brain`` (``module:Class`` under support.hostile);
    its last stdout line as JSON (a score or a failure record), and its run folder. The test process runs it as a
    child and goes on, whatever the brain does."""
    out = tmp_path / "run"
    argv = [sys.executable, "-m", "orchestrator.cli", "run", "--sandbox", "--json", "--max-sim-seconds", "2"]
    argv += ["--out", str(out), "--brain", f"support.hostile.{brain}", *extra]
    for option in options:
        argv += ["--brain-option", option]
    for limit in SMALL_LIMITS:
        argv += ["--sandbox-limit", limit]
    before = uid_processes(sandbox.NOBODY_UID)
    result = subprocess.run(argv, cwd=TESTS, capture_output=True, text=True, timeout=240)
    lines = result.stdout.strip().splitlines()
    assert lines, f"no JSON on stdout (exit {result.returncode}): {result.stderr[-2000:]}"
    left = uid_processes(sandbox.NOBODY_UID) - before
    assert not left, f"sandboxed processes outlived their run: {sorted(left)}"
    return json.loads(lines[-1]), out


def test_a_good_brain_is_scored_in_its_sandbox_connected_only_through_the_unix_socket(tmp_path):
    record, out = run_sandboxed(tmp_path, "base:Driving")
    assert record["reason"] == "time_limit", record
    assert record["metrics"]["steps"] == 40
    log = (out / "logs" / "brain-Driving.log").read_text()
    assert "sandboxed: true" in log
    assert "unixsock-stream//bus.sock" in log and "tcp/" not in log.split("resolved config:")[1].split("brain:")[0]


def test_a_tcp_connection_to_a_listener_outside_never_arrives(tmp_path):
    with socket.socket() as listener:
        listener.bind(("127.0.0.1", 0))
        listener.listen()
        listener.setblocking(False)
        record, _ = run_sandboxed(tmp_path, "network:NetworkBrain", f"port={listener.getsockname()[1]}")
        with pytest.raises(BlockingIOError):
            listener.accept()  # nothing ever connected
    assert record["failure"] == "sandbox_violation", record


def test_a_secret_in_a_path_outside_the_sandbox_is_not_there(tmp_path):
    secret = tmp_path / "board" / "secret-seed"
    secret.parent.mkdir()
    secret.write_text("s3cr3t-0451\n")
    record, out = run_sandboxed(tmp_path, "secret:SecretBrain", f"path={json.dumps(str(secret))}")
    # Not there, so the brain crashed: a brain death (the sandbox cannot tell a missing file from a hidden one).
    assert record["failure"] == "brain_died" and "FileNotFoundError" in record["detail"], record
    assert "s3cr3t" not in (out / "logs" / "brain-SecretBrain.log").read_text()


def test_a_path_to_hide_inside_a_bound_folder_is_covered(tmp_path):
    """A hidden path under a folder bound into the sandbox (a board's data folder inside the project) is empty."""
    visible = tmp_path / "project"
    hidden = visible / "board"
    hidden.mkdir(parents=True)
    (hidden / "secret-seed").write_text("s3cr3t-0451\n")
    (visible / "code.txt").write_text("readable\n")
    (visible / "seed.txt").write_text("s3cr3t-0451\n")  # a hidden file, beside the folder
    bus_socket = tmp_path / "bus.sock"
    with socket.socket(socket.AF_UNIX) as listener:
        listener.bind(str(bus_socket))
        box = Sandbox(scratch_dir=tmp_path / "scratch", hidden_paths=(hidden, visible / "seed.txt"))
        script = "\n".join(
            [
                "import os",
                f"print(open({str(visible / 'code.txt')!r}).read().strip(), os.listdir({str(hidden)!r}))",
                "try:",
                f"    print(open({str(visible / 'seed.txt')!r}).read())",
                "except PermissionError:",
                "    print('no seed')",  # a hidden file is /dev/null on a mount without devices: not even empty
            ]
        )
        confined = sandbox.spawn(
            box,
            command=[sandbox.interpreter(), "-c", script],
            log_path=tmp_path / "log.txt",
            socket_path=bus_socket,
            readable=[*sandbox.python_paths(), visible],
        )
        assert confined.process.wait(timeout=60) == 0, (tmp_path / "log.txt").read_text()
    confined.failure()  # joins the output thread
    assert (tmp_path / "log.txt").read_text().split() == ["readable", "[]", "no", "seed"]


def test_a_write_outside_the_scratch_is_refused(tmp_path):
    target = TESTS / "support" / "hostile" / f"written-{os.getpid()}.txt"  # in the project: bound read-only
    record, out = run_sandboxed(tmp_path, "writer:WriterBrain", f"path={json.dumps(str(target))}")
    assert record["failure"] == "sandbox_violation", record
    assert not target.exists()
    assert (out / "scratch" / "WriterBrain" / "inside-scratch.txt").read_text() == "allowed\n"


def test_hundreds_of_processes_stop_at_the_process_limit(tmp_path):
    record, _ = run_sandboxed(tmp_path, "forker:ForkerBrain", "processes=500")
    assert record["failure"] == "limit_exceeded" and "processes" in record["detail"], record


def test_tens_of_gigabytes_stop_at_the_memory_limit(tmp_path):
    record, _ = run_sandboxed(tmp_path, "hog:HogBrain", "gigabytes=40")
    assert record["failure"] == "limit_exceeded" and "memory" in record["detail"], record


def test_an_endless_act_stops_at_the_cpu_limit(tmp_path):
    # The brain timeout is longer than the CPU limit, so it is the sandbox that ends it.
    record, _ = run_sandboxed(tmp_path, "spinner:SpinnerBrain", extra=("--brain-timeout", "120"))
    assert record["failure"] == "limit_exceeded" and "cpu" in record["detail"], record


def test_a_brain_asleep_in_init_fails_at_its_start_timeout(tmp_path):
    record, _ = run_sandboxed(tmp_path, "sleeper:SleeperBrain")
    assert record["failure"] == "brain_start_timeout", record


def test_a_gigabyte_of_output_is_cut_at_the_output_limit(tmp_path):
    record, out = run_sandboxed(tmp_path, "shouter:ShouterBrain", "megabytes=1024")
    assert record["failure"] == "limit_exceeded" and "output" in record["detail"], record
    assert (out / "logs" / "brain-ShouterBrain.log").stat().st_size < 2 * 1048576


def test_publishing_on_the_simulators_and_scorers_keys_is_dropped_by_the_router(tmp_path):
    """The brain publishes END (laps completed) and far-away poses for episode 0 from frame 5 on: had any got
    through, the episode would end early or off the road."""
    record, out = run_sandboxed(
        tmp_path, "forger:ForgerBrain", "run_id=forged", extra=("--run-id", "forged", "--brain-timeout", "30")
    )
    assert record["reason"] == "time_limit" and record["metrics"]["steps"] == 40, record
    assert record["metrics"]["off_track_events"] == 0
    assert "forged 30" in (out / "logs" / "brain-ForgerBrain.log").read_text()  # it did try, every frame


def test_run_control_queries_for_the_conditions_get_no_answer(tmp_path):
    """The brain asks the simulator's run control for the episode's spec ("status") and to "stop" it, on frames 5
    to 7: the router drops both queries, so it learns nothing and the episode runs to its time limit."""
    record, out = run_sandboxed(
        tmp_path, "querier:QuerierBrain", "run_id=queried", extra=("--run-id", "queried", "--brain-timeout", "30")
    )
    assert record["reason"] == "time_limit" and record["metrics"]["steps"] == 40, record
    log = (out / "logs" / "brain-QuerierBrain.log").read_text()
    assert "run control status: no answer" in log and "run control stop: no answer" in log  # it did ask
    assert "run control status: answered" not in log and "run control stop: answered" not in log


def test_a_brain_can_make_no_user_namespace(tmp_path):
    """Inside a user namespace of its own a brain is root over what it makes there, which opens kernel code an
    unprivileged process never reaches. It tries on frame 5 by the system call and with ``unshare -U -r``: both are
    refused (the seccomp filter of orchestrator.stack.no_userns), and it drives on to its time limit."""
    record, out = run_sandboxed(tmp_path, "namespaces:NamespaceBrain")
    assert record["reason"] == "time_limit" and record["metrics"]["steps"] == 40, record
    log = (out / "logs" / "brain-NamespaceBrain.log").read_text()
    assert "unshare(CLONE_NEWUSER): refused, errno 1" in log, log[-2000:]
    assert "unshare -U -r: refused" in log and "Operation not permitted" in log, log[-2000:]
    assert "new user namespaces refused (seccomp)" in sandbox.limits_in_force(Sandbox.default(scratch_dir=tmp_path))


def test_a_brain_reads_its_camera_and_no_ground_truth_nor_the_conditions(tmp_path):
    """The brain subscribes to the simulator's poses, the scorer's live metrics (cross-track error: enough to steer
    blind), the brains' commands, the simulator's episode events and everything under the root, and asks the
    simulator's status for the episode's spec, on a stack whose frames it drives from: the router delivers it its
    camera and the brains' episode events only, and nothing it gets names the circuit (a challenge's hidden
    condition: a drawn circuit's name is its generator seed)."""
    record, out = run_sandboxed(
        tmp_path,
        "spy:SpyBrain",
        "run_id=spied",
        "secret=montreal",
        extra=("--run-id", "spied", "--brain-timeout", "30", "--circuit", "montreal"),
    )
    assert record["reason"] == "time_limit" and record["metrics"]["steps"] == 40, record
    log = (out / "logs" / "brain-SpyBrain.log").read_text()
    assert "spied: pose 0, live metrics 0, commands 0, events 0; status no answer" in log, log[-2000:]
    assert "spied brain events: 1" in log, log[-2000:]  # the START: its seed, and that is all
    assert "spied the secret: 0 time(s)" in log, log[-2000:]


def test_without_bubblewrap_run_sandbox_is_one_line_and_exit_2(tmp_path):
    empty = tmp_path / "bin"
    empty.mkdir()
    result = subprocess.run(
        [sys.executable, "-m", "orchestrator.cli", "run", "--sandbox", "--out", str(tmp_path / "run")],
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "PATH": str(empty)},
    )
    assert result.returncode == 2, result.stderr
    assert (
        result.stderr.strip().splitlines()[-1].startswith("drivebench: error: --sandbox: bubblewrap is not installed")
    )
    assert "Traceback" not in result.stderr


def test_a_sandboxed_brain_on_a_matrix_worker_gets_a_router_of_its_own(tmp_path):
    """A matrix's workers join one shared router; a stack with a sandboxed brain has its own instead (the router's
    access control is made for its brain), and its episode is scored."""
    from orchestrator.stack.launcher import BrainLaunch, LocalStack, free_loopback_port
    from protocol.bus import Bus, BusConfig
    from protocol.episode_spec import CameraSpec, EpisodeSpec

    shared = f"tcp/127.0.0.1:{free_loopback_port()}"
    launch = BrainLaunch("explicit", sandbox=Sandbox.default(scratch_dir=tmp_path / "scratch"))
    spec = EpisodeSpec(circuit="simple", max_sim_seconds=1.0, camera=CameraSpec(width_px=64, height_px=48))
    with (
        Bus(BusConfig(mode="router", listen=[shared]), name="matrix-router"),
        LocalStack(run_id="sandboxed", run_dir=tmp_path / "run", brains=[launch], router_endpoint=shared) as stack,
    ):
        assert stack.endpoint != shared
        score = stack.run_episode(spec)
    assert score.reason == "time_limit" and score.metrics.steps == 20


def test_a_warm_lane_gives_a_new_sandboxed_brain_a_new_stack(tmp_path):
    """A warm lane keeps its stack and swaps brain hosts; a sandboxed brain instead gets a fresh stack, since the
    router only lets the brains it started with publish commands."""
    from orchestrator.matrix.executor import WarmLane
    from orchestrator.stack.launcher import BrainLaunch, LocalStack

    lane = WarmLane(lane=0, stacks_dir=tmp_path / "stacks", make_stack=LocalStack, settings={})
    try:
        first = lane.stack_for([BrainLaunch("explicit", sandbox=Sandbox.default(scratch_dir=tmp_path / "a"))])
        second = lane.stack_for([BrainLaunch("constant", sandbox=Sandbox.default(scratch_dir=tmp_path / "b"))])
        assert second is not first and second.run_id != first.run_id
        assert [child.name for child in second.children if child.role == "brain"] == ["constant"]
        assert second.failure_now() is None
    finally:
        lane.close()
