"""Timestamps of every message a process puts on and takes off the bus, for measuring each hop of a step.

Off unless ``DRIVEBENCH_TRACE_DIR`` names a folder. Then each :class:`~protocol.bus.Bus` records, per message,
``time.monotonic_ns()`` (one clock for every process of a machine) at four points, and writes them when it closes to
``<folder>/<bus name>-<pid>.trace``, one ``NS EVENT KEY EPISODE SEQ`` line each:

  ``put``       about to hand the encoded message to Zenoh (the publisher's side)
  ``sent``      Zenoh's put returned
  ``arrived``   the subscriber's callback started (the bytes are in this process)
  ``decoded``   the message is decoded and queued for the process's loop
  ``taken``     the loop took it from its queue

SEQ is the frame a message belongs to: a frame's or pose's own ``header.seq``, a command's ``frame_seq``; a
message without a header gets -1. ``benchmarks/closed_loop.py`` joins the files of one stack into the time of each
hop (:func:`read_traces`). Recording costs a tuple append per event; at most ``MAX_EVENTS`` are kept per process.
"""

from __future__ import annotations

import logging
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from protocol import environment

log = logging.getLogger("drivebench.trace")

TRACE_DIR_ENV = environment.TRACE_DIR.name
MAX_EVENTS = 1_000_000
EVENTS = ("put", "sent", "arrived", "decoded", "taken")


@dataclass(frozen=True)
class TraceEvent:
    """One traced moment of one message in one process."""

    process: str  # the bus name of the process that recorded it
    ns: int  # time.monotonic_ns()
    event: str  # one of EVENTS
    key: str
    episode: int
    seq: int


def frame_of(message: Any) -> tuple[int, int]:
    """(episode, frame seq) a message belongs to; (-1, -1) without a header."""
    header = getattr(message, "header", None)
    if header is None:
        return -1, -1
    seq = getattr(message, "frame_seq", None)
    return header.episode, header.seq if seq is None else seq


class Tracer:
    """The trace of one process; every method is a no-op when tracing is off."""

    def __init__(self, name: str, *, folder: str | None = None) -> None:
        folder = (environment.TRACE_DIR.value() or None) if folder is None else folder
        self.on = bool(folder)
        self._path = Path(folder) / f"{name}-{os.getpid()}.trace" if folder else None
        self._events: list[tuple[int, str, str, int, int]] = []

    def mark(self, event: str, key: str, message: Any = None, *, ns: int | None = None) -> None:
        """Record ``event`` of ``message`` on ``key`` now (or at ``ns``, a time.monotonic_ns() taken earlier)."""
        if not self.on or len(self._events) >= MAX_EVENTS:
            return
        episode, seq = frame_of(message)
        self._events.append((time.monotonic_ns() if ns is None else ns, event, key, episode, seq))

    def write(self) -> None:
        """Write the events recorded so far (called when the bus closes)."""
        if self._path is None or not self._events:
            return
        lines = [f"{ns} {event} {key} {episode} {seq}\n" for ns, event, key, episode, seq in self._events]
        try:
            self._path.write_text("".join(lines))
        except OSError as error:  # a trace must never keep a process from closing its bus
            log.warning("cannot write the trace %s (%s): %s", self._path, TRACE_DIR_ENV, error.strerror or error)
        self._events.clear()


def read_traces(folder: Path) -> list[TraceEvent]:
    """Every event of every ``*.trace`` file in ``folder``, in time order."""
    events = []
    for path in sorted(Path(folder).glob("*.trace")):
        process = path.stem.rsplit("-", 1)[0]
        for line in path.read_text().splitlines():
            ns, event, key, episode, seq = line.split()
            events.append(TraceEvent(process, int(ns), event, key, int(episode), int(seq)))
    events.sort(key=lambda e: e.ns)
    return events
