"""Integration: a brain host with ``camera: auto`` drives from the simulator's frames in an episode without noise
(one hop fewer) and from the noise injector's in an episode with noise, seen in the processes' own traces
(``protocol.trace``); and it drives exactly as a host held to the noise injector's frames does."""

from __future__ import annotations

import msgspec
import pytest

from orchestrator.stack.launcher import BrainLaunch
from protocol import keys
from protocol.messages import CameraSpec, EndReason, EpisodeSpec, SaltPepper
from protocol.trace import TRACE_DIR_ENV, read_traces

pytestmark = pytest.mark.integration
SMALL = CameraSpec(width_px=96, height_px=72)


def brain_frames(trace_dir, run_id: str) -> dict[tuple[int, str], set[int]]:
    """(episode, "raw" | "perturbed") -> frame seqs whose bytes reached the brain host's Python at all
    ("arrived"), from its trace."""
    names = {keys.camera_raw(run_id): "raw", keys.camera_perturbed(run_id): "perturbed"}
    seen: dict[tuple[int, str], set[int]] = {}
    for event in read_traces(trace_dir):
        if event.process.startswith("brain-") and event.event == "arrived" and event.key in names:
            seen.setdefault((event.episode, names[event.key]), set()).add(event.seq)
    return seen


def test_auto_camera_takes_the_simulators_frames_without_noise_and_the_noise_injectors_with_it(
    make_stack, tmp_path, monkeypatch
):
    trace_dir = tmp_path / "trace"
    trace_dir.mkdir()
    monkeypatch.setenv(TRACE_DIR_ENV, str(trace_dir))
    stack = make_stack(BrainLaunch("explicit"))
    monkeypatch.delenv(TRACE_DIR_ENV)
    plain = EpisodeSpec(max_sim_seconds=2.0, camera=SMALL)
    noisy = msgspec.structs.replace(plain, noise=[SaltPepper(probability=0.2)])
    scores = [stack.run_episode(spec) for spec in (plain, noisy, plain)]
    assert [s.reason for s in scores] == [EndReason.TIME_LIMIT] * 3
    stack.close()  # the processes write their traces as they stop
    seen = brain_frames(trace_dir, stack.run_id)
    every_frame = set(range(40))
    # Without noise the simulator's copy of every frame gets in; with noise the noise injector's. The other copy is
    # dropped unread from the moment the first frame of the episode came on its stream, until the episode's END
    # opens both for the next one: only frame 0's, and the last frames' when the noise injector trails behind.
    for episode, source, other in ((0, "raw", "perturbed"), (1, "perturbed", "raw"), (2, "raw", "perturbed")):
        assert seen.get((episode, source)) == every_frame, (episode, source)
        let_in = seen.get((episode, other), set())
        assert len(let_in) <= 4 and let_in <= {0} | set(range(36, 40)), (episode, other, let_in)


def test_auto_camera_drives_exactly_as_the_noise_injectors_frames_do(make_stack):
    spec = EpisodeSpec(max_sim_seconds=6.0, camera=CameraSpec(width_px=160, height_px=120))
    auto = make_stack(BrainLaunch("explicit")).run_episode(spec)
    held = make_stack(BrainLaunch("explicit", host=("camera=perturbed",))).run_episode(spec)
    for score in (auto, held):
        assert score.reason == EndReason.TIME_LIMIT
    same = ("steps", "completed_distance_m", "position_deviation_mae", "cross_track_rms_m", "progress_m")
    for name in same:
        assert getattr(auto.metrics, name) == getattr(held.metrics, name), name
