"""Queries the simulator's run control over the bus it is given (the sandbox's Unix socket): "status" for the
episode's spec (its conditions) and "stop" to end the episode. Prints what came back, on frames 5 to 7."""

from __future__ import annotations

import sys

from brains.base import Action, Observation
from protocol import codec, keys
from protocol.bus import Bus, BusConfig
from protocol.messages import ControlRequest
from support.hostile.base import Driving


class QuerierBrain(Driving):
    def __init__(self, *, run_id: str, router: str = "unixsock-stream//bus.sock"):
        self._run_id = run_id
        self._bus = Bus(BusConfig(mode="client", connect=[router], shared_memory=False), name="querier")

    def act(self, observation: Observation) -> Action:
        if 5 <= observation.seq < 8:
            for action in ("status", "stop"):
                request = codec.encode(ControlRequest(action=action))
                reply = self._bus.request(keys.sim_control(self._run_id), request, timeout_s=0.5)
                print(f"run control {action}: {'answered' if reply else 'no answer'}", file=sys.stderr, flush=True)
        return Action(speed_mps=1.0, yaw_rate_radps=0.0)
