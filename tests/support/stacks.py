"""Control of a running stack over the bus, as an operator's tool does it."""

from __future__ import annotations

import time

from protocol import codec, keys
from protocol.bus import Bus, BusConfig
from protocol.messages import (
    ControlRequest,
)


def stop_episode(router: str, run_id: str) -> None:
    with Bus(BusConfig(mode="peer", connect=[router]), name="test") as bus:
        for _ in range(50):
            if bus.request(keys.sim_control(run_id), codec.encode(ControlRequest(action="stop")), timeout_s=2.0):
                return
            time.sleep(0.1)
    raise AssertionError("the simulator did not answer stop")
