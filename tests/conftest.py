"""Shared fixtures: local stacks of real processes over real Zenoh on loopback; a real rendered camera frame."""

from __future__ import annotations

import signal
import uuid
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from support.behavior_metrics import fake_bm_checkout

from orchestrator.stack.launcher import BrainLaunch, LocalStack


def pytest_configure(config) -> None:
    """A suite started in the background (``pytest &`` in a script) inherits SIGINT ignored, and so would every
    process it starts: the Ctrl-C tests would hang. Handle it again, as a terminal's suite does (exec resets a handled
    signal to its default in each child)."""
    if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)


@pytest.fixture(scope="session")
def road_frame() -> np.ndarray:
    """A real 320x240 camera frame: the simulator's view on the top straight of the simple circuit."""
    from circuits import load_circuit
    from protocol.episode_spec import EpisodeSpec
    from services.simulator.car import CarState
    from services.simulator.scene import Scene

    circuit, spec = load_circuit("simple"), EpisodeSpec()
    x, y, yaw = circuit.centreline.pose_at(20.0)
    with Scene.for_world(circuit, spec.world) as scene:
        return scene.render(CarState(x_m=x, y_m=y, yaw_rad=yaw), spec.camera)


@pytest.fixture
def make_stack(tmp_path) -> Iterator:
    """``make_stack(BrainLaunch(...), ..., record=PATH)`` starts a stack in tmp_path; every stack is stopped after
    the test. Keyword arguments go to :class:`LocalStack`."""
    stacks: list[LocalStack] = []

    def make(*brains: BrainLaunch, **options) -> LocalStack:
        run_id = options.pop("run_id", None) or f"t{uuid.uuid4().hex[:8]}"
        stack = LocalStack(
            run_id=run_id, run_dir=tmp_path / run_id, brains=list(brains) or [BrainLaunch("explicit")], **options
        )
        stacks.append(stack)
        stack.start()
        return stack

    yield make
    for stack in stacks:
        stack.close()
        for child in stack.children:
            assert child.process.poll() is not None, f"{child.role} {child.name} still running after close()"


@pytest.fixture
def bm_checkout(tmp_path) -> Path:
    """A fake Behavior Metrics checkout in a temporary folder (tests/support/behavior_metrics.py)."""
    return fake_bm_checkout(tmp_path)
