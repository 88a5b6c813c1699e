"""The kinematic unicycle: exact arc integration, straight-line limit, yaw wrapping, determinism."""

from __future__ import annotations

import dataclasses
import math

import pytest

from services.simulator.car import CarState, integrate_unicycle, wrap_angle


def test_a_full_circle_of_radius_v_over_w_returns_to_the_start():
    start = CarState(x_m=3.0, y_m=-2.0, yaw_rad=0.7)
    speed, yaw_rate, steps = 2.0, 0.5, 40
    dt = (2 * math.pi / yaw_rate) / steps
    state, farthest = start, 0.0
    for _ in range(steps):
        state = integrate_unicycle(state, speed_mps=speed, yaw_rate_radps=yaw_rate, dt_s=dt)
        farthest = max(farthest, math.hypot(state.x_m - start.x_m, state.y_m - start.y_m))
    assert state.x_m == pytest.approx(start.x_m, abs=1e-9)
    assert state.y_m == pytest.approx(start.y_m, abs=1e-9)
    assert wrap_angle(state.yaw_rad - start.yaw_rad) == pytest.approx(0.0, abs=1e-9)
    assert farthest == pytest.approx(2 * speed / yaw_rate, rel=1e-3)  # the diameter, 2 v / w


def test_every_point_of_the_arc_lies_on_the_circle_left_of_the_car_for_positive_yaw_rate():
    start = CarState(x_m=0.0, y_m=0.0, yaw_rad=0.0)  # heading +x; turning left means the centre is at (0, +R)
    radius = 3.0
    for dt in (0.1, 0.5, 1.0, 2.0):
        state = integrate_unicycle(start, speed_mps=1.5, yaw_rate_radps=1.5 / radius, dt_s=dt)
        assert math.hypot(state.x_m, state.y_m - radius) == pytest.approx(radius, abs=1e-12)
        assert state.y_m > 0
    quarter = integrate_unicycle(start, speed_mps=1.5, yaw_rate_radps=0.5, dt_s=math.pi)
    assert (quarter.x_m, quarter.y_m, quarter.yaw_rad) == pytest.approx((radius, radius, math.pi / 2), abs=1e-12)


def test_straight_line_when_the_yaw_rate_is_zero_or_negligible():
    start = CarState(x_m=1.0, y_m=2.0, yaw_rad=math.radians(30))
    for yaw_rate in (0.0, 1e-12, -5e-10):
        state = integrate_unicycle(start, speed_mps=4.0, yaw_rate_radps=yaw_rate, dt_s=0.5)
        assert state.x_m == pytest.approx(1.0 + 2.0 * math.cos(math.radians(30)), abs=1e-12)
        assert state.y_m == pytest.approx(2.0 + 2.0 * math.sin(math.radians(30)), abs=1e-12)
        assert state.yaw_rad == pytest.approx(math.radians(30), abs=1e-9)
    # Just above the threshold the arc formula agrees with the straight line to rounding.
    arc = integrate_unicycle(start, speed_mps=4.0, yaw_rate_radps=1e-8, dt_s=0.5)
    assert (arc.x_m, arc.y_m) == pytest.approx((1.0 + 2.0 * math.cos(math.radians(30)), 2.0 + 1.0), abs=1e-7)


def test_turning_on_the_spot():
    state = integrate_unicycle(CarState(1.0, 1.0, 0.0), speed_mps=0.0, yaw_rate_radps=-1.0, dt_s=0.25)
    assert (state.x_m, state.y_m, state.yaw_rad) == (1.0, 1.0, -0.25)


@pytest.mark.parametrize(
    ("speed", "yaw_rate"), [(7.0, 1.1), (24.0, -0.03), (3.0, -2.5), (-1.0, 0.4), (5.0, 0.0), (0.0, 3.0)]
)
def test_two_half_steps_equal_one_step(speed, yaw_rate):
    start = CarState(x_m=-12.5, y_m=40.25, yaw_rad=2.9)
    whole = integrate_unicycle(start, speed_mps=speed, yaw_rate_radps=yaw_rate, dt_s=0.05)
    half = integrate_unicycle(start, speed_mps=speed, yaw_rate_radps=yaw_rate, dt_s=0.025)
    halves = integrate_unicycle(half, speed_mps=speed, yaw_rate_radps=yaw_rate, dt_s=0.025)
    assert halves.x_m == pytest.approx(whole.x_m, abs=1e-12)
    assert halves.y_m == pytest.approx(whole.y_m, abs=1e-12)
    assert wrap_angle(halves.yaw_rad - whole.yaw_rad) == pytest.approx(0.0, abs=1e-12)


def test_yaw_is_wrapped_into_minus_pi_to_pi():
    state = CarState(0.0, 0.0, 3.0)
    for _ in range(100):
        state = integrate_unicycle(state, speed_mps=1.0, yaw_rate_radps=2.0, dt_s=0.1)
        assert -math.pi < state.yaw_rad <= math.pi
    assert wrap_angle(-math.pi) == math.pi
    assert wrap_angle(math.pi) == math.pi
    assert wrap_angle(3 * math.pi / 2) == pytest.approx(-math.pi / 2)


def test_integration_is_deterministic_and_pure():
    def drive() -> list[CarState]:
        state, states = CarState(0.0, 0.0, 0.0), []
        for step in range(500):
            state = integrate_unicycle(
                state, speed_mps=7.0 + math.sin(step), yaw_rate_radps=math.cos(0.1 * step), dt_s=0.05
            )
            states.append(state)
        return states

    start = CarState(0.5, 0.5, 0.5)
    integrate_unicycle(start, speed_mps=1.0, yaw_rate_radps=1.0, dt_s=1.0)
    assert start == CarState(0.5, 0.5, 0.5)
    assert drive() == drive()  # bitwise equal
    with pytest.raises(dataclasses.FrozenInstanceError):
        start.x_m = 1.0  # type: ignore[misc]
