"""Publishes on the simulator's and the scorer's keys, over the bus it is given (the sandbox's Unix socket): an
END event that would end the episode as if its laps were done, and a pose far from the road."""

from __future__ import annotations

import sys

from brains.base import Action, Observation
from protocol import codec, keys
from protocol.bus import Bus, BusConfig
from protocol.messages import EndReason, EpisodeEvent, EventKind, Header, Pose
from support.hostile.base import Driving


class ForgerBrain(Driving):
    def __init__(self, *, run_id: str, router: str = "unixsock-stream//bus.sock"):
        self._run_id = run_id
        self._bus = Bus(BusConfig(mode="client", connect=[router], shared_memory=False), name="forger")
        self._forged = 0

    def act(self, observation: Observation) -> Action:
        header = Header(run_id=self._run_id, episode=0, seq=observation.seq, stamp_ns=observation.stamp_ns)
        if observation.seq >= 5:
            end = EpisodeEvent(header=header, kind=EventKind.END, reason=EndReason.LAPS_COMPLETED, last_pose_seq=0)
            self._bus.session.put(keys.events(self._run_id), codec.encode(end))
            pose = Pose(header=header, x_m=1000.0, y_m=1000.0, yaw_rad=0.0)
            self._bus.session.put(keys.pose(self._run_id), codec.encode(pose))
            self._forged += 1
            print(f"forged {self._forged}", file=sys.stderr, flush=True)
        return Action(speed_mps=1.0, yaw_rate_radps=0.0)
