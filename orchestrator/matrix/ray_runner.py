"""Matrices on a Ray cluster: ``drivebench matrix FILE --ray ADDRESS``.

The driver (this process) plans the matrix, keeps ``results.sqlite``, the resume semantics, the progress display and
the report exactly as a local run (:class:`orchestrator.matrix.runner.MatrixRunner`); only the dispatch differs: one
loop (:meth:`RayMatrixRunner._dispatch`) over a pool of episode slots or of tasks.

Warm stacks (the default): each episode slot of the cluster is one long-lived Ray actor (:class:`EpisodeSlot`) that
keeps a stack alive across the episodes the driver gives it, one at a time, as a local worker's warm lane does
(:mod:`orchestrator.matrix.executor`, whose episode executor both run: brain hosts replaced only when an episode
names other brains, a stack that failed an episode replaced). The driver gives a slot, when one is waiting, an
episode with the brains its stack runs. Each episode is a streaming call on the actor (:meth:`EpisodeSlot.drive`)
that yields what a task does (below).

``--fresh-stacks``: every pending episode becomes one Ray task (:func:`run_episode_task`) that, on whichever node Ray
places it:

- starts the episode's own stack: a Zenoh router on a free loopback port of that node, simulator, noise injector,
  brain(s), scorer and, with ``--record``, a recorder, every process in one new process group;
- enforces the wall-clock guard inside the task (the stack's own guard, and a watchdog above it);
- always kills its process group before it returns (grandchildren included);
- returns the result row, the node it ran on and the episode folder's small files (score, config, trajectory,
  logs). Recordings are written straight to ``--artifacts DIR``, a folder every node mounts: never through Ray's
  object store.

Placement: each task or slot asks for one ``episode_slot`` (a custom resource every worker node declares:
``ray start --resources '{"episode_slot": 2}'``) plus any ``--ray-resource NAME=AMOUNT`` (a GPU share for a neural
brain). Before anything is submitted, a demand that no node can meet fails at once with one line (Ray itself would
wait forever). At most as many tasks as the cluster has slots are in flight, so the progress lanes are episodes that
run, not a queue.

Failures are typed. A task or slot lost with its node or its worker process (``NodeDiedError``,
``WorkerCrashedError``, ``ActorDiedError``, ...) has its episode submitted again, elsewhere if Ray can, at most
``--node-retries`` times; each lost attempt is recorded in the episode's row (``lost_attempts``), and only the attempt
that finishes is a result, so nothing is counted twice. A lost slot is dropped and a new one started when the cluster
has room. An episode that failed on its own (a brain died, off track, the time limit, the wall-clock guard) comes back
as a result like on a local run and is never retried; on a slot, its stack is replaced before the next episode.
Ctrl-C stops every slot's episode, kills its stack's process group and then the actor.
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import os
import re
import shutil
import signal
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from orchestrator.matrix.executor import EpisodeExecutor, RunOptions, WorkerState
from orchestrator.matrix.load import Matrix, PlannedEpisode
from orchestrator.matrix.ray_items import LiveItem, OutcomeItem, StreamItem, TaskError, next_item
from orchestrator.matrix.ray_options import (
    ClusterError,
    RayOptions,
    alive_nodes,
    capacity,
    connect,
    import_ray,
    node_label,
    slots_of,
    task_resources,
)
from orchestrator.matrix.results import EpisodeResult, LostAttempt, ResultStore
from orchestrator.matrix.runner import MatrixProgress, MatrixRunner
from orchestrator.stack.failures import Failure, FailureKind

log = logging.getLogger("drivebench.ray")

RECORDING_NAME = "recording.mcap"
SMALL_FILE_BYTES = 4 * 1024 * 1024  # a log longer than this comes back as its last 4 MiB
WATCHDOG_SLACK_S = 60.0  # above the stack's own guards: start-up, the episode, the recorder's stop grace
POLL_S = 0.25
LIVE_PERIOD_S = 0.5  # how often a running episode sends its live metrics to the driver
SLOT_CLOSE_S = 30.0  # how long the driver waits for episode slots to close their stacks
SLOT_START_FAILURES = 5  # slots that die starting, in a row, before the matrix ends with the reason


# -- the driver --


class RayMatrixRunner(MatrixRunner):
    """A :class:`MatrixRunner` whose episodes run as Ray tasks; results, resume and progress are the local ones."""

    def __init__(self, matrix: Matrix, out_dir: Path, options: RunOptions, *, ray_options: RayOptions, on_change=None):
        super().__init__(matrix, out_dir, options, on_change=on_change)
        self.ray_options = ray_options
        self._capacity = 1

    def run(self) -> MatrixProgress:
        connect(self.ray_options.address)
        self._capacity = capacity(self.ray_options.resources)  # before anything is submitted: fail at once
        return super().run()

    def _lanes(self) -> int:
        return self._capacity

    def _dispatch(self, todo: list[PlannedEpisode], store: ResultStore, progress: MatrixProgress) -> None:
        """Run ``todo`` on the cluster, each result through :meth:`_finish`: one loop for both kinds of worker, an
        episode slot per warm stack (:class:`_Slots`) or, with ``--fresh-stacks``, a task per episode
        (:class:`_Tasks`). A lost episode goes back to ``waiting`` (:meth:`_collect`)."""
        ray = import_ray()
        shared = dataclasses.replace(self.matrix, text="", episodes=())  # what a node needs: name and shadows
        pool: _Slots | _Tasks = (_Tasks if self.options.fresh_stacks else _Slots)(driver=self, shared=shared)
        waiting = collections.deque((episode, ()) for episode in todo)
        running: dict[Any, _Running] = {}  # by its ObjectRefGenerator
        free_lanes = list(range(len(progress.workers)))
        try:
            while waiting or running:
                self._submit(pool, waiting=waiting, running=running, free_lanes=free_lanes, progress=progress)
                starting = pool.starting()
                ready, _ = ray.wait([*running, *starting], num_returns=1, timeout=POLL_S)
                for ref in ready:  # a slot that came up, or a stream's next item: live metrics, outcome or error
                    if ref in starting:
                        pool.started(starting[ref])
                        continue
                    entry = running[ref]
                    item = self._ended(ref, entry, running=running, progress=progress, free_lanes=free_lanes)
                    if item is None:
                        continue
                    result = self._collect(item, entry, waiting, node=pool.ended(entry, item))
                    if result is not None:
                        pool.landed(entry, result)
                        self._finish(result, store, progress)
                self._on_change(progress)
        except BaseException:
            self.stop()
            pool.abort(running)  # Ctrl-C, SIGTERM: stop every episode and kill its processes
            raise
        pool.close()

    def _submit(
        self, pool: _Slots | _Tasks, *, waiting: collections.deque, running: dict, free_lanes: list, progress
    ) -> None:
        """Waiting episodes to the pool, while a lane of the display is free and the pool has room."""
        if waiting and free_lanes:
            pool.grow(waiting=len(waiting), in_flight=len(running))
        while waiting and free_lanes:
            submitted = pool.submit(waiting, in_flight=len(running), lane=free_lanes[0])
            if submitted is None:
                return
            stream, entry = submitted
            running[stream] = entry
            free_lanes.pop(0)
            with progress.lock:
                progress.workers[entry.lane].episode, progress.workers[entry.lane].live = entry.episode, None

    def _ended(
        self, stream, entry: _Running, *, running: dict, progress: MatrixProgress, free_lanes: list[int]
    ) -> OutcomeItem | TaskError | None:
        """Read a ready stream's next item: live metrics go to its lane's display (None: it runs on); an outcome or
        an error ends it, and its lane is free again."""
        item = next_item(stream)
        if isinstance(item, LiveItem):
            from protocol import codec
            from protocol.messages import LiveMetrics

            with progress.lock:
                progress.workers[entry.lane].live = codec.decode(item.data, LiveMetrics)
            return None
        del running[stream]
        with progress.lock:
            progress.workers[entry.lane].episode, progress.workers[entry.lane].live = None, None
        free_lanes.append(entry.lane)
        return item

    def window(self) -> int:
        """Tasks in flight: the cluster's slots now (nodes come and go), at least one."""
        try:
            return max(1, sum(slots_of(node, self.ray_options.resources) for node in alive_nodes()))
        except Exception:  # a GCS hiccup must not end the matrix; keep going one at a time
            return 1

    def artifacts_text(self) -> str | None:
        return None if self.ray_options.artifacts is None else str(self.ray_options.artifacts)

    def _collect(
        self, item: OutcomeItem | TaskError, running: _Running, waiting: collections.deque, *, node: str | None = None
    ) -> EpisodeResult | None:
        """The result of a finished task; None when its node (``node`` when known) was lost and it is submitted
        again."""
        episode, lost = running.episode, running.lost
        if isinstance(item, OutcomeItem):
            return self._land(episode, item, lost)
        error = item.error
        if isinstance(error, _lost_errors()):
            attempt = LostAttempt(node=node or _node_in(error), error=f"{type(error).__name__}: {_first_line(error)}")
            lost = (*lost, attempt)
            log.warning("episode %s: attempt %d lost (%s)", episode.key, len(lost), attempt.error)
            if len(lost) <= self.ray_options.node_retries:
                waiting.appendleft((episode, lost))
                return None
            return self._lost_result(episode, lost)
        if isinstance(error, (import_ray().exceptions.RayError, RuntimeError)):  # the task broke, not the episode
            return self._lost_result(
                episode, lost, failure=Failure(FailureKind.ERROR, f"{type(error).__name__}: {_first_line(error)}")
            )
        raise error

    def _land(self, episode: PlannedEpisode, outcome: OutcomeItem, lost: tuple[LostAttempt, ...]) -> EpisodeResult:
        """A task's outcome into the output folder: its small files, its row with the node and lost attempts."""
        result = outcome.result
        folder = self.out_dir / "episodes" / f"{episode.index:04d}"
        if not _same_folder(self.ray_options.artifacts, self.out_dir):
            if folder.exists():
                shutil.rmtree(folder)
            for relative, data in outcome.files.items():
                path = folder / relative
                path.parent.mkdir(parents=True, exist_ok=True)
                path.write_bytes(data)
        recording = result.recording
        if recording is not None and self.ray_options.artifacts is not None:
            recording = self._relative_or_absolute(self.ray_options.artifacts / recording)
        return dataclasses.replace(result, recording=recording, lost_attempts=lost)

    def _relative_or_absolute(self, path: Path) -> str:
        try:
            return str(path.resolve().relative_to(self.out_dir.resolve()))
        except ValueError:
            return str(path.resolve())

    def _lost_result(
        self, episode: PlannedEpisode, lost: tuple[LostAttempt, ...], *, failure: Failure | None = None
    ) -> EpisodeResult:
        now = time.time()
        if failure is None:
            failure = Failure(FailureKind.NODE_DIED, f"lost {len(lost)} time(s), last: {lost[-1].error}")
        return EpisodeResult.of(
            episode,
            status="failed",
            run_id="-",
            started_at=now,
            ended_at=now,
            failure=failure,
            node=lost[-1].node if lost else None,
            lost_attempts=lost,
        )


