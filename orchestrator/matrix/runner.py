"""Runs a test matrix: N workers on one router, each keeping a warm stack across its episodes, results into SQLite.

Each worker runs its episodes on one stack (simulator, noise injector, scorer, the episode's brain and any shadow
brains, optionally a recorder) under the worker's own run id, so workers run side by side on one router without
cross-talk; between episodes it changes only the brain hosts an episode needs (``orchestrator.matrix.executor``). A
stack that fails an episode, or whose process dies, is replaced before the next one. ``--fresh-stacks`` gives every
episode a new stack of its own instead. Each finished episode is committed to ``results.sqlite`` at once (see
:mod:`orchestrator.matrix.results`); ``resume`` runs only the episodes the database does not hold.

Folder layout of a matrix run::

    DIR/results.sqlite                   one row per finished episode
    DIR/matrix.yaml                      the matrix file as run
    DIR/episodes/<index>/                one folder per episode: config.yaml, score.json, logs/, trajectory.npz,
                                         recording.mcap (with --record)
    DIR/stacks/<run id>/logs/            the whole logs of each warm stack (an episode's logs/ holds its lines)
    DIR/report.html, report.md, ...      written at the end (``drivebench report DIR`` writes them again)
"""

from __future__ import annotations

import logging
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from orchestrator.matrix.executor import EpisodeExecutor, RunOptions, WorkerState
from orchestrator.matrix.load import Matrix, PlannedEpisode
from orchestrator.matrix.results import BASELINE_FACT, EpisodeResult, ResultStore
from orchestrator.matrix.resume import PLANNED_KEYS_FACT, resume_matrix
from orchestrator.stack.launcher import BrainLaunch, LocalStack, free_loopback_port, render_threads_for
from protocol.bus import Bus, BusConfig

log = logging.getLogger("drivebench.matrix")


@dataclass
class MatrixProgress:
    """Counts shared between the workers and the display."""

    total: int
    skipped: int = 0
    done: int = 0
    failed: int = 0
    workers: list[WorkerState] = field(default_factory=list)
    finished: list[EpisodeResult] = field(default_factory=list)  # in the order they ended, this session
    lock: threading.Lock = field(default_factory=threading.Lock)

    @property
    def running(self) -> int:
        return sum(1 for worker in self.workers if worker.episode is not None)


@dataclass
class MatrixBook:
    """One run's output folder as both runners keep it (local workers here, Ray in ``ray_runner``): the results
    database, the matrix as fitted to the results it resumes, the episodes still to run and the progress counts."""

    matrix: Matrix
    todo: list[PlannedEpisode]
    progress: MatrixProgress
    store: ResultStore
    on_result: Callable[[EpisodeResult, MatrixProgress], None]
    _store_lock: threading.Lock = field(default_factory=threading.Lock)

    def finish(self, result: EpisodeResult) -> None:
        """One finished episode: committed to the results, counted, then ``on_result`` (in the caller's thread; a
        local worker's stack is still up then). Safe from any thread."""
        with self._store_lock:
            self.store.record(result)
        with self.progress.lock:
            self.progress.finished.append(result)
            if result.status == "done":
                self.progress.done += 1
            else:
                self.progress.failed += 1
        self.on_result(result, self.progress)


def run_matrix(
    matrix: Matrix,
    out_dir: Path,
    options: RunOptions,
    *,
    lanes: int,
    dispatch: Callable[[MatrixBook], None],
    on_change: Callable[[MatrixProgress], None],
    on_result: Callable[[EpisodeResult, MatrixProgress], None],
) -> MatrixProgress:
    """The part of a run both runners share: open the results, record the matrix, take what is left to run (all of
    it without ``--resume``), and ``dispatch`` it with ``lanes`` progress lanes; each result goes through
    :meth:`MatrixBook.finish`. How the episodes run is ``dispatch``'s alone."""
    out_dir.mkdir(parents=True, exist_ok=True)
    store = ResultStore(out_dir)
    try:
        matrix = record_matrix(matrix, store, options=options, out_dir=out_dir)
        todo = pending(matrix, store, options=options)
        progress = MatrixProgress(
            total=len(matrix.episodes),
            skipped=len(matrix.episodes) - len(todo),
            workers=[WorkerState() for _ in range(lanes)],
        )
        dispatch(MatrixBook(matrix=matrix, todo=todo, progress=progress, store=store, on_result=on_result))
    finally:
        store.close()
    on_change(progress)
    return progress


