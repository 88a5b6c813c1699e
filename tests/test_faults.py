"""Faults an operator meets: the driver of an episode dies, two drivers want the same simulator.

Killed services (typed failures, a recorder death that spares the episode) are in tests/test_stack.py; bad input
before anything starts in tests/test_cli.py.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import pytest
from support.attach import attach_driver
from support.env import clean_env
from support.waits import wait_for

from orchestrator.stack.launcher import BrainLaunch
from protocol import keys
from protocol.bus import Inbox
from protocol.messages import EndReason, EpisodeEvent, EventKind
from services.simulator.service import DRIVER_GRACE_S

pytestmark = pytest.mark.integration


def attach(stack, out, *args: str) -> subprocess.Popen:
    """A driver attached to ``stack`` that prints its score as JSON on stdout."""
    return attach_driver(endpoint=stack.endpoint, run_id=stack.run_id, out=out, args=("--json", *args))


def next_event(inbox: Inbox, kind: EventKind, *, timeout_s: float) -> EpisodeEvent:
    deadline = time.monotonic() + timeout_s
    while (received := inbox.recv(timeout_s=max(0.0, deadline - time.monotonic()))) is not None:
        if received.message.kind == kind:
            return received.message
    raise AssertionError(f"no {kind} event within {timeout_s} s")


def still_stack_with_events(make_stack):
    """A stack whose brain stands still (episodes end only at their limit), and an inbox of its episode events."""
    stack = make_stack(BrainLaunch("constant", options=("speed_mps=0.0",)))
    events = Inbox()
    stack.bus.subscribe(keys.events(stack.run_id), EpisodeEvent, inbox=events)
    return stack, events


def test_a_killed_attached_driver_ends_its_episode_driver_lost_and_the_next_attach_runs(make_stack, tmp_path):
    stack, events = still_stack_with_events(make_stack)
    driver = attach(stack, tmp_path / "first", "--max-sim-seconds", "600", "--realtime")
    try:
        next_event(events, EventKind.START, timeout_s=60)
        time.sleep(1.0)
        os.killpg(driver.pid, signal.SIGKILL)  # the driver, and nothing else, is gone
        killed_at = time.monotonic()
        end = next_event(events, EventKind.END, timeout_s=DRIVER_GRACE_S + 10)
        assert end.reason == EndReason.DRIVER_LOST
        assert time.monotonic() - killed_at < DRIVER_GRACE_S + 2.0
    finally:
        driver.kill()
        driver.communicate()
    second = attach(stack, tmp_path / "second", "--max-sim-seconds", "3")
    stdout, stderr = second.communicate(timeout=120)
    assert second.returncode == 0, stderr
    assert json.loads(stdout)["reason"] == EndReason.TIME_LIMIT  # the same services, no restart


def test_attach_waits_for_a_busy_simulator_instead_of_failing(make_stack, tmp_path):
    stack, events = still_stack_with_events(make_stack)
    first = attach(stack, tmp_path / "first", "--max-sim-seconds", "4", "--realtime")
    try:
        next_event(events, EventKind.START, timeout_s=60)
        second = attach(stack, tmp_path / "second", "--max-sim-seconds", "1", "--wait", "60")
        out_second, err_second = second.communicate(timeout=120)
        out_first, err_first = first.communicate(timeout=60)
    finally:
        first.kill()
    assert first.returncode == 0 and second.returncode == 0, err_first + err_second
    assert json.loads(out_first)["header"]["episode"] + 1 == json.loads(out_second)["header"]["episode"]


def test_a_brain_host_with_an_orphan_timeout_exits_when_its_stack_is_gone(make_stack, tmp_path):
    """What drivebench swap starts watches no parent (it must outlive the swap command); it ends with its stack."""
    stack = make_stack(BrainLaunch("explicit"))
    env = clean_env()
    with open(tmp_path / "extra.log", "wb") as log:
        extra = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "brains",
                "--router",
                stack.endpoint,
                "--run-id",
                stack.run_id,
                "--brain",
                "constant",
                "--name",
                "extra",
                "--set",
                "orphan_timeout_s=2",
            ],
            stdout=log,
            stderr=subprocess.STDOUT,
            env=env,
            start_new_session=True,
        )
    try:
        token = keys.alive(stack.run_id, "brain", "extra")
        wait_for(
            lambda: token in stack.bus.alive_now(token),
            timeout_s=30,
            what="the extra brain host's liveliness token",
            alive=lambda: None if extra.poll() is None else (tmp_path / "extra.log").read_text(),
        )
        time.sleep(3.0)
        assert extra.poll() is None  # a simulator is there: it stays
        stack.child("simulator", "sim").process.kill()
        assert extra.wait(timeout=15) == 0
        assert "its stack is gone" in (tmp_path / "extra.log").read_text()
    finally:
        extra.kill()


def test_sigterm_mid_episode_ends_it_stopped_and_the_simulator_exits_143(make_stack, tmp_path):
    """Services stop on a flag, never from inside the signal handler: SIGTERM mid-episode lets the simulator finish
    its step, publish the episode's END (stopped) and close its session in order; the exit code says SIGTERM."""
    stack, events = still_stack_with_events(make_stack)
    driver = attach(stack, tmp_path / "run", "--max-sim-seconds", "600", "--realtime")
    try:
        next_event(events, EventKind.START, timeout_s=60)
        time.sleep(1.0)
        simulator = stack.child("simulator", "sim").process
        simulator.send_signal(signal.SIGTERM)
        assert next_event(events, EventKind.END, timeout_s=10).reason == EndReason.STOPPED
        assert simulator.wait(timeout=20) == 128 + signal.SIGTERM
    finally:
        driver.kill()
        driver.communicate()
