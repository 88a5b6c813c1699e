"""Episode specs as the simulator announces them, for processes that must set up per episode before its frames."""

from __future__ import annotations

import time

from protocol import keys
from protocol.bus import Bus, Inbox
from protocol.messages import EpisodeEvent, EpisodeSpec, EventKind


class EpisodeStarts:
    """The spec of each episode of a run, read from its START event.

    The simulator publishes START before the episode's first frame, on the same session, so it normally arrives
    first; ``spec`` waits briefly for it otherwise (a process that joined late never sees it and gets None).
    """

    def __init__(self, bus: Bus, run_id: str):
        self._inbox = Inbox()
        bus.subscribe(keys.events(run_id), EpisodeEvent, inbox=self._inbox)
        self._specs: dict[int, EpisodeSpec] = {}

    def spec(self, episode: int, *, wait_s: float = 0.5) -> EpisodeSpec | None:
        """The spec of ``episode`` (each is handed out once), or None if its START is not seen within ``wait_s``."""
        deadline = time.monotonic() + wait_s
        while episode not in self._specs:
            remaining = deadline - time.monotonic()
            received = self._inbox.recv(timeout_s=max(0.0, min(0.05, remaining)))
            if received is not None:
                event = received.message
                if event.kind == EventKind.START and event.spec is not None:
                    self._specs[event.header.episode] = event.spec
            elif remaining <= 0:
                break
        return self._specs.pop(episode, None)
