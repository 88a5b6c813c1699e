"""The explicit brain on frames rendered by the real scene: it steers towards the red line at any camera size."""

from __future__ import annotations

import math

import numpy as np
import pytest

from brains.base import Action, Brain, Observation
from brains.explicit.brain import ExplicitBrain
from brains.registry import make_brain
from circuits import Centreline, Circuit, load_circuit
from protocol.episode_spec import CameraSpec
from services.simulator.car import CarState
from services.simulator.scene import Scene

SIZES = [(320, 240), (640, 480), (200, 66)]


def stadium(straight_m: float = 120.0, radius_m: float = 30.0, step_m: float = 0.25) -> Circuit:
    """An anticlockwise stadium: a straight along +x from the origin, a half circle, a straight back, a half circle."""
    points = []
    for x in np.arange(0.0, straight_m, step_m):
        points.append((x, 0.0))
    for a in np.arange(0.0, math.pi, step_m / radius_m):
        points.append((straight_m + radius_m * math.sin(a), radius_m - radius_m * math.cos(a)))
    for x in np.arange(straight_m, 0.0, -step_m):
        points.append((x, 2 * radius_m))
    for a in np.arange(0.0, math.pi, step_m / radius_m):
        points.append((-radius_m * math.sin(a), radius_m + radius_m * math.cos(a)))
    return Circuit(
        name="stadium",
        description="test stadium",
        source="tests",
        centreline=Centreline(np.array(points)),
        road_half_width_m=1.5,
        line_width_m=0.10,
        wall_height_m=0.5,
    )


@pytest.fixture(scope="module")
def straight_scene():
    with Scene(stadium()) as scene:
        yield scene


def on_straight(lateral_m: float = 0.0) -> CarState:
    """Halfway down the stadium's first straight (heading +x), lateral_m to the left of the line."""
    return CarState(x_m=60.0, y_m=lateral_m, yaw_rad=0.0)


def act(brain: ExplicitBrain, image: np.ndarray, seq: int = 0) -> Action:
    return brain.act(Observation(image_rgb=image, stamp_ns=seq * 50_000_000, seq=seq))


def test_it_is_a_registered_brain():
    brain = make_brain("explicit")
    assert isinstance(brain, ExplicitBrain) and isinstance(brain, Brain)


@pytest.mark.parametrize("size", SIZES)
def test_on_the_line_of_a_straight_it_drives_straight_and_speeds_up(straight_scene, size):
    camera = CameraSpec(width_px=size[0], height_px=size[1])
    brain = ExplicitBrain()
    image = straight_scene.render(on_straight(), camera)
    speeds = []
    for seq in range(20):
        action = act(brain, image, seq)
        assert abs(action.yaw_rate_radps) < 0.02
        speeds.append(action.speed_mps)
    assert not brain.in_curve
    assert brain.last_line.points[0][0] == pytest.approx(320, abs=3)  # the line's far end is dead ahead
    # Straight mode with the sky ahead: v_mult 2 rises by 0.3 a frame up to 6, v = 4 v_mult.
    assert speeds[0] == pytest.approx(9.2)
    assert speeds == sorted(speeds) and speeds[-1] == pytest.approx(24.0)


@pytest.mark.parametrize("size", SIZES)
@pytest.mark.parametrize(("lateral_m", "turns_left"), [(-0.3, True), (0.3, False), (-0.15, True), (0.15, False)])
def test_it_steers_back_towards_the_line(straight_scene, size, lateral_m, turns_left):
    # A car to the right of the line (negative lateral) sees it on its left and must turn left: w > 0.
    camera = CameraSpec(width_px=size[0], height_px=size[1])
    brain = ExplicitBrain()
    image = straight_scene.render(on_straight(lateral_m), camera)
    for seq in range(3):
        action = act(brain, image, seq)
        assert (action.yaw_rate_radps > 0) == turns_left
        assert abs(action.yaw_rate_radps) > 0.005


@pytest.mark.parametrize("size", SIZES)
def test_it_sees_the_bends_of_the_simple_circuit(size):
    circuit = load_circuit("simple")
    camera = CameraSpec(width_px=size[0], height_px=size[1])
    with Scene(circuit) as scene:
        for s_m, right_turn in ((85.0, True), (125.0, False), (310.0, True)):
            brain = ExplicitBrain()
            image = scene.render(CarState(*circuit.centreline.pose_at(s_m)), camera)
            for seq in range(3):
                action = act(brain, image, seq)
            assert brain.in_curve
            assert action.speed_mps == 7.0
            assert (action.yaw_rate_radps < 0) == right_turn


def test_a_lost_line_steers_left_as_in_the_original():
    brain = ExplicitBrain()
    grey = np.full((240, 320, 3), 90, dtype=np.uint8)
    action = act(brain, grey)
    assert not brain.last_line.found
    assert action.yaw_rate_radps > 0  # e = 320 - 0
    # Behavior Metrics feeds a 3 x 3 black image before the first camera frame: no crash.
    act(ExplicitBrain(), np.zeros((3, 3, 3), dtype=np.uint8))


def test_reset_clears_all_state(straight_scene):
    camera = CameraSpec(width_px=320, height_px=240)
    frames = [straight_scene.render(on_straight(lateral), camera) for lateral in (0.0, -0.4, 0.2, 0.0, 0.0)]

    def drive(brain: ExplicitBrain) -> list[Action]:
        return [act(brain, frame, seq) for seq, frame in enumerate(frames)]

    fresh = drive(ExplicitBrain())
    used = ExplicitBrain()
    for seq in range(30):  # build up speed, then a bend: PID memory, curve mode and v_mult all change
        act(used, frames[0], seq)
    act(used, frames[1], 30)
    assert used.in_curve
    used.reset(seed=1)
    assert not used.in_curve
    assert drive(used) == fresh


def test_constants_are_keyword_options():
    slow = ExplicitBrain(curve_speed_mps=3.0, multiplier_max=2.0)
    with pytest.raises(TypeError):
        ExplicitBrain(230.0)  # type: ignore[misc]
    image = np.zeros((240, 320, 3), dtype=np.uint8)
    assert act(slow, image).speed_mps == pytest.approx(8.0)  # straight mode (no line), v_mult capped at 2
