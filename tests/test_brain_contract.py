"""Every registered brain honours the brain protocol (the contract test, run over the whole registry)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from brains import Action, Brain, Observation, brain_names, make_brain
from brains.registry import UnknownBrainError
from services.circuits import load_circuit
from services.simulator.car import CarState
from services.simulator.scene import Scene
from protocol.messages import CameraSpec

SIZES = [(320, 240), (200, 66), (100, 50)]

# Neural brains need weights: each gets an untrained checkpoint of its network ("neural" takes any network).
NEURAL = {"pilotnet": "pilotnet", "deepest_lstm_tiny_pilotnet": "deepest_lstm_tiny_pilotnet",
          "pilotnet_x3": "pilotnet_x3", "memdccp": "memdccp", "neural": "deepest_lstm_tiny_pilotnet"}


@pytest.fixture(scope="module")
def brain_options(tmp_path_factory):
    """``brain_options(name)``: the constructor options the contract test needs for brain ``name``."""
    made: dict[str, str] = {}

    def options(name: str) -> dict:
        if name not in NEURAL:
            return {}
        pytest.importorskip("torch")
        pytest.importorskip("onnxruntime")
        from brains.neural.checkpoint import make_random_checkpoint

        model = NEURAL[name]
        if model not in made:
            made[model] = str(make_random_checkpoint(tmp_path_factory.mktemp("weights") / f"{model}.pt", model))
        return {"weights": made[model]}

    return options


@pytest.fixture(scope="module")
def frames() -> dict[tuple[int, int], list[np.ndarray]]:
    """Real rendered frames along the start of the simple circuit, per camera size."""
    circuit = load_circuit("simple")
    with Scene(circuit) as scene:
        poses = [circuit.centreline.pose_at(s) for s in np.arange(0.0, 60.0, 4.0)]
        return {(w, h): [scene.render(CarState(x_m=x, y_m=y, yaw_rad=yaw), CameraSpec(width_px=w, height_px=h))
                         for x, y, yaw in poses] for w, h in SIZES}


def drive(brain: Brain, images: list[np.ndarray], *, seed: int) -> list[Action]:
    brain.reset(seed=seed)
    return [brain.act(Observation(image_rgb=image, stamp_ns=i * 50_000_000, seq=i)) for i, image in enumerate(images)]


@pytest.mark.parametrize("name", brain_names())
@pytest.mark.parametrize("size", SIZES, ids=lambda s: f"{s[0]}x{s[1]}")
def test_brain_contract(name, size, frames, brain_options):
    options = brain_options(name)
    brain = make_brain(name, **options)
    assert isinstance(brain, Brain)
    images = frames[size]
    first = drive(brain, images, seed=1)
    assert all(isinstance(a, Action) and math.isfinite(a.speed_mps) and math.isfinite(a.yaw_rate_radps)
               for a in first)
    # reset forgets everything: the same frames after other frames give the same actions as a fresh brain.
    drive(brain, images[::-1], seed=2)
    assert drive(brain, images, seed=1) == first
    assert drive(make_brain(name, **options), images, seed=1) == first


@pytest.mark.parametrize("name", brain_names())
def test_brain_does_not_modify_its_input(name, frames, brain_options):
    image = frames[(320, 240)][0].copy()
    before = image.copy()
    brain = make_brain(name, **brain_options(name))
    brain.reset(seed=0)
    brain.act(Observation(image_rgb=image, stamp_ns=0, seq=0))
    assert np.array_equal(image, before)


def test_unknown_brain_names_the_known_ones():
    with pytest.raises(UnknownBrainError, match=r"unknown brain 'hal' \(known: constant, deepest_lstm_tiny_pilotnet, "
                                                r"expert, explicit, memdccp, neural, noisy, pilotnet, pilotnet_x3"):
        make_brain("hal")
