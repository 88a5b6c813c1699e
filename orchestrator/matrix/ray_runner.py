"""Matrices on a Ray cluster: ``drivebench matrix FILE --ray ADDRESS``.

The driver (this process) plans the matrix, keeps ``results.sqlite``, the resume semantics, the progress display and
the report exactly as a local run, through the same public functions (:func:`orchestrator.matrix.runner.run_matrix`
and its :class:`~orchestrator.matrix.runner.MatrixBook`); only the dispatch differs: one loop
(:meth:`RayMatrixRunner._dispatch`) over a pool of episode slots or of tasks.

The node side (the slot actor and the task, below) is :mod:`orchestrator.matrix.ray_node`.

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
import re
import shutil
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from orchestrator.matrix.executor import EpisodeExecutor, RunOptions
from orchestrator.matrix.load import Matrix, PlannedEpisode
from orchestrator.matrix.ray_node import EpisodeSlot, LiveItem, OutcomeItem, StreamItem, run_episode_task
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
from orchestrator.matrix.results import EpisodeResult, LostAttempt
from orchestrator.matrix.runner import MatrixBook, MatrixProgress, run_matrix
from orchestrator.stack.failures import Failure, FailureKind

log = logging.getLogger("drivebench.ray")

POLL_S = 0.25
SLOT_CLOSE_S = 30.0  # how long the driver waits for episode slots to close their stacks
SLOT_START_FAILURES = 5  # slots that die starting, in a row, before the matrix ends with the reason


# -- the driver --


class RayMatrixRunner:
    """Runs the planned episodes of one matrix into one output folder on a Ray cluster; results, resume and progress
    are a local run's (:func:`run_matrix`), as are ``on_change`` and ``on_result`` (:class:`MatrixRunner`)."""

    def __init__(
        self,
        matrix: Matrix,
        out_dir: Path,
        options: RunOptions,
        *,
        ray_options: RayOptions,
        on_change: Callable[[MatrixProgress], None] | None = None,
        on_result: Callable[[EpisodeResult, MatrixProgress], None] | None = None,
    ):
        self.matrix = matrix
        self.out_dir = Path(out_dir)
        self.options = options
        self.ray_options = ray_options
        self._on_change = on_change or (lambda progress: None)
        self._on_result = on_result or (lambda result, progress: None)
        # The driver's executor only says which brains an episode launches (a slot is given episodes whose launches
        # its stack runs); the episodes run on the nodes' own executors (EpisodeSlot, run_episode_task).
        self.executor = EpisodeExecutor(
            matrix=matrix, out_dir=self.out_dir, options=options, node="driver", make_stack=_no_stack_on_the_driver
        )

    def stop(self) -> None:
        """Start no more episodes (the dispatch loop's Ctrl-C path stops the running ones)."""
        self.executor.stop()

    def run(self) -> MatrixProgress:
        connect(self.ray_options.address)
        lanes = capacity(self.ray_options.resources)  # before anything is submitted: fail at once
        return run_matrix(
            self.matrix,
            self.out_dir,
            self.options,
            lanes=lanes,
            dispatch=self._dispatch,
            on_change=self._on_change,
            on_result=self._on_result,
        )

    def _dispatch(self, book: MatrixBook) -> None:
        """Run ``book.todo`` on the cluster, each result through :meth:`MatrixBook.finish`: one loop for both kinds
        of worker, an episode slot per warm stack (:class:`_Slots`) or, with ``--fresh-stacks``, a task per episode
        (:class:`_Tasks`). A lost episode goes back to ``waiting`` (:meth:`_collect`)."""
        ray = import_ray()
        self.matrix = self.executor.matrix = book.matrix  # as fitted to the results it resumes
        progress = book.progress
        shared = dataclasses.replace(self.matrix, text="", episodes=())  # what a node needs: name and shadows
        pool: _Slots | _Tasks = (_Tasks if self.options.fresh_stacks else _Slots)(driver=self, shared=shared)
        waiting = collections.deque((episode, ()) for episode in book.todo)
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
                        book.finish(result)
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


@dataclasses.dataclass(frozen=True)
class TaskError:
    """What the driver reads instead of an item when the task failed (Ray raises it where the item would be)."""

    error: BaseException


def next_item(stream) -> StreamItem | TaskError:
    """The next item of a task's stream, or :class:`TaskError` when the task failed (Ray raises it where the item
    would be): the driver decides on the item's type, never by raising the error only to catch it."""
    ray = import_ray()
    try:
        return ray.get(next(stream))
    except StopIteration:
        return TaskError(RuntimeError("the episode's task ended without a result"))
    except ray.exceptions.RayError as error:
        return TaskError(error)


def _no_stack_on_the_driver(**settings: Any) -> Any:
    raise AssertionError("the Ray driver runs no episode: its slots and tasks do, each with its own executor")


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


__all__ = ["RayMatrixRunner"]
