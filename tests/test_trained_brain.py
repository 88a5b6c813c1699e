"""The shipped, trained DeepestLSTMTinyPilotNet drives the held-out circuit over the real stack."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest
from needs import require

from brains.base import Observation
from brains.registry import make_brain
from orchestrator.stack.launcher import BrainLaunch
from protocol.episode_spec import EpisodeSpec
from protocol.messages import EndReason
from protocol.variations import apply_variation

require("torch")
require("onnxruntime")
pytestmark = pytest.mark.integration

ROOT = Path(__file__).resolve().parents[1]
WEIGHTS = ROOT / "brains" / "weights" / "deepest_lstm_tiny_pilotnet.ckpt"


@pytest.mark.slow
def test_the_trained_tiny_network_follows_the_line_of_a_circuit_it_never_saw(make_stack):
    weights = f"weights={json.dumps(str(WEIGHTS))}"
    stack = make_stack(BrainLaunch("deepest_lstm_tiny_pilotnet", options=(weights,)))
    score = stack.run_episode(
        EpisodeSpec(circuit="simple", max_sim_seconds=25.0, active_brain="deepest_lstm_tiny_pilotnet")
    )
    metrics = score.metrics
    assert score.reason == EndReason.TIME_LIMIT  # 500 steps without leaving the road or touching a wall
    assert metrics.steps == 500 and metrics.off_track_events == 0
    assert metrics.progress_m > 150.0  # about a third of the lap, curves included
    assert metrics.cross_track_max_m < 0.5


def test_export_of_the_trained_network_matches_torch(tmp_path):
    result = subprocess.run(
        [sys.executable, "-m", "orchestrator.cli", "export", str(WEIGHTS), "-o", str(tmp_path / "tiny.onnx")],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=ROOT,
    )
    assert result.returncode == 0, result.stderr
    assert (tmp_path / "tiny.onnx").stat().st_size > 100_000
    difference = float((result.stdout + result.stderr).split("=")[-1].split()[0])
    assert difference < 1e-4


SHIPPED = sorted(path for path in (ROOT / "brains" / "weights").glob("*.ckpt"))


def test_drivebench_ships_every_network_of_the_paper_and_the_randomised_one():
    assert {path.stem for path in SHIPPED} >= {
        "pilotnet",
        "deepest_lstm_tiny_pilotnet",
        "pilotnet_x3",
        "memdccp",
        "deepest_lstm_tiny_pilotnet_dr",
        "recurrent_tiny_pilotnet_dr",
    }
    for path in (ROOT / "brains" / "weights").iterdir():
        assert path.stat().st_size < 10 * 2**20, f"{path.name}: git files stay under 10 MB"


@pytest.mark.parametrize("path", SHIPPED, ids=lambda path: path.stem)
def test_every_shipped_checkpoint_loads_and_answers_a_real_frame(path, road_frame):
    brain = make_brain("neural", weights=str(path))
    brain.reset(seed=0)
    actions = [brain.act(Observation(image_rgb=road_frame, stamp_ns=seq * 50_000_000, seq=seq)) for seq in range(12)]
    for action in actions:
        assert math.isfinite(action.speed_mps) and math.isfinite(action.yaw_rate_radps)
        assert 2.0 < action.speed_mps < 25.0 and abs(action.yaw_rate_radps) < 1.5  # a straight road ahead


@pytest.mark.slow
def test_the_shipped_memdccp_laps_simple_with_no_line(make_stack):
    """The paper's memory network, trained on the red line only, drives the held-out circuit with the line gone."""
    weights = f"weights={json.dumps(str(ROOT / 'brains' / 'weights' / 'memdccp.ckpt'))}"
    stack = make_stack(BrainLaunch("memdccp", options=(weights,)))
    spec = apply_variation(EpisodeSpec(circuit="simple", max_sim_seconds=120.0, active_brain="memdccp"), "line=none")
    score = stack.run_episode(spec)
    assert score.reason == EndReason.LAPS_COMPLETED, score
    assert score.metrics.off_track_events == 0 and score.metrics.cross_track_max_m < 0.5


def lap_of_simple(make_stack, *, brain: str, weights_file: str, variation: str):
    """The score of one lap of simple in ``variation`` by ``brain`` serving the shipped ``weights_file``."""
    weights = f"weights={json.dumps(str(ROOT / 'brains' / 'weights' / weights_file))}"
    stack = make_stack(BrainLaunch(brain, name="shipped", options=(weights,)))
    spec = EpisodeSpec(circuit="simple", max_sim_seconds=120.0, active_brain="shipped")
    return stack.run_episode(apply_variation(spec, variation))


@pytest.mark.slow
@pytest.mark.parametrize(
    "brain, weights_file, variation",
    [
        # Trained on random circuits in random worlds, it laps a world no paper-recipe network laps.
        ("deepest_lstm_tiny_pilotnet", "deepest_lstm_tiny_pilotnet_dr.ckpt", "line=none,road=white"),
        # The world the paper's memDCCP fails: only the road's edge against the grass, a few pixels at the horizon.
        ("recurrent_tiny_pilotnet", "recurrent_tiny_pilotnet_dr.ckpt", "line=none,walls=off"),
    ],
    ids=["tiny_dr-no-line-white-road", "rtiny_dr-no-line-no-walls"],
)
def test_the_randomised_networks_lap_worlds_the_paper_recipe_fails(make_stack, brain, weights_file, variation):
    score = lap_of_simple(make_stack, brain=brain, weights_file=weights_file, variation=variation)
    assert score.reason == EndReason.LAPS_COMPLETED, score
    assert score.metrics.off_track_events == 0