def pending(matrix: Matrix, store: ResultStore, *, options: RunOptions) -> list[PlannedEpisode]:
    """The episodes of ``matrix`` to run: all of them, or with ``--resume`` those ``store`` does not hold (failed
    ones too with ``--retry-failed``)."""
    if not options.resume:
        return list(matrix.episodes)
    finished = store.finished_keys(include_failed=not options.retry_failed)
    return [episode for episode in matrix.episodes if episode.key not in finished]


def record_matrix(matrix: Matrix, store: ResultStore, *, options: RunOptions, out_dir: Path) -> Matrix:
    """Refuse to resume results of another matrix (MatrixChangedError); then record this one's facts. The matrix as
    it runs (fitted to the results it resumes)."""
    if options.resume:
        matrix = resume_matrix(matrix, store).matrix
    previous = store.fact("source_text")
    if previous is not None and previous != matrix.text:
        log.warning(
            "%s holds results of a different version of the matrix file; episodes are matched by key", store.path
        )
    store.set_fact("name", matrix.name)
    store.set_fact("source_text", matrix.text)
    store.set_fact("variation_keys", list(matrix.variation_keys))
    # The report's baseline (the first value of every axis) without parsing the matrix file a second time.
    store.set_fact(BASELINE_FACT, matrix.episodes[0].variation if matrix.episodes else None)
    store.set_fact("shadows", [shadow.to_dict() for shadow in matrix.shadows])
    store.set_fact(PLANNED_KEYS_FACT, [episode.key for episode in matrix.episodes])
    for key, value in options.facts.items():
        store.set_fact(key, value)
    if store.fact("created_at") is None:
        store.set_fact("created_at", time.time())
    (out_dir / "matrix.yaml").write_text(matrix.text)
    return matrix


def _ignore(*_: object) -> None:
    pass


