"""The shipped, trained DeepestLSTMTinyPilotNet drives the held-out circuit over the real stack."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from orchestrator.launcher import BrainLaunch
from protocol.messages import EndReason, EpisodeSpec

pytest.importorskip("torch")
pytest.importorskip("onnxruntime")
pytestmark = pytest.mark.integration

ROOT = Path(__file__).resolve().parents[1]
WEIGHTS = ROOT / "brains" / "weights" / "deepest_lstm_tiny_pilotnet.ckpt"


@pytest.mark.slow
def test_the_trained_tiny_network_follows_the_line_of_a_circuit_it_never_saw(make_stack):
    weights = f"weights={json.dumps(str(WEIGHTS))}"
    stack = make_stack(BrainLaunch("deepest_lstm_tiny_pilotnet", options=(weights,)))
    score = stack.run_episode(EpisodeSpec(circuit="simple", max_sim_seconds=25.0,
                                          active_brain="deepest_lstm_tiny_pilotnet"))
    metrics = score.metrics
    assert score.reason == EndReason.TIME_LIMIT  # 500 steps without leaving the road or touching a wall
    assert metrics.steps == 500 and metrics.off_track_events == 0
    assert metrics.progress_m > 150.0  # about a third of the lap, curves included
    assert metrics.cross_track_max_m < 0.5


def test_export_of_the_trained_network_matches_torch(tmp_path):
    result = subprocess.run([sys.executable, "-m", "orchestrator.cli", "export", str(WEIGHTS), "-o",
                             str(tmp_path / "tiny.onnx")], capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert result.returncode == 0, result.stderr
    assert (tmp_path / "tiny.onnx").stat().st_size > 100_000
    difference = float((result.stdout + result.stderr).split("=")[-1].split()[0])
    assert difference < 1e-4
