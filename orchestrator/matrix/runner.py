"""Runs a test matrix: N workers on one router, each keeping a warm stack across its episodes, results into SQLite.

Each worker runs its episodes on one stack (simulator, noise injector, scorer, the episode's brain and any shadow
brains, optionally a recorder) under the worker's own run id, so workers run side by side on one router without
cross-talk; between episodes it changes only the brain hosts an episode needs (``orchestrator.matrix.warm``). A
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

import json
import logging
import shutil
import socket
import sys
import threading
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import msgspec
import numpy as np
import yaml

from orchestrator.matrix.load import BrainEntry, Matrix, PlannedEpisode
from orchestrator.matrix.results import BASELINE_FACT, EpisodeResult, ResultStore
from orchestrator.matrix.resume import PLANNED_KEYS_FACT, resume_matrix
from orchestrator.matrix.warm import JobQueue, WarmLane, copy_episode_logs, log_marks
from orchestrator.stack.failures import Failure, FailureKind
from orchestrator.stack.launcher import (
    BrainLaunch,
    EpisodeAborted,
    LocalStack,
    StackError,
    StackFailure,
    free_loopback_port,
    render_threads_for,
)
from protocol import codec, keys
from protocol.bus import Bus, BusConfig, Inbox
from protocol.messages import EndReason, EpisodeScore, LiveMetrics, Pose

log = logging.getLogger("drivebench.matrix")
# A brain whose episode ended brain_lost: how long to wait for its process to exit, so the failure names its last
# log line (a raising brain's traceback is written after its bus session, and so its token, is gone).
BRAIN_EXIT_WAIT_S = 5.0
SETTLE_S = 2.0  # the longest a trajectory waits for its last pose after the score came


@dataclass(frozen=True)
class RunOptions:
    """How to run a matrix.

    workers: episodes run at the same time (each on its own stack; about one core each).
    record: record every episode to ``episodes/<index>/recording.mcap``.
    record_images: "raw" (lossless) or "jpeg" camera images in recordings.
    resume: skip episodes the results database already holds (``retry_failed``: except failed ones).
    startup_timeout_s: per stack, how long its processes may take to come up.
    fresh_stacks: a new stack for every episode (``--fresh-stacks``); default: each worker keeps a warm stack
        across episodes (``orchestrator.matrix.warm``), meant to give the same results (docs/warm-stacks.md).
    facts: extra facts stored in the results database (``{"paper": True}`` for ``drivebench paper``).
    """

    workers: int = 1
    record: bool = False
    record_images: str = "jpeg"
    resume: bool = False
    retry_failed: bool = False
    startup_timeout_s: float = 90.0
    facts: dict = field(default_factory=dict)
    fresh_stacks: bool = False


@dataclass
class WorkerState:
    """What one worker is doing now, for the progress display."""

    episode: PlannedEpisode | None = None
    live: LiveMetrics | None = None


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
        self._stopping = threading.Event()
        self._store_lock = threading.Lock()

    def pending(self, store: ResultStore) -> list[PlannedEpisode]:
        if not self.options.resume:
            return list(self.matrix.episodes)
        finished = store.finished_keys(include_failed=not self.options.retry_failed)
        return [episode for episode in self.matrix.episodes if episode.key not in finished]

    def stop(self) -> None:
        """Abandon running episodes (they stay missing, so ``--resume`` runs them) and start no more."""
        self._stopping.set()

    def run(self) -> MatrixProgress:
        self.out_dir.mkdir(parents=True, exist_ok=True)
        store = ResultStore(self.out_dir)
        try:
            self._check_same_matrix(store)
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
        jobs = JobQueue(todo, launches=self._launches)
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
        lane = None
        if not self.options.fresh_stacks:
            settings = {"router_endpoint": endpoint, "startup_timeout_s": self.options.startup_timeout_s}
            lane = WarmLane(
                lane=lane_index, stacks_dir=self.out_dir / "stacks", make_stack=self._make_stack, settings=settings
            )
        try:
            while not self._stopping.is_set():
                episode = jobs.take(prefer=None if lane is None else lane.brains)
                if episode is None:
                    return
                with progress.lock:
                    state.episode, state.live = episode, None
                if lane is None:
                    result = self._run_one(episode, endpoint, state)
                else:
                    result = self._run_warm(episode, lane, state)
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

    def _run_one(self, episode: PlannedEpisode, endpoint: str, state: WorkerState) -> EpisodeResult | None:
        """One episode on a fresh stack of its own (``--fresh-stacks``, and every Ray task)."""
        folder = self._episode_folder(episode)
        run_id = f"m{episode.index:04d}-{uuid.uuid4().hex[:6]}"
        started_at = time.time()
        stack = self._make_stack(
            run_id=run_id,
            run_dir=folder,
            brains=self._launches(episode),
            router_endpoint=endpoint,
            startup_timeout_s=self.options.startup_timeout_s,
            record=folder / "recording.mcap" if self.options.record else None,
            record_options=(f"image_format={self.options.record_images}",),
        )
        self._write_config(folder, episode, run_id)
        trace = Trace()
        try:
            outcome = self._drive(episode, state, trace, lambda: (stack.start(), stack)[1])
        finally:
            stack.close()
        return self._episode_result(episode, stack, outcome, trace=trace, folder=folder, started_at=started_at)

    def _run_warm(self, episode: PlannedEpisode, lane: WarmLane, state: WorkerState) -> EpisodeResult | None:
        """One episode on the lane's warm stack (started, or its brain hosts changed, as the episode needs)."""
        folder = self._episode_folder(episode)
        started_at = time.time()
        trace = Trace()
        stacks: list[LocalStack] = []
        marks: dict[Path, int] = {}

        def prepare() -> LocalStack:
            if lane.stack is not None:  # where the episode's log lines begin (a new stack's: at their first line)
                marks.update(log_marks(lane.stack))
            stack = lane.stack_for(self._launches(episode))
            stacks.append(stack)
            stack.record_options = (f"image_format={self.options.record_images}",)
            self._write_config(folder, episode, stack.run_id)
            if self.options.record:  # the stack's recorder (started at its first episode) opens this file
                stack.record_episode(folder / "recording.mcap", attach=(folder / "config.yaml",))
            return stack

        try:
            outcome = self._drive(episode, state, trace, prepare)
        finally:
            trace.detach()
        if stacks and self.options.record and lane.stack is not None and outcome is not None:
            try:
                lane.stack.finish_recording()  # a complete, indexed file before the next episode starts
            except StackFailure as failure:
                lane.stack.recording_failure = failure  # scored all the same; the stack is replaced
        if stacks:
            copy_episode_logs(stacks[0], marks, folder / "logs")
        if outcome is None:
            lane.retire("its episode was abandoned")
            return None
        if not stacks:  # the stack did not come up: nothing ran on it
            return self._episode_result(episode, None, outcome, trace=trace, folder=folder, started_at=started_at)
        stack = stacks[0]
        result = self._episode_result(episode, stack, outcome, trace=trace, folder=folder, started_at=started_at)
        lane.after_episode(failed=outcome["status"] == "failed")
        return result

    def _drive(
        self, episode: PlannedEpisode, state: WorkerState, trace: Trace, prepare: Callable[[], LocalStack]
    ) -> dict | None:
        """Prepare a stack and run the episode on it: {"status", "score", "failure"}, or None when abandoned."""
        outcome: dict = {"status": "done", "score": None, "failure": None}
        try:
            stack = prepare()
            trace.attach(stack)
            outcome["score"] = stack.run_episode(
                episode.spec,
                on_live=lambda live: self._on_live(state, trace, live),
                abort=self._stopping.is_set,  # the wall-clock guard is the launcher's one rule (wall_guard_s)
            )
            trace.settle(last_seq=outcome["score"].metrics.steps, episode=stack.last_episode)
            if outcome["score"].reason == EndReason.BRAIN_LOST:  # scored, but the stack failed it
                detail = (
                    stack.dead_child_reason(wait_s=BRAIN_EXIT_WAIT_S) or "the active brain lost its liveliness token"
                )
                outcome.update(status="failed", failure=Failure(FailureKind.BRAIN_DIED, detail))
        except EpisodeAborted:
            return None
        except StackFailure as failure:
            outcome.update(status="failed", failure=failure.failure, score=failure.score)
        except StackError as error:
            outcome.update(status="failed", failure=Failure(FailureKind.START_FAILED, str(error)))
        except Exception as error:  # one broken episode must not end the matrix
            log.exception("episode %s", episode.key)
            outcome.update(status="failed", failure=Failure(FailureKind.ERROR, f"{type(error).__name__}: {error}"))
        return outcome

    def _episode_result(
        self,
        episode: PlannedEpisode,
        stack: LocalStack | None,
        outcome: dict | None,
        *,
        trace: Trace,
        folder: Path,
        started_at: float,
    ) -> EpisodeResult | None:
        """An episode's files (score, trajectory, a recording failure) and its result; None when it is no result."""
        if outcome is None:
            return None
        run_id = stack.run_id if stack is not None else ""
        if stack is not None and stack.recording_failure is not None:  # scored; the recording beside it is incomplete
            (folder / "recording_failure.json").write_text(
                json.dumps(stack.recording_failure.record(run_id=run_id), indent=2) + "\n"
            )
        if self._stopping.is_set() and outcome["status"] == "failed":
            return None  # its processes were stopped under it: run it again on resume
        score: EpisodeScore | None = outcome["score"]
        if score is not None:
            (folder / "score.json").write_text(codec.to_json(score, indent=2) + "\n")
        trajectory = trace.save(folder / "trajectory.npz", episode=None if stack is None else stack.last_episode)
        recording = folder / "recording.mcap"
        logs = folder / "logs"  # a warm stack's episode: the lines its processes logged during the episode
        return EpisodeResult.of(
            episode,
            status=outcome["status"],
            run_id=run_id,
            started_at=started_at,
            ended_at=time.time(),
            reason=str(score.reason) if score is not None else None,
            failure=outcome["failure"],
            score=score,
            recording=self._relative(recording) if recording.is_file() else None,
            trajectory=self._relative(trajectory),
            logs=self._relative(logs),
            node=self._node_name(),
        )

    def _make_stack(self, **settings) -> LocalStack:
        """The stack of one episode (a hook: a Ray task puts its processes in one process group); the workers'
        stacks share this machine's cores for rendering."""
        return LocalStack(render_threads=render_threads_for(stacks=self._lanes()), **settings)

    def _node_name(self) -> str:
        """Where episodes run, for the results (a hook: Ray tasks name their cluster node)."""
        return socket.gethostname()

    def _episode_folder(self, episode: PlannedEpisode) -> Path:
        folder = self.out_dir / "episodes" / f"{episode.index:04d}"
        if folder.exists():  # an attempt that never finished (killed or abandoned): not a result, start over
            shutil.rmtree(folder)
        (folder / "logs").mkdir(parents=True)
        return folder

    def _launches(self, episode: PlannedEpisode) -> list[BrainLaunch]:
        return [brain_launch(episode.brain), *(brain_launch(shadow, shadow=True) for shadow in self.matrix.shadows)]

    def _write_config(self, folder: Path, episode: PlannedEpisode, run_id: str) -> None:
        (folder / "config.yaml").write_text(
            yaml.safe_dump(
                {
                    "run_id": run_id,
                    "matrix": self.matrix.name,
                    "key": episode.key,
                    "episode": msgspec.to_builtins(episode.spec),
                    "brains": [entry.to_dict() for entry in (episode.brain, *self.matrix.shadows)],
                },
                sort_keys=False,
                default_flow_style=None,
            )
        )

    @staticmethod
    def _on_live(state: WorkerState, trace: Trace, live: LiveMetrics) -> None:
        state.live = live
        trace.add_live(live)

    def _relative(self, path: Path) -> str:
        return str(path.relative_to(self.out_dir))