def _lost_errors() -> tuple[type, ...]:
    """Ray's errors for a task lost with its node or worker process (infrastructure, not the episode)."""
    exceptions = import_ray().exceptions
    names = (
        "NodeDiedError",
        "WorkerCrashedError",
        "ObjectLostError",
        "LocalRayletDiedError",
        "OutOfMemoryError",
        "TaskUnschedulableError",
        "RaySystemError",
        "ActorDiedError",  # an episode slot's actor, with its node or its process
        "ActorUnavailableError",  # what a slot's stream raises first when its node goes (before the node is dead)
    )
    return tuple(getattr(exceptions, name) for name in names if hasattr(exceptions, name))


def _kill(actor) -> None:
    """End an episode slot's actor now (its stack's processes watch their parent and go with it)."""
    ray = import_ray()
    try:
        ray.kill(actor, no_restart=True)
    except (ray.exceptions.RayError, ValueError) as error:  # already gone with its node
        log.debug("killing an episode slot: %s", error)


def _first_line(error: BaseException) -> str:
    text = str(error).strip()
    return text.splitlines()[0][:300] if text else ""


def _node_in(error: BaseException) -> str | None:
    """The node a Ray error names (``node id: <hex>`` / ``address: <ip>``), as :func:`node_label` writes it."""
    text = str(error)
    node_id = re.search(r"node(?:[ _]id)?[:=]?\s*([0-9a-f]{16,})", text, re.IGNORECASE)
    ip = re.search(r"(?:address|ip)[:=]?\s*([0-9]+(?:\.[0-9]+){3})", text, re.IGNORECASE)
    if node_id is None:
        return None
    return node_label(ip=ip.group(1) if ip else "?", node_id=node_id.group(1))


