"""Putting a recording back on the bus: the recorded messages, on their keys, as their original wire bytes.

Each recorded message is rebuilt by the protocol's mapping (``protocol.mapping.recording``) and encoded by the
protocol's codec, so subscribers receive what the original publishers sent (byte for byte for raw-image recordings; JPEG
images come back decoded). ``run_id`` moves everything to another run: keys and headers both. Every key is
published reliably (blocking, never dropping): a replay exists to deliver all of it, unlike a live camera.

The brains' copy of the episode events (``keys.brain_events``) is not recorded: it is published again from each
replayed START and END, as the simulator publishes it, so a brain host fed by a replay is seeded as it was live.
"""

from __future__ import annotations

import sys
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import msgspec

from protocol import codec, keys
from protocol.bus import Bus, Publisher, Traffic
from protocol.episodes import brain_event
from protocol.messages import BrainEvent, EpisodeEvent, RunMessage
from recorder.reading import read_messages, recording_info


@dataclass(frozen=True)
class ReplayReport:
    counts: dict[str, int]  # messages published per key (the keys they were published on)
    wall_s: float
    span_s: float  # recording time covered

    @property
    def messages(self) -> int:
        return sum(self.counts.values())


def rebased(message: RunMessage, run_id: str) -> RunMessage:
    """The same message in another run."""
    return msgspec.structs.replace(message, header=msgspec.structs.replace(message.header, run_id=run_id))


SUBSCRIBER_WAIT_S = 2.0  # a replay with nobody listening starts this much later; one with listeners at once
DRAIN_S = 0.5  # after the last put, before the publishers and the session close


def replay(
    path: Path,
    bus: Bus,
    *,
    rate: float | None = 1.0,
    run_id: str | None = None,
    keys_glob: str | None = None,
    progress: bool = False,
) -> ReplayReport:
    """Publish a recording's messages in log-time order.

    rate: 1.0 = the recorded pace, 2.0 = twice as fast, None = as fast as the bus takes them.
    run_id: publish under this run id instead of the recorded one. keys_glob: only keys matching it (fnmatch on
    the recorded key, e.g. ``*/sim/*``).
    """
    if rate is not None and not rate > 0:
        raise ValueError(f"rate must be > 0, got {rate}")
    if run_id is not None:
        keys.check_name(run_id, what="run id")
    info = recording_info(path)
    publishers = _publishers(bus, [c.key for c in info.channels if c.bus_key], run_id)
    for_brains = _brain_publishers(bus, publishers)
    _wait_for_subscribers(publishers, timeout_s=SUBSCRIBER_WAIT_S)
    counts: Counter[str] = Counter()
    bar = _progress_bar(sum(c.messages for c in info.channels if c.bus_key), enabled=progress)
    started = time.monotonic()
    first_ns: int | None = None  # the first message's log time; None until one is read
    last_ns = 0
    for recorded in read_messages(path, keys_glob=keys_glob):
        first_ns = recorded.log_time_ns if first_ns is None else first_ns
        last_ns = recorded.log_time_ns
        if rate is not None:
            due = started + (recorded.log_time_ns - first_ns) / 1e9 / rate
            if (delay := due - time.monotonic()) > 0:
                time.sleep(delay)
        message = recorded.message if run_id is None else rebased(recorded.message, run_id)
        publisher = publishers[recorded.key]
        publisher.publish_bytes(codec.encode(message))
        counts[publisher.key] += 1
        if isinstance(message, EpisodeEvent) and (told := brain_event(message)) is not None:
            for_brains[recorded.key].publish(told)
            counts[for_brains[recorded.key].key] += 1
        bar.update(1)
    bar.close()
    if counts and any(publisher.has_subscribers() for publisher in publishers.values()):
        # The last puts may still sit in the session's transmission queue, which undeclaring and closing drop: a
        # full-speed replay lost its last frame on each key once in 20 runs without this.
        time.sleep(DRAIN_S)
    for publisher in [*publishers.values(), *for_brains.values()]:
        publisher.close()
    span = (last_ns - first_ns) / 1e9 if first_ns is not None else 0.0
    return ReplayReport(counts=dict(counts), wall_s=time.monotonic() - started, span_s=span)


def _wait_for_subscribers(publishers: dict[str, Publisher], *, timeout_s: float) -> bool:
    """Until some subscriber (a recorder, a viewer) matches a publisher, at most ``timeout_s``: a session that has
    just opened learns the subscriptions from its router a moment later, and a put before that reaches nobody."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if any(publisher.has_subscribers() for publisher in publishers.values()):
            return True
        time.sleep(0.01)
    return False


def _publishers(bus: Bus, recorded_keys: list[str], run_id: str | None) -> dict[str, Publisher]:
    """One publisher per recorded key, declared before the first message so none races its declaration."""
    return {
        key: bus.publisher(key if run_id is None else keys.with_run_id(key, run_id), msgspec.Struct, Traffic.EVENTS)
        for key in recorded_keys
    }


def _brain_publishers(bus: Bus, publishers: dict[str, Publisher]) -> dict[str, Publisher]:
    """For each recorded episode-events key, a publisher of the brains' copy in the run it is replayed to."""
    brains: dict[str, Publisher] = {}
    for recorded, publisher in publishers.items():
        run_id = keys.run_of_key(publisher.key)
        if publisher.key == keys.events(run_id):
            brains[recorded] = bus.publisher(keys.brain_events(run_id), BrainEvent, Traffic.EVENTS)
    return brains


def _progress_bar(total: int, *, enabled: bool):
    from tqdm import tqdm

    return tqdm(total=total, unit="msg", file=sys.stderr, disable=not enabled, dynamic_ncols=True, desc="replay")
