"""The privileged expert (pure pursuit on ground truth), the brain host feeding it poses, and randomised collection."""

from __future__ import annotations

import argparse
import math

import numpy as np
import pytest

from brains.base import GroundTruth, Observation
from brains.registry import make_brain
from circuits import load_circuit
from orchestrator.collect import CollectError, collection_specs
from orchestrator.stack.launcher import BrainLaunch
from protocol.episode_spec import CameraSpec, EpisodeSpec
from protocol.messages import EndReason
from protocol.variations import apply_variation

BLANK = np.zeros((8, 8, 3), np.uint8)


def observe(truth: GroundTruth | None, seq: int = 0) -> Observation:
    return Observation(image_rgb=BLANK, stamp_ns=seq * 50_000_000, seq=seq, ground_truth=truth)


def truth_at(circuit: str, s_m: float, *, lateral_m: float = 0.0, direction: str = "forward") -> GroundTruth:
    centreline = load_circuit(circuit, direction=direction).centreline
    x, y, heading = centreline.pose_at(s_m)
    return GroundTruth(
        x_m=x - lateral_m * math.sin(heading),
        y_m=y + lateral_m * math.cos(heading),
        yaw_rad=heading,
        circuit=circuit,
        direction=direction,
    )


def test_it_steers_back_to_the_centre_line_from_either_side():
    expert = make_brain("expert")
    assert expert.needs_ground_truth
    left = expert.act(observe(truth_at("simple", 5.0, lateral_m=0.5)))
    expert.reset(seed=0)
    right = expert.act(observe(truth_at("simple", 5.0, lateral_m=-0.5)))
    assert left.yaw_rate_radps < -0.1 < 0.1 < right.yaw_rate_radps


@pytest.mark.slow  # over 9 s: out of the quick tier
def test_it_slows_down_before_a_tight_curve_and_speeds_up_on_a_straight():
    centreline = load_circuit("montmelo").centreline
    expert = make_brain("expert")
    speeds = []
    for seq in range(int(centreline.length_m / 0.4)):  # a whole lap on the line, 0.4 m a frame
        speeds.append(expert.act(observe(truth_at("montmelo", seq * 0.4), seq)).speed_mps)
    assert min(speeds) < 7.0 and max(speeds) > 11.0
    assert max(abs(np.diff(speeds))) <= 2 * 4.0 * 0.05 + 1e-9  # never faster than its acceleration limit


def test_without_ground_truth_it_holds_its_speed_and_steers_straight():
    action = make_brain("expert").act(observe(None))
    assert action.yaw_rate_radps == 0.0 and action.speed_mps > 0


def test_the_noisy_driver_passes_the_privilege_on():
    assert make_brain("noisy", base="expert").needs_ground_truth
    assert not make_brain("noisy", base="explicit").needs_ground_truth


def test_randomised_collection_draws_every_world_from_the_seed():
    args = argparse.Namespace(
        circuits=",".join(f"random:{i}" for i in range(12)),
        direction="both",
        laps=1,
        max_sim_seconds=100.0,
        camera=(320, 240),
        recovery_noise=0.0,
        brain="expert",
        variation=[],
        randomise=True,
    )
    specs = collection_specs(args)
    again = collection_specs(args)
    assert specs == again and len(specs) == 24
    assert {s.direction for s in specs} == {"forward", "reverse"}
    assert {s.world.line for s in specs} == {"red", "white", "none"}
    assert {s.world.walls for s in specs} == {True, False}
    assert len({s.camera.lateral_offset_m for s in specs}) > 20  # drawn per episode (rounded to mm)
    assert all(abs(s.camera.lateral_offset_m) <= 0.08 and -0.03 <= s.camera.pitch_down_rad <= 0.22 for s in specs)
    assert 4 <= sum(bool(s.noise) for s in specs) <= 20
    # --variation pins what it names and leaves the rest drawn: more data of one hard world.
    pinned = collection_specs(argparse.Namespace(**{**vars(args), "variation": ["line=none,walls=off"]}))
    assert {(s.world.line, s.world.walls) for s in pinned} == {("none", False)}
    assert [(s.camera, s.noise, s.world.road) for s in pinned] == [(s.camera, s.noise, s.world.road) for s in specs]
    # A start along the circuit is checked against each circuit's length before anything is collected.
    simple = argparse.Namespace(**{**vars(args), "circuits": "simple", "variation": ["start_m=100"]})
    assert {s.start_m for s in collection_specs(simple)} == {100.0}
    off = argparse.Namespace(**{**vars(simple), "variation": ["start_m=500"]})
    with pytest.raises(CollectError, match=r"start_m must be >= 0 and below 442.836 m, the length of circuit 'simple'"):
        collection_specs(off)


@pytest.mark.slow
def test_the_expert_laps_a_world_without_line_or_walls_in_reverse(make_stack):
    stack = make_stack(BrainLaunch("expert"))
    spec = EpisodeSpec(
        circuit="simple",
        laps=1,
        direction="reverse",
        camera=CameraSpec(width_px=160, height_px=120),
        active_brain="expert",
    )
    score = stack.run_episode(apply_variation(spec, "line=none,walls=off,camera=left"))
    assert score.reason == EndReason.LAPS_COMPLETED, score
    assert score.metrics.cross_track_mean_m < 0.05 and score.metrics.off_track_events == 0
