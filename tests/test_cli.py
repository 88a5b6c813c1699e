"""End to end: the ``drivebench`` command as a user runs it."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from needs import require, require_gl
from support.waits import wait_for_file

pytestmark = pytest.mark.integration


def drivebench(*args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "orchestrator.cli", *args], capture_output=True, text=True, timeout=timeout
    )


def test_run_json_prints_one_json_object_and_writes_the_run_folder(tmp_path):
    out = tmp_path / "run"
    result = drivebench(
        "run",
        "--circuit",
        "simple",
        "--brain",
        "explicit",
        "--max-sim-seconds",
        "5",
        "--camera",
        "160x120",
        "--seed",
        "4",
        "--json",
        "--out",
        str(out),
        "--run-id",
        "0042",
    )  # digits only: must stay a string in every process
    assert result.returncode == 0, result.stderr
    score = json.loads(result.stdout)  # stdout is exactly one JSON object
    assert result.stdout.count("\n") == 1
    assert score["reason"] == "time_limit"
    assert score["spec"]["seed"] == 4 and score["spec"]["camera"]["width_px"] == 160
    assert score["metrics"]["steps"] == 100
    assert score["header"]["run_id"] == "0042"
    assert json.loads((out / "score.json").read_text()) == score
    assert "circuit: simple" in (out / "config.yaml").read_text()
    logs = {path.name for path in (out / "logs").iterdir()}
    assert logs == {"simulator.log", "noise.log", "scorer.log", "brain-explicit.log"}
    assert "resolved config" in (out / "logs" / "simulator.log").read_text()


def test_run_prints_a_metrics_table(tmp_path):
    result = drivebench(
        "run", "--max-sim-seconds", "3", "--camera", "100x50", "--start-m", "50", "--out", str(tmp_path / "r")
    )
    assert result.returncode == 0, result.stderr
    assert "ended by" in result.stdout and "time_limit" in result.stdout
    assert "BM position deviation" in result.stdout
    # No lap in 3 s: said in words, not as a bare "- s"
    assert re.search(r"^lap times \(arc length\) +no lap completed$", result.stdout, re.MULTILINE), result.stdout
    # The run's first line says where the car starts and which look the world has, as the table's episode row does
    first = result.stderr.splitlines()[0]
    assert "explicit on simple from 50 m along, look flat, 1 lap(s), seed 0" in first, first
    assert "explicit on simple from 50 m along, look flat, 1 lap(s), seed 0" in result.stdout


@pytest.mark.parametrize(
    "args, message",
    [
        (["--circuit", "atlantis"], "unknown circuit 'atlantis' (known: "),
        (["--brain", "hal"], "unknown brain 'hal' (known: "),
        (["--laps", "0"], "laps must be >= 1"),
    ],
)
def test_user_mistakes_give_one_line_and_exit_2(tmp_path, args, message):
    result = drivebench("run", "--out", str(tmp_path / "r"), *args, timeout=30)
    assert result.returncode == 2
    assert message in result.stderr
    assert "Traceback" not in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1


def test_a_run_started_along_the_circuit_laps_it_from_there_and_its_config_runs_it_again(tmp_path):
    from circuits import load_circuit
    from protocol.messages import Pose
    from recorder.reading import read_messages

    require_gl()  # ~5 s a lap of simple (TinyRenderer: ~30 s)
    recording = tmp_path / "first.mcap"
    argv = ["--renderer", "gl", "--start-m", "40", "--laps", "1", "--json", "--out", str(tmp_path / "first")]
    first = drivebench("run", *argv, "--record", str(recording), "--record-images", "jpeg")
    assert first.returncode == 0, first.stderr
    score = json.loads(first.stdout)
    assert score["spec"]["start_m"] == 40.0 and score["reason"] == "laps_completed"
    circuit = load_circuit("simple")
    start = next(r.message for r in read_messages(recording) if isinstance(r.message, Pose))
    assert (start.header.seq, start.x_m, start.y_m, start.yaw_rad) == (0, *circuit.centreline.pose_at(40.0))
    m = score["metrics"]
    assert m["completed_laps"] == 1 and len(m["lap_times_s"]) == 1
    # A lap is the circuit's length from where the car started: the run ends just past it.
    assert circuit.length_m <= m["progress_m"] < circuit.length_m + 1.0 and m["percentage_completed"] > 100.0
    config = tmp_path / "first" / "config.yaml"
    again = drivebench("run", "--config", str(config), "--json", "--out", str(tmp_path / "again"))
    assert again.returncode == 0, again.stderr
    rerun = json.loads(again.stdout)
    assert rerun["spec"]["start_m"] == 40.0 and rerun["metrics"]["progress_m"] == m["progress_m"]
    config.write_text(config.read_text().replace("start_m: 40.0", "start_m: 500.0"))
    line = config.read_text().splitlines().index("  start_m: 500.0") + 1  # the mistake's own line
    refused = drivebench("run", "--config", str(config), "--out", str(tmp_path / "refused"), timeout=30)
    assert refused.returncode == 2 and refused.stderr == (
        f"drivebench: error: --config {config}:{line}: start_m must be >= 0 and below 442.836 m, the length of "
        "circuit 'simple', got 500\n"
    )


@pytest.mark.parametrize(
    "args, message",
    [
        (["--start-m", "-1"], "--start-m -1.0: start_m must be >= 0, got -1.0"),
        (["--start-m", "442.9"], "--start-m 442.9: start_m must be >= 0 and below 442.836 m, the length of circuit"),
        (["--direction", "reverse", "--variation", "start_m=500"], "--variation start_m: start_m must be >= 0 and"),
    ],
    ids=["negative", "past-the-length", "variation"],
)
def test_a_start_off_the_circuit_is_one_line_and_exit_2_before_anything_starts(tmp_path, args, message):
    result = drivebench("run", "--out", str(tmp_path / "r"), *args, timeout=30)
    assert result.returncode == 2 and result.stderr.startswith(f"drivebench: error: {message}"), result.stderr
    assert len(result.stderr.strip().splitlines()) == 1 and not (tmp_path / "r").exists()


def test_bad_camera_size_is_a_usage_error(tmp_path):
    result = drivebench("run", "--camera", "big", timeout=30)
    assert result.returncode == 2 and "camera size must look like 320x240" in result.stderr


def test_bad_brain_option_is_refused_before_anything_starts(tmp_path):
    result = drivebench(
        "run", "--brain", "constant", "--brain-option", "warp=9", "--out", str(tmp_path / "r"), timeout=90
    )
    assert result.returncode == 2  # a usage mistake, found before the stack starts: no run folder
    assert "bad options for brain 'constant'" in result.stderr and "warp" in result.stderr
    assert "Traceback" not in result.stderr and not (tmp_path / "r").exists()


@pytest.mark.parametrize(
    "args, expected",
    [
        (["--brain", "explicit", "--weights", "{good}"], "brain 'explicit' takes no weights"),
        (["--brain", "pilotnet", "--weights", "{good}"], "holds a memdccp network, not pilotnet"),
        (["--brain", "memdccp", "--weights", "{random}"], "not a torch checkpoint"),
        (["--brain", "memdccp", "--weights", "{pickle}"], "not a torch checkpoint of tensors"),
        (["--shadow", "memdccp={random}"], "not a torch checkpoint"),
    ],
    ids=["no-weights-brain", "wrong-network", "random-bytes", "pickled-object", "shadow"],
)
def test_bad_weights_are_refused_before_anything_starts(tmp_path, args, expected):
    require("torch")
    import torch

    (tmp_path / "random.ckpt").write_bytes(bytes(range(256)) * 8)
    torch.save({"model": print}, tmp_path / "pickle.ckpt")  # loading it would need unpickling a function
    paths = {
        "good": str(Path(__file__).resolve().parent.parent / "brains" / "weights" / "memdccp.ckpt"),
        "random": str(tmp_path / "random.ckpt"),
        "pickle": str(tmp_path / "pickle.ckpt"),
    }
    result = drivebench("run", *[arg.format(**paths) for arg in args], "--out", str(tmp_path / "r"), timeout=60)
    assert result.returncode == 2 and expected in result.stderr, result.stderr
    assert len(result.stderr.strip().splitlines()) == 1 and "Traceback" not in result.stderr
    assert "weights_only" not in result.stderr and "arbitrary code" not in result.stderr  # no unsafe advice
    # Refused before anything starts: no run folder (its wall time is the machine's, 31-33 s seen at load 11)
    assert not (tmp_path / "r").exists()


@pytest.mark.parametrize("signal_number", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_interrupting_a_run_stops_every_process(tmp_path, signal_number):
    out = tmp_path / "run"
    # Real time: the lap lasts its wall time, so the signal lands mid-episode however fast the machine drives.
    run = subprocess.Popen(
        [sys.executable, "-m", "orchestrator.cli", "run", "--realtime", "--out", str(out)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    wait_for_file(
        out / "logs" / "simulator.log",
        containing="episode 0 started",
        timeout_s=60,
        alive=lambda: None if run.poll() is None else f"exited with {run.returncode}",
    )
    children = _child_pids(run.pid)
    assert len(children) == 4  # simulator, noise injector, scorer, brain
    run.send_signal(signal_number)
    _, stderr = run.communicate(timeout=30)
    assert run.returncode == 128 + signal_number
    assert "every process stopped" in stderr and "Traceback" not in stderr
    for pid in children:
        assert not _alive(pid), f"child {pid} outlived the launcher"


def _child_pids(parent: int) -> list[int]:
    found = []
    for status in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = status.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == parent:
            found.append(int(status.parent.name))
    return found


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def test_a_failed_run_leaves_a_failure_record_and_prints_it_with_json(tmp_path):
    """A hard failure (the scorer killed) is typed, in failure.json and on stdout with --json: not only prose."""
    out = tmp_path / "run"
    run = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "orchestrator.cli",
            "run",
            "--brain",
            "constant",
            "--brain-option",
            "speed_mps=0",
            "--max-sim-seconds",
            "600",
            "--realtime",  # 600 s of wall time, whatever the machine's speed: the kill lands mid-episode
            "--camera",
            "64x48",
            "--run-id",
            "failjson",
            "--json",
            "--out",
            str(out),
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        wait_for_file(
            out / "logs" / "simulator.log",
            containing="episode 0 started",
            timeout_s=60,
            alive=lambda: None if run.poll() is None else f"exited with {run.returncode}",
        )
        scorer = subprocess.run(["pgrep", "-f", "services.scorer.*failjson"], capture_output=True, text=True)
        os.kill(int(scorer.stdout.split()[0]), signal.SIGKILL)
        stdout, stderr = run.communicate(timeout=30)
    finally:
        run.kill()
    assert run.returncode == 1 and "(scorer_died)" in stderr and "killed by SIGKILL" in stderr
    record = json.loads(stdout)
    assert record["failure"] == "scorer_died" and record["run_id"] == "failjson"
    assert json.loads((out / "failure.json").read_text()) == record