def brain_launch(entry: BrainEntry, *, shadow: bool = False) -> BrainLaunch:
    """The brain host launch of one matrix brain entry (its label is its bus name); ``shadow``: one of ``shadows:``."""
    host = ("shadow=true",) if shadow else ()
    return BrainLaunch(entry.brain, name=entry.label, options=entry.launch_options(), host=host)


class Trace:
    """An episode's ground-truth poses and live metrics, as received, for trajectory plots and progress curves."""

    def __init__(self) -> None:
        self._poses = Inbox()
        self._received: list[Pose] = []
        self._live: list[tuple[float, float, float]] = []
        self._subscription = None

    def attach(self, stack: LocalStack) -> None:
        assert stack.bus is not None
        self._subscription = stack.bus.subscribe(keys.pose(stack.run_id), Pose, inbox=self._poses)

    def detach(self) -> None:
        """Stop receiving poses (a warm stack's bus outlives the episode; its subscriptions must not pile up)."""
        if self._subscription is not None:
            self._subscription.close()
            self._subscription = None

    def settle(self, *, last_seq: int, episode: int | None, timeout_s: float = SETTLE_S) -> None:
        """Wait (at most ``timeout_s``) for the episode's last pose, ``last_seq``: the score can overtake the last
        poses on a loaded machine, and a trajectory must not lose its end to that (seen: 3 of 61 poses)."""
        deadline = time.monotonic() + timeout_s
        while True:
            self._received.extend(p.message for p in self._poses.drain())
            if any(p.header.seq >= last_seq and episode in (None, p.header.episode) for p in self._received):
                return
            remaining_s = deadline - time.monotonic()
            if remaining_s <= 0:
                return
            arrived = self._poses.recv(timeout_s=min(remaining_s, 0.05))
            if arrived is not None:
                self._received.append(arrived.message)

    def add_live(self, live: LiveMetrics) -> None:
        self._live.append((live.sim_time_s, live.progress_laps, live.cross_track_m))

    def save(self, path: Path, *, episode: int | None = None) -> Path:
        """Write the trajectory; ``episode``: keep only that episode's poses (on a warm stack, a pose of the episode
        before may still trail in after this one's subscription began)."""
        received = self._received + [p.message for p in self._poses.drain()]
        if episode is not None:
            received = [pose for pose in received if pose.header.episode == episode]
        # The first pose of each frame: a lock-step resend of a frame nobody answered yet publishes its pose again
        # with the speed zeroed, and the trajectory must not depend on whether the brain was slow to its first answer.
        first: dict[int, Pose] = {}
        for pose in received:
            first.setdefault(pose.header.seq, pose)
        poses = sorted(first.items())
        rows = np.array(
            [(pose.header.stamp_ns / 1e9, pose.x_m, pose.y_m, pose.yaw_rad, pose.speed_mps) for _, pose in poses],
            dtype=np.float64,
        ).reshape(-1, 5)
        live = np.array(self._live, dtype=np.float64).reshape(-1, 3)
        np.savez_compressed(
            path,
            stamp_s=rows[:, 0],
            x_m=rows[:, 1],
            y_m=rows[:, 2],
            yaw_rad=rows[:, 3],
            speed_mps=rows[:, 4],
            live_sim_time_s=live[:, 0],
            live_progress_laps=live[:, 1],
            live_cross_track_m=live[:, 2],
        )
        return path


