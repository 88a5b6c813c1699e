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


class MatrixRunner:
    """Runs the planned episodes of one matrix into one output folder. ``run()`` returns the finished count."""

    def __init__(
        self,
        matrix: Matrix,
        out_dir: Path,
        options: RunOptions,
        *,
        on_change: Callable[[MatrixProgress], None] | None = None,
    ):
        self.matrix = matrix
        self.out_dir = Path(out_dir)
        self.options = options
        self._on_change = on_change or (lambda progress: None)
        self._store_lock = threading.Lock()
        # Every worker runs its episodes through this one executor (it holds no episode's state); its stacks share
        # this machine's cores for rendering.
        self.executor = EpisodeExecutor(
            matrix=matrix, out_dir=self.out_dir, options=options, node=socket.gethostname(), make_stack=self._stack
        )

    def pending(self, store: ResultStore) -> list[PlannedEpisode]:
        if not self.options.resume:
            return list(self.matrix.episodes)
        finished = store.finished_keys(include_failed=not self.options.retry_failed)
        return [episode for episode in self.matrix.episodes if episode.key not in finished]

    def stop(self) -> None:
        """Abandon running episodes (they stay missing, so ``--resume`` runs them) and start no more."""
        self.executor.stop()

    def run(self) -> MatrixProgress:
        self.out_dir.mkdir(parents=True, exist_ok=True)
        store = ResultStore(self.out_dir)
        try:
            self._check_same_matrix(store)
            self.executor.matrix = self.matrix  # as fitted to the results it resumes
            todo = self.pending(store)
            progress = MatrixProgress(
                total=len(self.matrix.episodes),
                skipped=len(self.matrix.episodes) - len(todo),
                workers=[WorkerState() for _ in range(self._lanes())],
            )
            self._dispatch(todo, store, progress)
        finally:
            store.close()
        self._on_change(progress)
        return progress

    def _lanes(self) -> int:
        """How many episodes run at once (one progress lane each)."""
        return max(1, self.options.workers)

    def _dispatch(self, todo: list[PlannedEpisode], store: ResultStore, progress: MatrixProgress) -> None:
        """Run ``todo``, each result through :meth:`_finish`, calling ``on_change`` as it goes. Here: worker threads
        on this machine; :mod:`orchestrator.matrix.ray_runner` runs them as tasks on a Ray cluster instead."""
        jobs = JobQueue(todo, launches=self.executor.launches)
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
        ended = [threading.Event() for _ in progress.workers]
        threads = [
            threading.Thread(
                target=self._lane,
                args=(done, jobs, store, progress, state, endpoint, i),
                name=f"matrix-worker-{i}",
                daemon=False,
            )
            for i, (done, state) in enumerate(zip(ended, progress.workers))
        ]
        try:
            for thread in threads:
                thread.start()
            for done in ended:
                while not done.wait(timeout=0.25):
                    self._on_change(progress)
        except BaseException:
            self.stop()  # Ctrl-C, SIGTERM: every worker abandons its episode and closes its stack
            for thread, done in zip(threads, ended):
                # One that Ctrl-C kept from starting runs nothing: it sees the stop before its first episode.
                if thread.ident is not None:
                    done.wait()
            raise
        finally:
            router.close()

    def _check_same_matrix(self, store: ResultStore) -> None:
        """Refuse to resume results of another matrix (MatrixChangedError); then record this one's facts."""
        if self.options.resume:
            self.matrix = resume_matrix(self.matrix, store).matrix
        previous = store.fact("source_text")
        if previous is not None and previous != self.matrix.text:
            log.warning(
                "%s holds results of a different version of the matrix file; episodes are matched by key", store.path
            )
        store.set_fact("name", self.matrix.name)
        store.set_fact("source_text", self.matrix.text)
        store.set_fact("variation_keys", list(self.matrix.variation_keys))
        # The report's baseline (the first value of every axis) without parsing the matrix file a second time.
        store.set_fact(BASELINE_FACT, self.matrix.episodes[0].variation if self.matrix.episodes else None)
        store.set_fact("shadows", [shadow.to_dict() for shadow in self.matrix.shadows])
        store.set_fact(PLANNED_KEYS_FACT, [episode.key for episode in self.matrix.episodes])
        for key, value in self.options.facts.items():
            store.set_fact(key, value)
        if store.fact("created_at") is None:
            store.set_fact("created_at", time.time())
        (self.out_dir / "matrix.yaml").write_text(self.matrix.text)

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
        store: ResultStore,
        progress: MatrixProgress,
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
                with progress.lock:
                    state.episode, state.live = episode, None
                if lane is None:
                    result = executor.run_fresh(episode, router_endpoint=endpoint, state=state)
                else:
                    result = executor.run_warm(episode, lane=lane, state=state)
                with progress.lock:
                    state.episode, state.live = None, None
                if result is None:  # abandoned: not a result
                    return
                self._finish(result, store, progress)
        finally:
            if lane is not None:
                lane.close()

    def _finish(self, result: EpisodeResult, store: ResultStore, progress: MatrixProgress) -> None:
        """One finished episode: committed to the results, then counted."""
        with self._store_lock:
            store.record(result)
        with progress.lock:
            progress.finished.append(result)
            if result.status == "done":
                progress.done += 1
            else:
                progress.failed += 1

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


__all__ = ["JobQueue", "MatrixProgress", "MatrixRunner", "RunOptions", "WorkerState", "never_moved"]
