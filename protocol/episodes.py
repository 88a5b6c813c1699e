"""Episode specs as the simulator announces them, for processes that must set up per episode before its frames."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Any, Generic, TypeVar

from protocol import codec, keys
from protocol.bus import Bus, BusError, Inbox
from protocol.episode_spec import EpisodeSpec
from protocol.messages import BrainEvent, ControlReply, ControlRequest, EpisodeEvent, EventKind, Header

log = logging.getLogger("drivebench.episodes")
Start = TypeVar("Start")

STATUS_TIMEOUT_S = 2.0


def running_spec(bus: Bus, run_id: str, episode: int) -> EpisodeSpec | None:
    """The spec of ``episode`` from the simulator's status (``keys.sim_status``) while it runs, else None (and a log
    line why).

    For a process that sees an episode's messages but missed its START event: it joined late, or its subscription
    reached the simulator only after START went out. Blocks for up to ``STATUS_TIMEOUT_S``: call it from a main
    loop, never from a Zenoh callback.
    """
    try:
        # The read-only status key, not sim/control: access control lets only the orchestrator use that one.
        payload = bus.request(
            keys.sim_status(run_id), codec.encode(ControlRequest(action="status")), timeout_s=STATUS_TIMEOUT_S
        )
        reply = codec.decode(payload, ControlReply) if payload is not None else None
    except (BusError, codec.DecodeError) as error:
        log.warning("cannot ask the simulator for episode %d's spec: %s", episode, error)
        return None
    if reply is None or reply.episode != episode or reply.spec is None:
        log.warning("missed the start of episode %d, and the simulator no longer runs it", episode)
        return None
    log.info("missed the start of episode %d: its spec comes from the simulator's status", episode)
    return reply.spec


def start_event(run_id: str, episode: int, spec: EpisodeSpec) -> EpisodeEvent:
    """The START event of an episode, exactly as the simulator publishes it."""
    return EpisodeEvent(
        header=Header(run_id=run_id, episode=episode, seq=0, stamp_ns=0), kind=EventKind.START, spec=spec
    )


def brain_event(event: EpisodeEvent) -> BrainEvent | None:
    """What brains are told of ``event`` on ``keys.brain_events``: a START's seed, mode and whether its frames are
    perturbed, an END; None for the events brains are not told (laps, switches)."""
    if event.kind == EventKind.START and event.spec is not None:
        spec = event.spec
        return BrainEvent(
            header=event.header, kind=event.kind, seed=spec.seed, realtime=spec.realtime, perturbed=bool(spec.noise)
        )
    if event.kind == EventKind.END:
        return BrainEvent(header=event.header, kind=event.kind)
    return None


class _Starts(Generic[Start]):
    """The START of each episode of a run, read from its events as they arrive (the simulator publishes START before
    the episode's first frame, on the same session, so it normally arrives first); ``_start`` waits briefly for it
    otherwise (a process that joined late never sees it and gets None)."""

    def __init__(self, bus: Bus, key: str, message_type: type, *, on_event: Callable[[Any], None] | None = None):
        """``on_event(event)`` runs on the bus's callback thread as each event arrives. Zenoh runs each subscription's
        callbacks on a thread of its own, so it may run before or after frames that were published after the event:
        use it to let more in early, never to shut something out."""
        self._inbox = Inbox()
        hook = None if on_event is None else lambda received: on_event(received.message)
        bus.subscribe(key, message_type, inbox=self._inbox, on_message=hook)
        self._starts: dict[int, Start] = {}

    def _start(self, episode: int, *, wait_s: float) -> Start | None:
        deadline = time.monotonic() + wait_s
        while episode not in self._starts:
            remaining = deadline - time.monotonic()
            received = self._inbox.recv(timeout_s=max(0.0, min(0.05, remaining)))
            if received is not None:
                self._take(received.message)
            elif remaining <= 0:
                break
        return self._starts.pop(episode, None)  # each is handed out once

    def _take(self, event: Any) -> None:
        """Keep ``event`` when it is a START (each subclass says what of it it keeps)."""
        if event.kind == EventKind.START and (start := self._start_of(event)) is not None:
            self._starts[event.header.episode] = start

    @staticmethod
    def _start_of(event: Any) -> Start | None:
        return event  # BrainStarts: the event itself


class EpisodeStarts(_Starts[EpisodeSpec]):
    """The spec of each episode of a run, from the START events of ``keys.events`` (for the stack's own processes:
    an untrusted brain may not read them)."""

    def __init__(self, bus: Bus, run_id: str, *, on_event: Callable[[EpisodeEvent], None] | None = None):
        super().__init__(bus, keys.events(run_id), EpisodeEvent, on_event=on_event)

    @staticmethod
    def _start_of(event: EpisodeEvent) -> EpisodeSpec | None:
        return event.spec

    def spec(self, episode: int, *, wait_s: float = 0.5) -> EpisodeSpec | None:
        """The spec of ``episode``, or None if its START is not seen within ``wait_s``."""
        return self._start(episode, wait_s=wait_s)


class BrainStarts(_Starts[BrainEvent]):
    """The START of each episode of a run as brains are told it (``keys.brain_events``: seed and mode, no
    conditions)."""

    def __init__(self, bus: Bus, run_id: str, *, on_event: Callable[[BrainEvent], None] | None = None):
        super().__init__(bus, keys.brain_events(run_id), BrainEvent, on_event=on_event)

    def start(self, episode: int, *, wait_s: float = 0.5) -> BrainEvent | None:
        """The START of ``episode``, or None if it is not seen within ``wait_s``."""
        return self._start(episode, wait_s=wait_s)


def running_runs(bus: Bus, *, timeout_s: float = 1.0) -> set[str]:
    """The runs that have a simulator alive on this bus (from their liveliness tokens)."""
    runs = set()
    for key in bus.alive_now(keys.alive_everywhere(), timeout_s=timeout_s):
        try:
            run_id, role, _ = keys.parse_alive(key)
        except ValueError:
            continue
        if role == "simulator":
            runs.add(run_id)
    return runs
