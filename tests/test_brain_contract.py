"""Every registered brain meets the brain contract: ``brains.checker`` (what ``drivebench brains check`` runs), over
the whole registry, on real rendered frames; and the checker names the fix for brains that break it."""

from __future__ import annotations

import sys

import numpy as np
import pytest
from needs import require

from brains import Observation, brain_names, make_brain
from brains.checker import CHECK_WORLDS, check_brain, passed, render_frames
from brains.nets import MODELS
from brains.registry import UnknownBrainError
from circuits import load_circuit
from protocol.episode_spec import CameraSpec
from services.simulator.car import CarState
from services.simulator.scene import Scene

# Neural brains need weights: each network's brain gets an untrained checkpoint of it ("neural" takes any network),
# so a new network in brains.nets.MODELS is checked here without a test edit.
NEURAL = {name: name for name in MODELS} | {"neural": "deepest_lstm_tiny_pilotnet"}
BM_EXAMPLE = "examples/behavior_metrics/brain_f1_follow_line.py"


@pytest.fixture(scope="module")
def brain_options(tmp_path_factory):
    """``brain_options(name)``: the constructor options the contract needs for brain ``name``."""
    made: dict[str, str] = {}

    def options(name: str) -> dict:
        if name == "behavior_metrics":
            return {"file": BM_EXAMPLE}
        if name not in NEURAL:
            return {}
        require("torch")
        require("onnxruntime")
        from brains.neural.checkpoint import make_random_checkpoint

        model = NEURAL[name]
        if model not in made:
            made[model] = str(make_random_checkpoint(tmp_path_factory.mktemp("weights") / f"{model}.pt", model))
        return {"weights": made[model]}

    return options


@pytest.fixture(scope="module")
def frames():
    """The checker's own frames: consecutive views along simple in four worlds, read-only as the host gives them."""
    return render_frames()


# Brains that drive through the bus themselves (ros2: a ROS 2 node answers each frame) have nobody to answer them
# here; tests/test_ros2_bridge.py drives one with a real Zenoh peer publishing the Twists.
BUS_BRAINS = {"ros2"}


@pytest.mark.parametrize("name", [name for name in brain_names() if name not in BUS_BRAINS])
def test_every_registered_brain_meets_the_contract(name, frames, brain_options):
    results = check_brain(name, options=brain_options(name), frames=frames, memory_steps=120)
    assert [r.name for r in results] == [
        "make",
        "protocol",
        "act",
        "read-only",
        "units",
        "answer time",
        "determinism",
        "memory",
    ]
    assert passed(results), "\n".join(r.line() for r in results)


def test_the_checker_frames_are_real_renders_of_every_world(frames):
    assert len(frames) == 12 * len(CHECK_WORLDS)
    assert all(f.image_rgb.shape == (240, 320, 3) and not f.image_rgb.flags.writeable for f in frames)
    red = [(f.image_rgb[..., 0] > 2 * f.image_rgb[..., 1].astype(int)).sum() for f in frames]
    assert min(red[:12]) > 100 and max(red[24:36]) == 0  # the red line in the default world, none without a line


@pytest.mark.parametrize("size", [(200, 66), (100, 50)], ids=lambda s: f"{s[0]}x{s[1]}")
@pytest.mark.parametrize("name", ["explicit", "deepest_lstm_tiny_pilotnet", "memdccp"])
def test_brains_answer_any_camera_size(name, size, brain_options):
    circuit = load_circuit("simple")
    with Scene(circuit) as scene:
        images = [
            scene.render(CarState(*circuit.centreline.pose_at(s)), CameraSpec(width_px=size[0], height_px=size[1]))
            for s in np.arange(0.0, 12.0, 4.0)
        ]
    brain = make_brain(name, **brain_options(name))
    brain.reset(seed=0)
    actions = [
        brain.act(Observation(image_rgb=image, stamp_ns=i * 50_000_000, seq=i)) for i, image in enumerate(images)
    ]
    assert all(np.isfinite([a.speed_mps, a.yaw_rate_radps]).all() for a in actions)


