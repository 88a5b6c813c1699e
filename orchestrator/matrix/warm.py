"""Warm stacks: a matrix worker keeps one stack across episodes and changes only what an episode changes.

The simulator, the noise injector and the scorer already take everything an episode changes from its spec (circuit,
direction, world, camera, renderer, noise, limits, seed): the simulator builds (or takes from its scene cache) the
episode's scene, the noise injector builds the episode's pipeline seeded from the spec, and the scorer starts a new
scorer at each START. So a warm stack changes only its brain hosts, and only when the next episode names other brains
(another brain, other weights or options, other shadows): a host whose launch is the same stays and resets its brain
with the episode's seed at the episode's first frame. A recorder (``--record``) is started for each episode and
stopped after it, so that each episode's file is closed, complete and indexed before the next episode begins.

A stack that failed an episode (any typed failure, a ``brain_lost`` ending, a recorder that died), or one of whose
processes has died between episodes, is closed and a fresh one started for the next episode. ``--fresh-stacks``
turns all of this off (one new stack per episode, as before warm stacks).
"""

from __future__ import annotations

import logging
import threading
import uuid
from collections.abc import Callable
from pathlib import Path

from orchestrator.matrix.load import PlannedEpisode
from orchestrator.stack.launcher import BrainLaunch, LocalStack

log = logging.getLogger("drivebench.matrix")


class JobQueue:
    """The episodes still to run, shared by the workers. A worker takes, when there is one, an episode with the
    brains its warm stack already runs (so a brain host is replaced only when no such episode is left); results do
    not depend on the order (every episode is seeded from its own spec)."""

    def __init__(self, episodes: list[PlannedEpisode], *, launches: Callable[[PlannedEpisode], list[BrainLaunch]]):
        self._episodes = list(episodes)
        self._launches = launches
        self._lock = threading.Lock()

    def take(self, *, prefer: list[BrainLaunch] | None = None) -> PlannedEpisode | None:
        """The next episode (one whose launches equal ``prefer`` first), or None when none is left."""
        with self._lock:
            if not self._episodes:
                return None
            index = 0
            if prefer is not None:
                index = next((i for i, e in enumerate(self._episodes) if self._launches(e) == prefer), 0)
            return self._episodes.pop(index)


class WarmLane:
    """One worker's warm stack: started at its first episode, reused while it stays healthy, replaced after a
    failure. ``stacks_dir`` holds one folder per stack (its logs), named by its run id."""

    def __init__(self, *, lane: int, stacks_dir: Path, make_stack: Callable[..., LocalStack], settings: dict):
        self.lane = lane
        self.stacks_dir = stacks_dir
        self._make_stack = make_stack
        self._settings = settings  # router_endpoint, startup_timeout_s: the same for every stack of the lane
        self.stack: LocalStack | None = None
        self.started = 0  # stacks started by this lane
        self.episodes_on_stack = 0  # episodes run on the current stack

    @property
    def brains(self) -> list[BrainLaunch] | None:
        """The brain launches of the running stack (None: no stack yet)."""
        return None if self.stack is None else list(self.stack.brains)

    def stack_for(self, launches: list[BrainLaunch]) -> LocalStack:
        """A running stack with exactly ``launches`` as its brain hosts; StackError when it cannot come up (the lane
        then has no stack, and the next episode starts a new one)."""
        if self.stack is not None and (failure := self.stack.failure_now()) is not None:
            self.retire(f"a process died between episodes: {failure}")
        if self.stack is None:
            run_id = f"w{self.lane}-{uuid.uuid4().hex[:6]}"
            stack = self._make_stack(
                run_id=run_id, run_dir=self.stacks_dir / run_id, brains=list(launches), **self._settings
            )
            self.stack, self.episodes_on_stack = stack, 0
            self.started += 1
            try:
                stack.start()
            except BaseException:
                self.retire("it did not come up")
                raise
            return stack
        if self.stack.brains != launches and any(
            launch.sandbox is not None for launch in [*self.stack.brains, *launches]
        ):
            # A sandboxed brain's router lets only the brains it started with publish commands: a stack of its own.
            self.retire("its brain hosts change, and a sandboxed one has a stack of its own")
            return self.stack_for(launches)
        if self.stack.brains != launches:
            try:
                kept, started = self.stack.set_brains(launches)
            except BaseException:
                self.retire("a brain host did not come up")
                raise
            log.info("lane %d: brain hosts kept %d, started %d", self.lane, kept, started)
        return self.stack

    def after_episode(self, *, failed: bool) -> None:
        """Count the episode; a stack that failed it, or whose recorder died, is not reused."""
        self.episodes_on_stack += 1
        stack = self.stack
        if stack is None:
            return
        if failed:
            self.retire("it failed an episode")
        elif stack.recording_failure is not None:
            self.retire("its recorder died")

    def retire(self, why: str) -> None:
        """Close the lane's stack; the next episode starts a new one."""
        if self.stack is None:
            return
        log.info("lane %d: replacing stack %s (%s)", self.lane, self.stack.run_id, why)
        stack, self.stack = self.stack, None
        stack.close()

    def close(self) -> None:
        if self.stack is not None:
            stack, self.stack = self.stack, None
            stack.close()


def log_marks(stack: LocalStack) -> dict[Path, int]:
    """Where each of the stack's logs ends now (bytes): an episode's lines start there."""
    return {child.log_path: _size(child.log_path) for child in stack.children}


def copy_episode_logs(stack: LocalStack, marks: dict[Path, int], folder: Path) -> None:
    """Each process log's lines since ``marks`` (all of it for a process started since) into ``folder``, under the
    log's own name: an episode's folder holds its own logs, as with fresh stacks; the stack's folder keeps them all."""
    folder.mkdir(parents=True, exist_ok=True)
    for child in stack.children:
        try:
            with child.log_path.open("rb") as log_file:
                log_file.seek(marks.get(child.log_path, 0))
                (folder / child.log_path.name).write_bytes(log_file.read())
        except OSError as error:
            log.warning("could not copy %s for the episode: %s", child.log_path, error)


def _size(path: Path) -> int:
    try:
        return path.stat().st_size
    except OSError:
        return 0


__all__ = ["JobQueue", "WarmLane", "copy_episode_logs", "log_marks"]