class ProgressDisplay:
    """Progress on stderr: one line per finished episode, and on a terminal live bars: episodes done / running /
    failed with an ETA, and each worker's lap progress.

    The bars are made on the first update, when the number of episodes a resume skips is known (the ETA counts
    only the episodes run in this session).
    """

    def __init__(self, *, enabled: bool = True):
        self._enabled = enabled
        self._tty = sys.stderr.isatty()
        self._main = None
        self._lanes: list = []
        self._reported = 0

    def _make(self, progress: MatrixProgress) -> None:
        from tqdm import tqdm

        bars = self._enabled and self._tty
        self._main = tqdm(
            total=progress.total,
            initial=progress.skipped,
            unit="episode",
            file=sys.stderr,
            disable=not bars,
            dynamic_ncols=True,
            smoothing=0.0,
            desc="matrix",
        )
        self._lanes = [
            tqdm(
                total=100,
                file=sys.stderr,
                position=i + 1,
                leave=False,
                dynamic_ncols=True,
                disable=not bars,
                bar_format="  {desc} {percentage:3.0f}%|{bar}|",
            )
            for i in range(len(progress.workers))
        ]

    def update(self, progress: MatrixProgress) -> None:
        if self._main is None:
            self._make(progress)
        with progress.lock:
            finished = progress.skipped + progress.done + progress.failed
            new_results = progress.finished[self._reported :]
            self._reported = len(progress.finished)
            lanes = [(worker.episode, worker.live) for worker in progress.workers]
            counts = f"done {progress.done}, running {progress.running}, failed {progress.failed}" + (
                f", resumed past {progress.skipped}" if progress.skipped else ""
            )
        for number, result in enumerate(new_results, start=finished - len(new_results) + 1):
            if self._enabled:
                self._main.write(f"[{number}/{progress.total}] {_result_line(result)}", file=sys.stderr)
        self._main.update(finished - self._main.n)
        self._main.set_postfix_str(counts, refresh=False)
        self._main.refresh()
        for lane, (episode, live) in zip(self._lanes, lanes):
            lane.n = 0 if episode is None else self._lap_percent(live)
            lane.set_description_str("idle" if episode is None else self._lane_text(episode, live), refresh=False)
            lane.refresh()

    @staticmethod
    def _lap_percent(live: LiveMetrics | None) -> int:
        if live is None:
            return 0
        return min(100, round(100 * live.progress_laps / max(1, live.laps_target)))

    @staticmethod
    def _lane_text(episode: PlannedEpisode, live: LiveMetrics | None) -> str:
        status = f"sim {live.sim_time_s:5.1f} s" if live is not None else "starting"
        return f"{episode.key[:60]:<60} {status}"

    def close(self) -> None:
        for lane in self._lanes:
            lane.close()
        if self._main is not None:
            self._main.close()


