"""A control query answered late (a loaded machine: the simulator's callback waits seconds for its CPU) is still
an answer: the stack does not turn it into a failure. On a 2-core machine at load 11, ``test_camera_source`` and the
challenge server's evaluations failed with "request to .../sim/control failed: Timeout" after 2 s."""

from __future__ import annotations

import subprocess
import sys
import time

import pytest

from orchestrator.stack.launcher import LocalStack, free_loopback_port
from protocol import codec, keys
from protocol.bus import Bus, BusConfig, probe_router
from protocol.messages import ControlReply, ControlRequest, ServerState

LATE_S = 3.0  # later than the 2 s every control query waited before


@pytest.fixture
def router():
    port = free_loopback_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    process = subprocess.Popen([sys.executable, "-m", "services.router", "--listen", endpoint])
    try:
        deadline = time.monotonic() + 30
        while True:
            try:
                probe_router(endpoint, timeout_s=0.5)
                break
            except Exception:
                assert time.monotonic() < deadline, "the router did not listen"
                time.sleep(0.1)
        yield endpoint
    finally:
        process.terminate()
        process.wait(timeout=20)


def test_a_simulator_that_answers_a_start_late_is_answered_not_failed(router, tmp_path):
    def late_answer(payload: bytes) -> bytes:
        time.sleep(LATE_S)
        request = codec.decode(payload, ControlRequest)
        return codec.encode(ControlReply(ok=True, state=ServerState.STARTING, episode=len(request.action)))

    with Bus(BusConfig(mode="client", connect=[router]), name="late-sim") as simulator:
        simulator.serve(keys.sim_control("late"), late_answer)
        stack = LocalStack(run_id="late", run_dir=tmp_path, router_endpoint=router)
        with Bus(BusConfig(mode="client", connect=[router]), name="driver") as bus:
            stack.bus = bus
            started = time.monotonic()
            reply = stack._control(ControlRequest(action="start"))
            assert reply.ok and reply.episode == len("start")
            assert time.monotonic() - started >= LATE_S
