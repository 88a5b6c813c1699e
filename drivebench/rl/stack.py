"""The stack under a Gymnasium environment: a local stack with no brain host (the environment is the brain), or a
running stack joined through its router.

Beside the launcher, not in it: :class:`EnvLocalStack` and :class:`EnvAttachedStack` add to ``LocalStack`` and
``AttachedStack`` only what an environment needs that ``run_episode`` does not give: start an episode without
waiting for its score, stop it, and say whether the stack still stands.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

from orchestrator.stack.attached import AttachedStack
from orchestrator.stack.failures import StackError, StackFailure
from orchestrator.stack.launcher import LocalStack
from protocol.bus import BusError, probe_router
from protocol.episode_spec import EpisodeSpec
from protocol.messages import ControlRequest

log = logging.getLogger("drivebench.rl")


class EnvStackMixin:
    """Episode control for an environment (mixed into both stacks below)."""

    def begin(self, spec: EpisodeSpec) -> int:
        """Start ``spec`` (this stack's driver token watches it); the episode's number. StackError when refused."""
        reply = self._start(spec)  # type: ignore[attr-defined]
        if not reply.ok:
            raise StackError(f"the simulator refused the episode: {reply.detail}")
        return reply.episode

    def stop_episode(self) -> None:
        """Ask the simulator to end the running episode (``stopped``); a no-op when none runs."""
        self._control(ControlRequest(action="stop"), attempts=1)  # type: ignore[attr-defined]

    def raise_failure(self) -> None:
        """Raise the stack's failure (a process died, a token vanished) as StackFailure; nothing when it stands."""
        failure = self._failure()  # type: ignore[attr-defined]
        if failure is not None:
            raise failure


@dataclass
class EnvLocalStack(EnvStackMixin, LocalStack):
    """A local stack (router, simulator, noise injector, scorer) with no brain host: the environment drives."""


@dataclass
class EnvAttachedStack(EnvStackMixin, AttachedStack):
    """A running stack joined as a client through its router: nothing is started or stopped here. It waits for
    the simulator, the noise injector and the scorer of ``run_id``; the environment brings the brain."""

    def start(self) -> None:
        self.run_dir.mkdir(parents=True, exist_ok=True)
        first = self.endpoint.split(",")[0].strip()
        try:
            probe_router(first, timeout_s=min(5.0, self.startup_timeout_s))
        except BusError as error:
            raise StackError(f"router={self.endpoint!r}: {error}") from None
        self._join_run(client=f"gym-{self.run_id}")
        log.info("attached to run %s on %s", self.run_id, self.endpoint)


def open_stack(
    *, router: str | None, run_id: str, run_dir: Path, startup_timeout_s: float, render_threads: int = 1
) -> EnvLocalStack | EnvAttachedStack:
    """A started stack: a new local one (``router`` None; its simulator renders on ``render_threads`` llvmpipe
    threads) or the run ``run_id`` behind ``router``. On any failure whatever was started is stopped again before
    StackError is raised."""
    stack: EnvLocalStack | EnvAttachedStack
    if router is None:
        stack = EnvLocalStack(
            run_id=run_id,
            run_dir=run_dir,
            brains=[],
            startup_timeout_s=startup_timeout_s,
            render_threads=render_threads,
        )
    else:
        stack = EnvAttachedStack(
            run_id=run_id, run_dir=run_dir, router_endpoint=router, startup_timeout_s=startup_timeout_s
        )
    try:
        stack.start()
    except BaseException:
        stack.close()
        raise
    return stack


__all__ = ["EnvAttachedStack", "EnvLocalStack", "StackError", "StackFailure", "open_stack"]
