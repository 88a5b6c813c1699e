"""Integration: the noise injector as its own process between the simulator and the brains."""

from __future__ import annotations

import numpy as np
import pytest

from orchestrator.stack.launcher import BrainLaunch
from protocol import keys
from protocol.bus import Inbox
from protocol.episode_spec import CameraSpec, Delay, Drop, EpisodeSpec, SaltPepper, WorldVariation
from protocol.images import frame_image
from protocol.messages import CameraFrame, EndReason, Pose

pytestmark = pytest.mark.integration
SMALL = CameraSpec(width_px=96, height_px=72)


def test_brains_see_perturbed_frames_and_the_scorer_ground_truth(make_stack):
    stack = make_stack(BrainLaunch("explicit"))
    raw, perturbed = Inbox(), Inbox()
    stack.bus.subscribe(keys.camera_raw(stack.run_id), CameraFrame, inbox=raw)
    stack.bus.subscribe(keys.camera_perturbed(stack.run_id), CameraFrame, inbox=perturbed)
    score = stack.run_episode(EpisodeSpec(max_sim_seconds=2.0, camera=SMALL, noise=[SaltPepper(probability=0.4)]))
    assert score.reason == EndReason.TIME_LIMIT
    raw_frames = {r.message.header.seq: frame_image(r.message) for r in raw.drain()}
    noisy_frames = {r.message.header.seq: frame_image(r.message) for r in perturbed.drain()}
    assert set(noisy_frames) == set(raw_frames) == set(range(40))
    changed = np.mean([np.any(raw_frames[s] != noisy_frames[s], axis=2).mean() for s in raw_frames])
    assert 0.3 < changed < 0.5  # about 40 % of the pixels (a few were already black or white)


def test_dropped_frames_do_not_stall_lock_step(make_stack):
    stack = make_stack(BrainLaunch("explicit"))
    score = stack.run_episode(EpisodeSpec(max_sim_seconds=5.0, camera=SMALL, noise=[Drop(probability=0.3)]))
    assert score.reason == EndReason.TIME_LIMIT
    assert score.metrics.steps == 100
    assert score.metrics.command_rate_hz == pytest.approx(20.0)  # every frame answered, dropped or not
    assert score.metrics.wall_time_s < 10  # and no frame waited for a resend


def test_noise_is_seeded_from_the_spec(make_stack):
    stack = make_stack(BrainLaunch("explicit"))
    poses = Inbox()
    stack.bus.subscribe(keys.pose(stack.run_id), Pose, inbox=poses)
    noise = [SaltPepper(probability=0.3), Delay(frames=2)]
    runs = [
        stack.run_episode(
            EpisodeSpec(max_sim_seconds=8.0, seed=seed, camera=CameraSpec(width_px=160, height_px=120), noise=noise)
        )
        for seed in (1, 1, 2)
    ]
    by_episode: dict[int, list] = {}
    for received in poses.drain():
        by_episode.setdefault(received.message.header.episode, []).append(
            (received.message.x_m, received.message.y_m, received.message.yaw_rad)
        )
    first, again, other = (np.array(by_episode[run.header.episode]) for run in runs)
    assert np.array_equal(first, again)
    assert not np.array_equal(first, other)


def test_without_the_line_the_explicit_brain_fails_with_a_typed_reason(make_stack):
    stack = make_stack(BrainLaunch("explicit"))
    score = stack.run_episode(EpisodeSpec(max_sim_seconds=120.0, camera=SMALL, world=WorldVariation(line="none")))
    assert score.reason in (EndReason.CRASH, EndReason.OFF_TRACK)
    assert score.metrics.completed_laps == 0
    assert score.metrics.progress_laps < 0.5
