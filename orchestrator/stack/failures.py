"""Typed stack failures: what went wrong with the stack during an episode (never what the brain did on the road).

One enum, :class:`FailureKind`, for the launcher, the runners and the results. Its ``<role>_died`` members follow
the process graph: every role of ``protocol/deploy/graph.py`` that runs a process has one (``tests/test_failures.py``
fails when a role is added without it), and :meth:`FailureKind.died` maps a role to its member, so nothing decides
on the text of a message. What the stack raises carries it: :class:`StackFailure` (an episode the stack failed, with
its kind), beside :class:`StackError` (the stack could not run) and :class:`EpisodeAborted` (the caller gave up).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from enum import StrEnum

import msgspec

from protocol.messages import EpisodeScore


class FailureKind(StrEnum):
    """Why the stack failed an episode. The value is what results store (in their own column) and tables show."""

    BRAIN_DIED = "brain_died"  # a brain process exited or lost its liveliness token during the episode
    SIMULATOR_DIED = "simulator_died"  # the simulator process exited or lost its token
    SCORER_DIED = "scorer_died"  # the scorer exited or lost its token
    NOISE_DIED = "noise_died"  # the noise injector exited or lost its token
    RECORDER_DIED = "recorder_died"  # the recorder exited (the episode is still scored; its recording is incomplete)
    ROUTER_DIED = "router_died"  # the router went away: every process lost its link at once
    VIZ_DIED = "viz_died"  # the live view exited
    ROS2_BRIDGE_DIED = "ros2_bridge_died"  # the ROS 2 bridge exited (drivebench run --ros2)
    START_FAILED = "start_failed"  # the stack did not come up, or the simulator refused the episode
    WALL_TIMEOUT = "wall_timeout"  # no score within the wall-clock guard (a hung episode)
    # A sandboxed brain (orchestrator.stack.sandbox) that met its sandbox: a resource limit it went past (memory,
    # processes, CPU seconds, file size, output), an operation the sandbox refused (a write outside its scratch,
    # the network), or a host that did not come up within its start timeout (a brain slow in __init__).
    LIMIT_EXCEEDED = "limit_exceeded"
    SANDBOX_VIOLATION = "sandbox_violation"
    BRAIN_START_TIMEOUT = "brain_start_timeout"
    NODE_DIED = "node_died"  # (--ray) the cluster node running it died, more often than the retries allow
    ERROR = "error"  # anything else, with its message

    @classmethod
    def died(cls, role: str) -> FailureKind:
        """The failure a dead or vanished process of graph role ``role`` means for its episode (``error`` for a
        role without one)."""
        try:
            return cls(f"{role}_died")
        except ValueError:
            return cls.ERROR


@dataclass(frozen=True)
class Failure:
    """One failed episode's failure: its kind, and the detail a person reads (never parsed)."""

    kind: FailureKind
    detail: str

    def __str__(self) -> str:
        return f"{self.kind}: {self.detail}"  # the form a person reads (results store kind and detail apart)


class StackError(RuntimeError):
    """The stack could not run: a process died, did not come up, or refused the episode. One line, says which."""


class StackFailure(StackError):
    """An episode the stack failed, typed for results (``kind``, a :class:`FailureKind`).

    ``score`` is the episode's score when the scorer still produced one (a brain killed mid-episode ends it with
    ``brain_lost`` and is scored), else None.
    """

    def __init__(self, kind: FailureKind, detail: str, *, score: EpisodeScore | None = None):
        super().__init__(detail)
        self.kind = kind
        self.score = score
        self.detected_at_s = time.time()  # wall clock (Unix time) when the stack noticed it

    @property
    def failure(self) -> Failure:
        return Failure(self.kind, str(self))

    def record(self, *, run_id: str, episode: int | None = None) -> dict:
        """The failure as a JSON-able record, beside scores in the same family (``--json``, ``failure.json``)."""
        return {
            "run_id": run_id,
            "episode": episode,
            "failure": self.kind,
            "detail": str(self),
            "detected_at_s": round(self.detected_at_s, 3),
            "score": None if self.score is None else msgspec.to_builtins(self.score),
        }


class EpisodeAborted(StackError):
    """The caller asked to abandon the running episode (Ctrl-C of a matrix): nothing about it is a result."""
