"""An ONNX file written by ``drivebench export`` drives on every route that takes weights: run, shadow, matrix (brain
and shadow), swap and brains check (real CLI, real processes, real onnxruntime)."""

from __future__ import annotations

import json
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pytest
from needs import require
from support.stacks import stop_episode

require("torch")  # to export the shipped checkpoint
require("onnxruntime")
pytestmark = pytest.mark.integration

ROOT = Path(__file__).resolve().parents[1]
CHECKPOINT = ROOT / "brains" / "weights" / "deepest_lstm_tiny_pilotnet.ckpt"
BRAIN = "deepest_lstm_tiny_pilotnet"


def drivebench(*args: str, timeout: float = 180, **options) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "orchestrator.cli", *args], capture_output=True, text=True, timeout=timeout, **options
    )


@pytest.fixture(scope="module")
def onnx_file(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("onnx") / "tiny.onnx"
    exported = drivebench("export", str(CHECKPOINT), "-o", str(path), timeout=300)
    assert exported.returncode == 0, exported.stderr
    return path


def test_run_drives_an_exported_onnx_file_and_shadows_one(onnx_file, tmp_path):
    result = drivebench(
        "run",
        *("--brain", BRAIN, "--weights", str(onnx_file)),
        *("--shadow", f"{BRAIN}={onnx_file}"),
        *("--max-sim-seconds", "2", "--camera", "96x72", "--out", str(tmp_path / "run"), "--json"),
    )
    assert result.returncode == 0, result.stderr
    score = json.loads(result.stdout)
    assert score["brain"] == BRAIN and score["reason"] == "time_limit"
    assert score["metrics"]["progress_m"] > 0.5  # the network drove the car
    [shadow] = score["shadows"]
    assert shadow["frames"] >= 1  # it loaded the file and answered (it may miss the first frames of 2 s)
    assert shadow["speed_mae_mps"] < 1e-6  # the same network on the same frames


def test_a_matrix_drives_and_shadows_an_exported_onnx_file(onnx_file, tmp_path):
    matrix = tmp_path / "m.yaml"
    matrix.write_text(
        f"name: onnx\nbrains: [{{name: {BRAIN}, weights: {onnx_file}, label: net}}]\n"
        f"shadows: [{{name: neural, weights: {onnx_file}, label: twin}}]\n"
        "circuits: [simple]\nlimits: {max_sim_seconds: 2}\ncamera: 96x72\n"
    )
    out = tmp_path / "out"
    result = drivebench("matrix", str(matrix), "-o", str(out), "--no-report")
    assert result.returncode == 0, result.stderr
    with sqlite3.connect(out / "results.sqlite") as db:
        [(status, score_json)] = db.execute("SELECT status, score_json FROM episodes").fetchall()
    score = json.loads(score_json)
    assert status == "done" and score["brain"] == "net"
    # A shadow that answered at all has loaded the file (a shadow may miss the first frames of a short episode).
    assert [shadow["brain"] for shadow in score["shadows"]] == ["twin"] and score["shadows"][0]["frames"] >= 1


def test_swap_makes_an_exported_onnx_file_drive(onnx_file, tmp_path):
    out = tmp_path / "run"
    # Real time: the episode lasts its wall time (3000 s), so the swap lands in it however fast the machine.
    run = subprocess.Popen(
        [sys.executable, "-m", "orchestrator.cli", "run", "--realtime", "--max-sim-seconds", "3000", "--laps", "50"]
        + ["--camera", "96x72", "--out", str(out), "--json"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        deadline = time.monotonic() + 90
        while not ((out / "stack.json").is_file() and "started" in _read(out / "logs" / "simulator.log")):
            assert time.monotonic() < deadline, "the run did not start its episode"
            assert run.poll() is None, run.communicate()[1]
            time.sleep(0.2)
        swapped = drivebench("swap", BRAIN, "--weights", str(onnx_file), "--runs-dir", str(tmp_path), timeout=120)
        assert swapped.returncode == 0, swapped.stderr
        assert BRAIN in swapped.stdout
        stack = json.loads((out / "stack.json").read_text())
        stop_episode(stack["router"], stack["run_id"])  # the episode is long: it cannot end before the swap
        stdout, stderr = run.communicate(timeout=120)
    finally:
        if run.poll() is None:
            run.kill()
    assert run.returncode == 0, stderr
    score = json.loads(stdout)
    assert score["brain"] == BRAIN, stderr
    assert [(s["from_brain"], s["to_brain"]) for s in score["switches"]] == [("explicit", BRAIN)]


def test_brains_check_takes_an_exported_onnx_file(onnx_file):
    result = drivebench("brains", "check", BRAIN, "--weights", str(onnx_file), "--memory-steps", "20")
    assert result.returncode == 0, result.stdout + result.stderr
    assert "meets the brain contract" in result.stderr and "FAIL" not in result.stdout


@pytest.mark.parametrize(
    ("args", "expected"),
    [
        (["--brain", "pilotnet"], f"holds a {BRAIN} network, not pilotnet"),
        (["--brain", BRAIN, "--brain-option", "backend=torch"], "serves with backend 'onnx' only"),
        (["--brain", "explicit", "--shadow", "pilotnet={onnx}"], f"holds a {BRAIN} network, not pilotnet"),
    ],
    ids=["wrong-network", "torch-backend", "wrong-network-shadow"],
)
def test_a_mistaken_onnx_file_is_refused_in_one_line_before_anything_starts(onnx_file, tmp_path, args, expected):
    weights = [] if "--shadow" in args else ["--weights", str(onnx_file)]
    command = [arg.format(onnx=onnx_file) for arg in args]
    result = drivebench("run", *command, *weights, "--out", str(tmp_path / "r"), timeout=60)
    assert result.returncode == 2 and expected in result.stderr, result.stderr
    assert len(result.stderr.strip().splitlines()) == 1 and "Traceback" not in result.stderr
    assert not (tmp_path / "r").exists()


def _read(path: Path) -> str:
    try:
        return path.read_text()
    except OSError:
        return ""
