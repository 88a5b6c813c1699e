"""Integration: a brain host with ``camera: auto`` drives from the simulator's frames in an episode without noise
(one hop fewer) and from the noise injector's in an episode with noise, seen in the processes' own traces
(``protocol.trace``); and it drives exactly as a host held to the noise injector's frames does."""

from __future__ import annotations

import msgspec
import pytest

from orchestrator.stack.launcher import BrainLaunch
from protocol import keys
from protocol.episode_spec import CameraSpec, EpisodeSpec, SaltPepper
from protocol.messages import EndReason
from protocol.trace import TRACE_DIR_ENV, read_traces

pytestmark = pytest.mark.integration
SMALL = CameraSpec(width_px=96, height_px=72)


def brain_frames(trace_dir, run_id: str) -> dict[tuple[int, str], dict[int, int]]:
    """(episode, "raw" | "perturbed") -> {frame seq: when its bytes first reached the brain host's Python
    ("arrived", monotonic ns)}, from its trace; (episode, "end") -> {0: when the episode's last event, its END,
    arrived there}."""
    names = {
        keys.camera_raw(run_id): "raw",
        keys.camera_perturbed(run_id): "perturbed",
        keys.brain_events(run_id): "end",
    }
    seen: dict[tuple[int, str], dict[int, int]] = {}
    for event in read_traces(trace_dir):
        if event.process.startswith("brain-") and event.event == "arrived" and event.key in names:
            if names[event.key] == "end":
                ends = seen.setdefault((event.episode, "end"), {0: event.ns})
                ends[0] = max(ends[0], event.ns)
            else:
                seen.setdefault((event.episode, names[event.key]), {}).setdefault(event.seq, event.ns)
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
    # opens both for the next one: only frame 0's (lock-step: no frame 1 before frame 0 is answered), and frames
    # that trail in after the END. How many trail (a noise injector running behind) is the machine's speed, so the
    # test checks when they came, not how many.
    for episode, source, other in ((0, "raw", "perturbed"), (1, "perturbed", "raw"), (2, "raw", "perturbed")):
        assert set(seen.get((episode, source), {})) == every_frame, (episode, source)
        (end_ns,) = seen[(episode, "end")].values()
        let_in = seen.get((episode, other), {})
        late = {seq: ns for seq, ns in let_in.items() if seq != 0 and ns <= end_ns}
        assert not late, (episode, other, sorted(late), "let in before the END")


def test_auto_camera_drives_exactly_as_the_noise_injectors_frames_do(make_stack):
    spec = EpisodeSpec(max_sim_seconds=6.0, camera=CameraSpec(width_px=160, height_px=120))
    auto = make_stack(BrainLaunch("explicit")).run_episode(spec)
    held = make_stack(BrainLaunch("explicit", host=("camera=perturbed",))).run_episode(spec)
    for score in (auto, held):
        assert score.reason == EndReason.TIME_LIMIT
    same = ("steps", "completed_distance_m", "position_deviation_mae", "cross_track_rms_m", "progress_m")
    for name in same:
        assert getattr(auto.metrics, name) == getattr(held.metrics, name), name
