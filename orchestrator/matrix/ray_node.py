"""The node side of a matrix on a Ray cluster (``drivebench matrix FILE --ray ADDRESS``): what runs where Ray places
it, one episode at a time. :class:`EpisodeSlot`, a long-lived actor that keeps a warm stack across the episodes the
driver gives it, and :func:`run_episode_task` (``--fresh-stacks``), one task per episode on a stack of its own. Both
run their episodes through an :class:`~orchestrator.matrix.executor.EpisodeExecutor`, as a local worker does, with
every process of a stack in one process group, and stream typed items (:class:`LiveItem`, then an
:class:`OutcomeItem`) that the driver decides on by their type.
The driver, its dispatch loop and its retries are :mod:`orchestrator.matrix.ray_runner`.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
import signal
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

from orchestrator.matrix.executor import EpisodeExecutor, RunOptions, WorkerState
from orchestrator.matrix.load import Matrix, PlannedEpisode
from orchestrator.matrix.ray_options import node_label
from orchestrator.matrix.results import EpisodeResult
from orchestrator.stack.failures import Failure, FailureKind

RECORDING_NAME = "recording.mcap"
SMALL_FILE_BYTES = 4 * 1024 * 1024  # a log longer than this comes back as its last 4 MiB
WATCHDOG_SLACK_S = 60.0  # above the stack's own guards: start-up, the episode, the recorder's stop grace
LIVE_PERIOD_S = 0.5  # how often a running episode sends its live metrics to the driver


# -- what a task or a slot's drive() streams back to the driver --


@dataclasses.dataclass(frozen=True)
class LiveItem:
    """A stream item: a running episode's live metrics, encoded (:mod:`protocol.codec`, as on the bus)."""

    data: bytes


@dataclasses.dataclass(frozen=True)
class OutcomeItem:
    """A stream's last item: the episode's result and its small files (path relative to its folder -> bytes)."""

    result: EpisodeResult
    files: dict[str, bytes]


StreamItem = LiveItem | OutcomeItem


class _GroupStacks:
    """How a node's executor makes stacks: every process of one in a new process group, the last one kept so that
    whatever of its group is left can be killed (grandchildren included)."""

    def __init__(self) -> None:
        self.stack = None

    def make(self, **settings):
        from orchestrator.stack.launcher import LocalStack

        self.stack = LocalStack(one_group=True, **settings)
        return self.stack

    def kill_group(self) -> None:
        """SIGKILL whatever of the last stack's process group is left."""
        group = None if self.stack is None else self.stack.process_group
        if group is not None:
            try:
                os.killpg(group, signal.SIGKILL)
            except (ProcessLookupError, PermissionError):
                pass  # every member already gone


def _node_executor(
    *, matrix: Matrix, work: Path, options: RunOptions, node: str
) -> tuple[EpisodeExecutor, _GroupStacks]:
    """The episode executor of a Ray slot or task: its stacks in one process group each, rows naming ``node``."""
    stacks = _GroupStacks()
    executor = EpisodeExecutor(matrix=matrix, out_dir=work, options=options, node=node, make_stack=stacks.make)
    return executor, stacks


