"""The noisy driver: the base brain's commands plus seeded bursts of yaw rate (recovery-data collection)."""

from __future__ import annotations

import numpy as np
import pytest

from brains import Observation, make_brain


def observations(count: int) -> list[Observation]:
    image = np.zeros((48, 64, 3), np.uint8)
    return [Observation(image_rgb=image, stamp_ns=i * 50_000_000, seq=i) for i in range(count)]


def yaw_rates(brain, *, seed: int, count: int = 400) -> np.ndarray:
    brain.reset(seed=seed)
    return np.array([brain.act(o).yaw_rate_radps for o in observations(count)])


def test_bursts_add_to_the_base_yaw_rate_and_leave_speed_alone():
    base = {"speed_mps": 3.0, "yaw_rate_radps": 0.2}
    brain = make_brain("noisy", base="constant", base_options=base, steering_noise_radps=0.8)
    brain.reset(seed=1)
    actions = [brain.act(o) for o in observations(400)]
    assert all(a.speed_mps == 3.0 for a in actions)
    disturbance = np.array([a.yaw_rate_radps for a in actions]) - 0.2
    active = np.abs(disturbance) > 1e-12
    assert 0.05 < active.mean() < 0.4  # bursts of 3-8 frames, one starting every ~33 frames
    assert np.all((np.abs(disturbance[active]) >= 0.4 - 1e-9) & (np.abs(disturbance[active]) <= 0.8 + 1e-9))
    assert (disturbance > 0).any() and (disturbance < 0).any()


def test_bursts_are_seeded():
    brain = make_brain("noisy", base="constant", steering_noise_radps=0.5)
    assert np.array_equal(yaw_rates(brain, seed=3), yaw_rates(brain, seed=3))
    assert not np.array_equal(yaw_rates(brain, seed=3), yaw_rates(brain, seed=4))


def test_without_noise_it_is_the_base_brain():
    brain = make_brain("noisy", base="constant", base_options={"yaw_rate_radps": -0.1}, steering_noise_radps=0.0)
    assert np.all(yaw_rates(brain, seed=0) == -0.1)


def test_bad_options_are_refused():
    with pytest.raises(ValueError, match="wrap itself"):
        make_brain("noisy", base="noisy")
    with pytest.raises(ValueError, match="steering_noise_radps"):
        make_brain("noisy", steering_noise_radps=-1.0)