BROKEN = '''
import random
from brains.base import Action


class Hoarder:
    """Keeps every frame, answers in km/h and draws random numbers without a seed."""
    def __init__(self):
        self.seen = []
    def reset(self, *, seed):
        pass
    def act(self, observation):
        self.seen.append(observation.image_rgb.copy())
        return Action(speed_mps=100 + random.random(), yaw_rate_radps=0.0)


class Tuple:
    def reset(self, *, seed):
        pass
    def act(self, observation):
        return (1.0, 0.0)


class Scribbler:
    def reset(self, *, seed):
        pass
    def act(self, observation):
        observation.image_rgb[0, 0] = 0
        return Action(speed_mps=1.0, yaw_rate_radps=0.0)


class FlagFlipper:
    """Writes into the image after making it writeable: numpy's error then names no read-only at all."""
    def reset(self, *, seed):
        pass
    def act(self, observation):
        observation.image_rgb.setflags(write=True)
        observation.image_rgb[0, 0] = 0
        return Action(speed_mps=1.0, yaw_rate_radps=0.0)


class Picky:
    """Raises its own ValueError, whose words happen to say read-only: it never writes into the image."""
    def reset(self, *, seed):
        pass
    def act(self, observation):
        raise ValueError("config is read-only and not writeable: refusing to drive")


class PositionalSeed:
    def reset(self, seed_value):
        pass
    def act(self, observation):
        return Action(speed_mps=1.0, yaw_rate_radps=0.0)


class Degrees:
    def reset(self, *, seed):
        pass
    def act(self, observation):
        return Action(speed_mps=5.0, yaw_rate_radps=45.0)


class NeedsOption:
    def __init__(self, *, gain):
        self.gain = gain
'''


@pytest.fixture
def broken_brains(tmp_path, monkeypatch):
    (tmp_path / "broken_brains.py").write_text(BROKEN)
    monkeypatch.syspath_prepend(str(tmp_path))
    yield
    sys.modules.pop("broken_brains", None)


def failures(results) -> dict[str, str]:
    return {r.name: f"{r.detail} | fix: {r.fix}" for r in results if r.status == "fail"}


def test_checker_names_the_fix_for_each_broken_rule(broken_brains, frames):
    hoarder = failures(check_brain("broken_brains:Hoarder", frames=frames))
    assert set(hoarder) == {"units", "determinism", "memory"}
    assert "km/h" in hoarder["units"] and "seed every random generator" in hoarder["determinism"]
    assert "deque" in hoarder["memory"] and "MiB" in hoarder["memory"]
    assert "not brains.base.Action" in failures(check_brain("broken_brains:Tuple", frames=frames))["act"]
    assert "copy the image" in failures(check_brain("broken_brains:Scribbler", frames=frames))["read-only"]
    assert (
        "def reset(self, *, seed: int)"
        in failures(check_brain("broken_brains:PositionalSeed", frames=frames))["protocol"]
    )
    assert "radians per second" in failures(check_brain("broken_brains:Degrees", frames=frames))["units"]
    assert "gain" in failures(check_brain("broken_brains:NeedsOption", frames=frames))["make"]
    assert passed(check_brain("broken_brains:NeedsOption", options={"gain": 1}, frames=frames)) is False  # no act


def test_writing_into_the_image_is_told_by_what_act_does_not_by_the_error_words(broken_brains, frames):
    flipper = failures(check_brain("broken_brains:FlagFlipper", frames=frames))
    assert set(flipper) == {"read-only"} and "copy the image" in flipper["read-only"], flipper
    picky = failures(check_brain("broken_brains:Picky", frames=frames))
    assert set(picky) == {"act"} and "refusing to drive" in picky["act"], picky  # its own error, not read-only


def test_checker_stops_at_a_name_that_leads_nowhere(broken_brains):
    for name, expected in (
        ("hal", "unknown brain 'hal'"),
        ("broken_brains:Nope", "has no 'Nope'"),
        ("no_such_module:Brain", "cannot import module 'no_such_module'"),
        ("missing_brain.py", "not found"),
    ):
        results = check_brain(name)
        assert [(r.name, r.status) for r in results] == [("make", "fail")] and expected in results[0].detail


def test_unknown_brain_names_the_known_ones_and_the_other_forms():
    with pytest.raises(
        UnknownBrainError,
        match=r"unknown brain 'hal' \(known: behavior_metrics, constant, "
        r"deepest_lstm_tiny_pilotnet, expert, explicit, .*memdccp, .*; or give "
        r"package.module:Class, or a Behavior Metrics brain file",
    ):
        make_brain("hal")