def _same_folder(artifacts: Path | None, out_dir: Path) -> bool:
    return artifacts is not None and artifacts.resolve() == out_dir.resolve()


@dataclasses.dataclass(frozen=True)
class _Running:
    """An episode in flight: its lost attempts so far, its lane of the progress display and, on a warm stack, its
    slot."""

    episode: PlannedEpisode
    lost: tuple[LostAttempt, ...]
    lane: int
    slot: _Slot | None = None


@dataclasses.dataclass
class _Slot:
    """The driver's view of one :class:`EpisodeSlot` actor."""

    actor: Any
    ready: Any  # the ObjectRef of its where(): resolved once the actor is up
    node: str | None = None  # its node, once up
    brains: list | None = None  # its stack's brain launches after its last episode (None: no stack, or unknown)
    busy: bool = False


class _Tasks:
    """``--fresh-stacks``: one Ray task, on a fresh stack, per episode; as many in flight as the cluster has slots."""

    def __init__(self, *, driver: RayMatrixRunner, shared: Matrix):
        ray = import_ray()
        self._driver, self._shared = driver, shared
        self._task = ray.remote(run_episode_task).options(
            **task_resources(driver.ray_options.resources),
            max_retries=0,  # node deaths: retried by the driver, recorded
            name="drivebench-episode",
        )

    def grow(self, *, waiting: int, in_flight: int) -> None:
        """Tasks need no workers started beforehand."""

    def submit(self, waiting: collections.deque, *, in_flight: int, lane: int) -> tuple[Any, _Running] | None:
        """The next waiting episode as a task, in ``lane``: its stream and its entry (None: the cluster is full)."""
        if in_flight >= self._driver.window():
            return None
        episode, lost = waiting.popleft()
        options, artifacts = self._driver.options, self._driver.artifacts_text()
        stream = self._task.remote(matrix=self._shared, episode=episode, options=options, artifacts=artifacts)
        return stream, _Running(episode, lost, lane)

    def starting(self) -> dict:
        return {}

    def started(self, slot: _Slot) -> None:
        raise AssertionError("tasks have no slots")

    def ended(self, entry: _Running, item: OutcomeItem | TaskError) -> str | None:
        return None  # the node of a lost task: what its error names

    def landed(self, entry: _Running, result: EpisodeResult) -> None:
        pass

    def abort(self, running: dict) -> None:
        for stream in running:  # stop them now (force: a plain cancel waits for a sleeping task)
            import_ray().cancel(stream, force=True)

    def close(self) -> None:
        pass