def _result_line(result: EpisodeResult) -> str:
    """``explicit/simple/default/none/r0: laps_completed, BM lap 57.20 s (21.3 s wall)`` or the failure: the lap
    time the report's tables give (BM lap seconds; the arc-length lap when BM counts no lap), named as there."""
    wall = f"({result.wall_s:.1f} s wall)"
    if result.status == "failed":
        return f"{result.key}: FAILED {result.failure} {wall}"
    metrics = result.score.metrics
    if metrics.bm_lap_seconds is not None:
        lap = f", BM lap {metrics.bm_lap_seconds:.2f} s"
    else:
        lap = f", lap (arc length) {metrics.lap_times_s[0]:.2f} s" if metrics.lap_times_s else ""
    return (
        f"{result.key}: {result.reason}{lap}, {metrics.percentage_completed:.0f} % of a lap in "
        f"{metrics.sim_time_s:.1f} s sim {wall}"
    )


def summary_line(progress: MatrixProgress, out_dir: Path) -> str:
    ran = progress.done + progress.failed
    return (
        f"{ran} episode(s) run ({progress.done} done, {progress.failed} failed)"
        + (f", {progress.skipped} already in the results" if progress.skipped else "")
        + f"; results in {out_dir / 'results.sqlite'}"
    )


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


def plan_table(matrix: Matrix) -> str:
    """The planned episodes, one per line (``drivebench matrix FILE --plan``)."""
    lines = [f"{matrix.name}: {len(matrix.episodes)} episode(s)"]
    lines += [f"{episode.index:4d}  {episode.key}  seed {episode.spec.seed}" for episode in matrix.episodes]
    return "\n".join(lines)


def plan_json(matrix: Matrix) -> str:
    """The planned episodes as one JSON array (``drivebench matrix FILE --plan --json``)."""
    episodes = [
        {"index": episode.index, "key": episode.key, "spec": msgspec.to_builtins(episode.spec)}
        for episode in matrix.episodes
    ]
    return json.dumps(episodes, indent=2)


__all__ = [
    "MatrixRunner",
    "RunOptions",
    "MatrixProgress",
    "ProgressDisplay",
    "summary_line",
    "never_moved",
    "plan_table",
    "plan_json",
]
