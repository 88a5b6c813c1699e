"""The RL pieces without a bus: the line features on real renders, the reward against hand-computed values, the
policy brain's file checks."""

from __future__ import annotations

import numpy as np
import pytest

from brains.lane_policy.brain import LanePolicyBrain, PolicyFileError
from brains.lane_policy.features import FEATURES, line_features, scaled
from brains.registry import BrainOptionsError, preflight
from circuits import load_circuit
from drivebench.rl.reward import ProgressReward
from protocol.episode_spec import CameraSpec
from services.simulator.car import CarState
from services.simulator.scene import Scene


def test_the_features_say_on_which_side_the_line_is():
    circuit = load_circuit("simple")
    x_m, y_m, yaw_rad = circuit.start_pose()  # heading along the top straight, +x; y is to the left
    left_normal = np.array([-np.sin(yaw_rad), np.cos(yaw_rad)])
    with Scene(circuit) as scene:
        features = {
            offset_m: line_features(
                scene.render(CarState(*(np.array([x_m, y_m]) + offset_m * left_normal), yaw_rad), CameraSpec()),
                previous_action=np.array([0.25, -0.5]),
            )
            for offset_m in (-0.5, 0.0, 0.5)
        }
    assert all(f.shape == (FEATURES,) and f.dtype == np.float32 for f in features.values())
    assert np.all(features[0.5][:4] < -0.05) and np.all(features[-0.5][:4] > 0.05)  # car left: line to the right
    assert np.all(np.abs(features[0.0][:4]) < 0.05) and np.all(features[0.0][4:8] == 1.0)
    assert list(features[0.0][8:]) == [0.25, -0.5]
    blank = line_features(np.zeros((240, 320, 3), np.uint8), previous_action=np.zeros(2))
    assert not blank[:8].any()  # no line: bearings 0, seen flags 0


def test_the_reward_is_progress_times_centring_minus_smoothness_and_crash():
    circuit = load_circuit("simple")
    reward = ProgressReward(circuit, smoothness=0.1, crash_penalty=10.0)
    centreline = circuit.centreline
    x_m, y_m, yaw_rad = centreline.pose_at(1.0)
    still = np.zeros(2)
    on_line = reward.step(x_m=x_m, y_m=y_m, action=still, previous_action=still, crashed=False)
    assert on_line.progress_m == pytest.approx(1.0, abs=1e-6) and on_line.reward == pytest.approx(1.0, abs=1e-6)
    x_m, y_m, yaw_rad = centreline.pose_at(2.0)
    half_m = circuit.road_half_width_m / 2  # halfway to the edge: half the progress counts
    x_m, y_m = x_m - half_m * np.sin(yaw_rad), y_m + half_m * np.cos(yaw_rad)
    jerky = reward.step(x_m=x_m, y_m=y_m, action=np.array([1.0, -1.0]), previous_action=still, crashed=True)
    assert jerky.lateral_m == pytest.approx(half_m, abs=1e-3)
    assert jerky.smoothness_penalty == pytest.approx(0.1 * 2.0) and jerky.crash_penalty == 10.0
    assert jerky.reward == pytest.approx(jerky.progress_m * 0.5 - 0.2 - 10.0, abs=1e-3)
    assert reward.progress_m == pytest.approx(on_line.progress_m + jerky.progress_m)


def test_a_bad_policy_file_is_one_line_before_anything_starts(tmp_path):
    with pytest.raises(BrainOptionsError, match="nothing.npz is not a policy file"):
        preflight("lane_policy", {"weights": str(tmp_path / "nothing.npz")})
    other = tmp_path / "other.npz"
    np.savez(other, meta=np.array('{"layers": 1}'), w0=np.zeros((2, 3)), b0=np.zeros(2))
    with pytest.raises(PolicyFileError, match="maps 3 features to 2 actions, expected 10 -> 2"):
        LanePolicyBrain(weights=str(other))


def test_actions_map_linearly_onto_the_ranges():
    assert scaled(-1.0, 2.0, 8.0) == 2.0 and scaled(1.0, 2.0, 8.0) == 8.0 and scaled(0.0, -2.0, 2.0) == 0.0
    assert scaled(0.5, 0.0, 4.0) == 3.0 and scaled(0.5, -0.25, 0.25) == 0.125  # exact: the trajectory test uses them