class _Slots:
    """Warm stacks: episodes go to long-lived :class:`EpisodeSlot` actors, one at a time each, an episode with the
    brains a slot's stack runs first. A slot lost with its node is dropped (its episode retried as a task's is) and
    another started when the cluster has room."""

    def __init__(self, *, driver: RayMatrixRunner, shared: Matrix):
        ray = import_ray()
        self._driver, self._shared = driver, shared
        # stop() runs in its own group, beside a running drive() (Ray takes the groups here, not in options()).
        self._make = ray.remote(concurrency_groups={"control": 1})(EpisodeSlot).options(
            **task_resources(driver.ray_options.resources),
            max_restarts=0,  # node deaths: its episode is retried by the driver, recorded; a new slot replaces it
            max_task_retries=0,
        )
        self.slots: list[_Slot] = []
        self._start_failures = 0  # slots that died starting, in a row

    def grow(self, *, waiting: int, in_flight: int) -> None:
        """Start slots up to the cluster's slots now (nodes come and go), no more than the episodes left."""
        if waiting <= sum(1 for slot in self.slots if not slot.busy):
            return
        target = min(self._driver.window(), waiting + in_flight)
        while len(self.slots) < target:
            actor = self._make.remote(
                matrix=self._shared, options=self._driver.options, artifacts=self._driver.artifacts_text()
            )
            self.slots.append(_Slot(actor=actor, ready=actor.where.remote()))

    def submit(self, waiting: collections.deque, *, in_flight: int, lane: int) -> tuple[Any, _Running] | None:
        """An episode for the first idle slot, in ``lane``: its stream and its entry (None: no slot is idle)."""
        slot = next((slot for slot in self.slots if slot.node is not None and not slot.busy), None)
        if slot is None:
            return None
        episode, lost = self._take(waiting, prefer=slot.brains)
        slot.busy = True
        return slot.actor.drive.remote(episode=episode), _Running(episode, lost, lane, slot)

    def _take(self, waiting: collections.deque, *, prefer: list | None) -> tuple[PlannedEpisode, tuple]:
        """The next waiting episode for a slot whose stack runs ``prefer``: one with the same launches first (as
        :meth:`JobQueue.take`); results do not depend on the order."""
        index = 0
        if prefer is not None:
            launches = self._driver.executor.launches
            index = next((i for i, (episode, _) in enumerate(waiting) if launches(episode) == prefer), 0)
        item = waiting[index]
        del waiting[index]
        return item

    def starting(self) -> dict:
        return {slot.ready: slot for slot in self.slots if slot.node is None}

    def started(self, slot: _Slot) -> None:
        """A slot answered: it takes episodes from now on; one that died starting is dropped (a few in a row: the
        slots cannot start at all, which ends the matrix with the reason)."""
        ray = import_ray()
        try:
            slot.node = ray.get(slot.ready)
            self._start_failures = 0
        except ray.exceptions.RayError as error:
            self._start_failures += 1
            self._drop(slot, why=f"it did not start: {type(error).__name__}: {_first_line(error)}")
            if self._start_failures > SLOT_START_FAILURES:
                raise ClusterError(f"episode slots do not start on the Ray cluster: {_first_line(error)}") from None

    def ended(self, entry: _Running, item: OutcomeItem | TaskError) -> str | None:
        """The slot is free again; one whose node, process or actor failed is never used again. Its node."""
        owner = entry.slot
        assert owner is not None  # every episode here runs on a slot
        owner.busy = False
        if isinstance(item, TaskError):
            self._drop(owner, why=f"{type(item.error).__name__}")
        return owner.node

    def landed(self, entry: _Running, result: EpisodeResult) -> None:
        assert entry.slot is not None
        entry.slot.brains = self._driver.executor.launches(entry.episode) if result.status == "done" else None

    def _drop(self, slot: _Slot, *, why: str) -> None:
        log.warning("episode slot on %s dropped (%s)", slot.node or "a node", why)
        self.slots.remove(slot)
        _kill(slot.actor)

    def abort(self, running: dict) -> None:
        """Stop every slot's episode and kill its stack's process group, then the actors themselves."""
        self._end_slots([slot.actor.stop.options(concurrency_group="control").remote() for slot in self._up()])

    def close(self) -> None:
        """The matrix is done: each slot closes its stack, then the actors go (their resources free at once)."""
        self._end_slots([slot.actor.close.remote() for slot in self._up()])

    def _up(self) -> list[_Slot]:
        return [slot for slot in self.slots if slot.node]

    def _end_slots(self, calls: list) -> None:
        if calls:
            import_ray().wait(calls, num_returns=len(calls), timeout=SLOT_CLOSE_S)
        for slot in self.slots:
            _kill(slot.actor)


# -- one episode, on a node --


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


__all__ = ["EpisodeSlot", "RayMatrixRunner", "run_episode_task"]