class EpisodeSlot:
    """One episode slot of a node as a long-lived Ray actor: it keeps a warm stack (:class:`WarmLane`, as a local
    matrix worker does) across the episodes the driver gives it, one at a time. Its router, its stacks' logs
    (``<work>/stacks/``) and, without artifacts, its scratch folder live as long as the actor."""

    def __init__(self, *, matrix: Matrix, options: RunOptions, artifacts: str | None):
        import ray

        from orchestrator.stack.launcher import free_loopback_port
        from protocol.bus import Bus, BusConfig

        context = ray.get_runtime_context()
        self.node = node_label(ip=ray.util.get_node_ip_address(), node_id=context.get_node_id())
        work = Path(artifacts) if artifacts is not None else Path(tempfile.mkdtemp(prefix="drivebench-slot-"))
        self._scratch = None if artifacts is not None else work
        self._executor, self._stacks = _node_executor(matrix=matrix, work=work, options=options, node=self.node)
        self._router = Bus(BusConfig(mode="router", listen=[f"tcp/127.0.0.1:{free_loopback_port()}"]), name="slot")
        self._lane = self._executor.warm_lane(lane=0, router_endpoint=self._router.config.listen[0])
        self._stopped = False

    def where(self) -> str:
        """This slot's node (:func:`node_label`); the driver gives episodes only to a slot that answered."""
        return self.node

    def drive(self, *, episode: PlannedEpisode) -> Iterator[StreamItem]:
        """One episode on the warm stack (a streaming method): the items :func:`run_episode_task` yields."""
        if self._stopped:
            raise RuntimeError("the episode slot was stopped")
        self._executor.go_on()  # a watchdog that stopped the episode before stopped that episode only

        def cleanup(*, abandoned: bool) -> None:
            if abandoned:  # its processes were killed: the next episode starts a new stack
                self._lane.retire("its episode was abandoned")

        items = _watched(
            executor=self._executor,
            stacks=self._stacks,
            episode=episode,
            node=self.node,
            run=lambda state: self._executor.run_warm(episode, lane=self._lane, state=state),
            cleanup=cleanup,
        )
        for item in items:
            if isinstance(item, OutcomeItem) and self._scratch is not None:  # its files travel in the item
                shutil.rmtree(self._scratch / "episodes" / f"{episode.index:04d}", ignore_errors=True)
            yield item

    def stop(self) -> None:
        """Ctrl-C on the driver (called beside a running ``drive``): abandon the episode, kill the stack's group."""
        self._stopped = True
        self._executor.stop()
        self._stacks.kill_group()

    def close(self) -> None:
        """The matrix is done: close the stack (after any running episode), the router and the scratch folder."""
        self._lane.close()
        self._router.close()
        if self._scratch is not None:
            shutil.rmtree(self._scratch, ignore_errors=True)


def run_episode_task(
    *, matrix: Matrix, episode: PlannedEpisode, options: RunOptions, artifacts: str | None
) -> Iterator[StreamItem]:
    """One episode on this node (a Ray generator task's body): ``{"live": <LiveMetrics, encoded>}`` twice a
    second while it drives (the driver's progress lanes), then ``{"result": EpisodeResult, "files": {path: bytes}}``.

    The episode folder is ``<artifacts>/episodes/<index>`` (recording included) or, without artifacts, a temporary
    folder removed before returning; ``files`` holds its small files (not the recording), paths relative to it.
    """
    import ray

    context = ray.get_runtime_context()
    node = node_label(ip=ray.util.get_node_ip_address(), node_id=context.get_node_id())
    work = Path(artifacts) if artifacts is not None else Path(tempfile.mkdtemp(prefix="drivebench-episode-"))
    scratch = None if artifacts is not None else work
    try:
        yield from _drive(matrix=matrix, episode=episode, options=options, node=node, work=work)
    finally:
        if scratch is not None:
            shutil.rmtree(scratch, ignore_errors=True)


def _drive(
    *, matrix: Matrix, episode: PlannedEpisode, options: RunOptions, node: str, work: Path
) -> Iterator[StreamItem]:
    """:func:`run_episode_task` in the folder ``work``: a fresh stack in one process group, under a watchdog."""
    from orchestrator.stack.launcher import free_loopback_port
    from protocol.bus import Bus, BusConfig

    executor, stacks = _node_executor(matrix=matrix, work=work, options=options, node=node)
    router = Bus(BusConfig(mode="router", listen=[f"tcp/127.0.0.1:{free_loopback_port()}"]), name="episode-router")

    def cleanup(*, abandoned: bool) -> None:  # the stack is closed or abandoned: kill whatever of its group is left
        stacks.kill_group()
        router.close()

    yield from _watched(
        executor=executor,
        stacks=stacks,
        episode=episode,
        node=node,
        run=lambda state: executor.run_fresh(episode, router_endpoint=router.config.listen[0], state=state),
        cleanup=cleanup,
    )