class MatrixRunner:
    """Runs the planned episodes of one matrix into one output folder on this machine's worker threads. ``run()``
    returns the progress; ``on_change`` follows it, ``on_result`` sees each result once it is committed."""

    def __init__(
        self,
        matrix: Matrix,
        out_dir: Path,
        options: RunOptions,
        *,
        on_change: Callable[[MatrixProgress], None] | None = None,
        on_result: Callable[[EpisodeResult, MatrixProgress], None] | None = None,
    ):
        self.matrix = matrix
        self.out_dir = Path(out_dir)
        self.options = options
        self._on_change = on_change or _ignore
        self._on_result = on_result or _ignore
        # Every worker runs its episodes through this one executor (it holds no episode's state); its stacks share
        # this machine's cores for rendering.
        self.executor = EpisodeExecutor(
            matrix=matrix, out_dir=self.out_dir, options=options, node=socket.gethostname(), make_stack=self._stack
        )

    def stop(self) -> None:
        """Abandon running episodes (they stay missing, so ``--resume`` runs them) and start no more."""
        self.executor.stop()

    def run(self) -> MatrixProgress:
        return run_matrix(
            self.matrix,
            self.out_dir,
            self.options,
            lanes=self._lanes(),
            dispatch=self._dispatch,
            on_change=self._on_change,
            on_result=self._on_result,
        )

    def _lanes(self) -> int:
        """How many episodes run at once (one progress lane each)."""
        return max(1, self.options.workers)

    def _dispatch(self, book: MatrixBook) -> None:
        """Run ``book.todo`` on worker threads of this machine, each result through :meth:`MatrixBook.finish`,
        calling ``on_change`` as it goes."""
        self.matrix = self.executor.matrix = book.matrix  # as fitted to the results it resumes
        jobs = JobQueue(book.todo, launches=self.executor.launches)
        # One router for the whole matrix, embedded here; every episode's processes connect to it.
        router = Bus(BusConfig(mode="router", listen=[f"tcp/127.0.0.1:{free_loopback_port()}"]), name="matrix-router")
        endpoint = router.config.listen[0]
        # Each worker sets its event when it ends: the main thread waits on those, never in Thread.join(), because
        # Ctrl-C inside a join makes Python 3.11 take a running thread for stopped (Thread._wait_for_tstate_lock's
        # bpo-45274 handler releases the lock the running thread holds): it was neither joined nor waited for at
        # exit, and the interpreter shut down under it while it was still closing its Zenoh session, which aborted
        # the process ("FATAL: exception not rethrown"; its core dump shows the worker in Session.close()).
        # Never daemon threads either: the thread Zenoh starts for each callback subscription inherits the flag,
        # and a daemon one still in Zenoh's code at exit aborts the process the same way.
        ended = [threading.Event() for _ in book.progress.workers]
        threads = [
            threading.Thread(
                target=self._lane,
                args=(done, jobs, book, state, endpoint, i),
                name=f"matrix-worker-{i}",
                daemon=False,
            )
            for i, (done, state) in enumerate(zip(ended, book.progress.workers))
        ]
        try:
            for thread in threads:
                thread.start()
            for done in ended:
                while not done.wait(timeout=0.25):
                    self._on_change(book.progress)
        except BaseException:
            self.stop()  # Ctrl-C, SIGTERM: every worker abandons its episode and closes its stack
            for thread, done in zip(threads, ended):
                # One that Ctrl-C kept from starting runs nothing: it sees the stop before its first episode.
                if thread.ident is not None:
                    done.wait()
            raise
        finally:
            router.close()

    # -- one worker: episodes one after another --

    def _lane(self, done: threading.Event, *work_args) -> None:
        """A worker thread: :meth:`_work`, then ``done`` set however it ended."""
        try:
            self._work(*work_args)
        finally:
            done.set()

    def _work(
        self,
        jobs: JobQueue,
        book: MatrixBook,
        state: WorkerState,
        endpoint: str,
        lane_index: int,
    ) -> None:
        executor = self.executor
        lane = None if self.options.fresh_stacks else executor.warm_lane(lane=lane_index, router_endpoint=endpoint)
        try:
            while not executor.stopping:
                episode = jobs.take(prefer=None if lane is None else lane.brains)
                if episode is None:
                    return
                with book.progress.lock:
                    state.episode, state.live = episode, None
                if lane is None:
                    result = executor.run_fresh(episode, router_endpoint=endpoint, state=state)
                else:
                    result = executor.run_warm(episode, lane=lane, state=state)
                with book.progress.lock:
                    state.episode, state.live = None, None
                if result is None:  # abandoned: not a result
                    return
                book.finish(result)
        finally:
            if lane is not None:
                lane.close()

    def _stack(self, **settings) -> LocalStack:
        """A worker's stack: the workers' stacks share this machine's cores for rendering."""
        return LocalStack(render_threads=render_threads_for(stacks=self._lanes()), **settings)


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


NEVER_MOVED_M = 1.0  # a smoke episode is seconds of driving at metres per second: under a metre is standing still


def never_moved(progress: MatrixProgress) -> list[str]:
    """One line per brain whose every finished episode of this session drove less than :data:`NEVER_MOVED_M`:
    "done" says the stack ran, not that the brain drives (a brain that swallows its own errors sends nothing)."""
    distances: dict[str, list[float]] = {}
    for result in progress.finished:
        if result.status == "done" and result.score is not None:
            distances.setdefault(result.brain, []).append(result.score.metrics.completed_distance_m)
    return [
        f"{brain} never moved: at most {max(metres):.2f} m in each of its {len(metres)} episode(s); read its log "
        "(a brain that catches its own errors drives nothing)"
        for brain, metres in distances.items()
        if max(metres) < NEVER_MOVED_M
    ]


__all__ = [
    "JobQueue",
    "MatrixBook",
    "MatrixProgress",
    "MatrixRunner",
    "RunOptions",
    "WorkerState",
    "never_moved",
    "run_matrix",
]
