"""Listens, over the bus it is given (the sandbox's Unix socket), for what would let it drive without its camera: the
simulator's ground-truth poses, the scorer's live metrics (cross-track error, progress), the brains' commands,
everything under the project's root, the simulator's episode events (their START carries the episode's spec: its
conditions), the brains' copy of them, and the simulator's status (the spec again). On frame 30 it prints how many
messages of each it got, and how many held ``secret`` (the name of the circuit it drives: a condition)."""

from __future__ import annotations

import collections
import sys

from brains.base import Action, Observation
from protocol import codec, keys
from protocol.bus import Bus, BusConfig
from protocol.messages import ControlRequest
from support.hostile.base import Driving


class SpyBrain(Driving):
    def __init__(self, *, run_id: str, secret: str = "", router: str = "unixsock-stream//bus.sock"):
        self._run_id = run_id
        self._secret = secret.encode()
        self._secret_seen = 0
        self._bus = Bus(BusConfig(mode="client", connect=[router], shared_memory=False), name="spy")
        self._got: collections.Counter[str] = collections.Counter()
        self._subscribers = [
            self._bus.session.declare_subscriber(key, lambda sample, what=what: self._spied(what, sample))
            for what, key in (
                ("pose", keys.pose(run_id)),
                ("live metrics", keys.live_metrics(run_id)),
                ("commands", keys.commands_all(run_id)),
                ("events", keys.events(run_id)),
                ("brain events", keys.brain_events(run_id)),
                ("anything", f"{keys.ROOT}/**"),
            )
        ]

    def _spied(self, what: str, sample) -> None:
        self._got.update([what])
        if self._secret and self._secret in sample.payload.to_bytes():
            self._secret_seen += 1

    def act(self, observation: Observation) -> Action:
        if observation.seq == 30:
            request = codec.encode(ControlRequest(action="status"))
            status = self._bus.request(keys.sim_status(self._run_id), request, timeout_s=0.5)
            got = ", ".join(f"{what} {self._got[what]}" for what in ("pose", "live metrics", "commands", "events"))
            print(f"spied: {got}; status {'answered' if status else 'no answer'}", file=sys.stderr, flush=True)
            print(f"spied anything: {self._got['anything']}", file=sys.stderr, flush=True)
            print(f"spied brain events: {self._got['brain events']}", file=sys.stderr, flush=True)
            print(f"spied the secret: {self._secret_seen} time(s)", file=sys.stderr, flush=True)
        return Action(speed_mps=1.0, yaw_rate_radps=0.0)