def _watched(
    *,
    executor: EpisodeExecutor,
    stacks: _GroupStacks,
    episode: PlannedEpisode,
    node: str,
    run: Callable[[WorkerState], EpisodeResult | None],
    cleanup: Callable[..., None],
) -> Iterator[StreamItem]:
    """Drive one episode with ``run`` in a thread under a watchdog: its live metrics twice a second, then the result
    and the episode folder's small files. ``cleanup(abandoned=...)`` runs before the result is sent (abandoned: the
    watchdog fired or the stream was closed, so the stack was stopped and its process group killed)."""
    from orchestrator.stack.launcher import wall_guard_s
    from protocol import codec

    guard_s = executor.options.startup_timeout_s + wall_guard_s(max_sim_seconds=episode.spec.max_sim_seconds)
    guard_s += WATCHDOG_SLACK_S
    fired = threading.Event()

    def watchdog() -> None:  # the stack's own guards failed to end it: abandon it and kill its processes
        fired.set()
        executor.stop()
        stacks.kill_group()

    timer = threading.Timer(guard_s, watchdog)
    timer.daemon = True
    started_at = time.time()
    state = WorkerState()
    outcome: dict = {}

    def drive() -> None:
        try:
            outcome["result"] = run(state)
        except BaseException as error:  # raised again in the task, where Ray reports it
            outcome["error"] = error

    thread = threading.Thread(target=drive, name="episode", daemon=True)
    try:
        timer.start()
        thread.start()
        sent = None
        while thread.is_alive():
            thread.join(timeout=LIVE_PERIOD_S)
            if state.live is not None and state.live is not sent:
                sent = state.live
                yield LiveItem(data=codec.encode(sent))
    finally:
        timer.cancel()
        abandoned = thread.is_alive() or fired.is_set()
        if thread.is_alive():  # the stream was closed (the task cancelled): abandon the episode
            executor.stop()
            stacks.kill_group()
        thread.join(timeout=10.0)
        cleanup(abandoned=abandoned)
    if "error" in outcome:
        raise outcome["error"]
    result = outcome.get("result")
    if result is None or fired.is_set():
        result = _timed_out(episode, node=node, started_at=started_at, guard_s=guard_s, result=result)
    yield OutcomeItem(result=result, files=_small_files(executor.out_dir / "episodes" / f"{episode.index:04d}"))


def _timed_out(
    episode: PlannedEpisode, *, node: str, started_at: float, guard_s: float, result: EpisodeResult | None
) -> EpisodeResult:
    failure = Failure(
        FailureKind.WALL_TIMEOUT, f"the episode's task ran past its {guard_s:.0f} s guard; its processes were killed"
    )
    if result is not None:
        return dataclasses.replace(result, status="failed", failure=failure)
    return EpisodeResult.of(
        episode,
        status="failed",
        run_id="-",
        started_at=started_at,
        ended_at=time.time(),
        failure=failure,
        node=node,
    )


def _small_files(folder: Path) -> dict[str, bytes]:
    """Every file of an episode folder but the recording, relative paths to bytes (a long log: its tail)."""
    files = {}
    for path in sorted(folder.rglob("*")) if folder.is_dir() else ():
        if not path.is_file() or path.name == RECORDING_NAME:
            continue
        size = path.stat().st_size
        with path.open("rb") as handle:
            if size > SMALL_FILE_BYTES:
                handle.seek(size - SMALL_FILE_BYTES)
            files[str(path.relative_to(folder))] = handle.read()
    return files


__all__ = ["EpisodeSlot", "LiveItem", "OutcomeItem", "StreamItem", "run_episode_task"]
