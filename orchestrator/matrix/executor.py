"""One episode of a matrix, run into its folder: the episode executor that local matrix workers and Ray episode
slots and tasks share (:class:`EpisodeExecutor`), on a fresh stack of its own or on a lane's warm stack
(:class:`WarmLane`). Who holds an executor says how its stacks are made and which node its rows name; what an
episode does on its stack, and what lands in its folder, is written once, here.

Warm stacks: a matrix worker (or a Ray episode slot) keeps one stack across episodes and changes only what an
episode changes.

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

import dataclasses
import json
import logging
import shutil
import threading
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import msgspec
import yaml

from orchestrator.matrix.load import BrainEntry, Matrix, PlannedEpisode
from orchestrator.matrix.plan import EpisodeConfig
from orchestrator.matrix.results import EpisodeResult
from orchestrator.stack.failures import EpisodeAborted, Failure, FailureKind, StackError, StackFailure
from orchestrator.stack.launcher import BrainLaunch, LocalStack
from orchestrator.stack.sandbox import Sandbox
from orchestrator.stack.trace import Trace
from protocol import codec
from protocol.messages import EndReason, EpisodeScore, LiveMetrics

log = logging.getLogger("drivebench.matrix")
# A brain whose episode ended brain_lost: how long to wait for its process to exit, so the failure names its last
# log line (a raising brain's traceback is written after its bus session, and so its token, is gone).
BRAIN_EXIT_WAIT_S = 5.0


@dataclass(frozen=True)
class RunOptions:
    """How to run a matrix.

    workers: episodes run at the same time (each on its own stack; about one core each).
    record: record every episode to ``episodes/<index>/recording.mcap``.
    record_images: "raw" (lossless) or "jpeg" camera images in recordings.
    resume: skip episodes the results database already holds (``retry_failed``: except failed ones).
    startup_timeout_s: per stack, how long its processes may take to come up.
    fresh_stacks: a new stack for every episode (``--fresh-stacks``); default: each worker keeps a warm stack
        across episodes (``orchestrator.matrix.executor``), meant to give the same results (docs/warm-stacks.md).
    facts: extra facts stored in the results database (``{"paper": True}`` for ``drivebench paper``).
    sandbox: every brain host in bubblewrap with these limits (``orchestrator.stack.sandbox``; a challenge's
        evaluations), each with a scratch folder of its own under ``out_dir/scratch/<episode>/<brain>``; None: none.
    """

    workers: int = 1
    record: bool = False
    record_images: str = "jpeg"
    resume: bool = False
    retry_failed: bool = False
    startup_timeout_s: float = 90.0
    facts: dict = field(default_factory=dict)
    fresh_stacks: bool = False
    sandbox: Sandbox | None = None


@dataclass
class WorkerState:
    """What one worker is doing now, for the progress display."""

    episode: PlannedEpisode | None = None
    live: LiveMetrics | None = None


@dataclass(kw_only=True)
class Outcome:
    """How an episode ended on its stack, before its files are written (an abandoned episode has none)."""

    status: str = "done"
    score: EpisodeScore | None = None
    failure: Failure | None = None


class EpisodeExecutor:
    """Runs planned episodes of ``matrix``, one at a time, each into ``out_dir/episodes/<index>/``, and returns each
    one's result row (None: abandoned, so not a result). The local runner's workers share one; a Ray episode slot or
    task holds its own. ``make_stack`` makes a stack from the launcher's settings (the local runner's share the
    machine's cores for rendering; a Ray node's put their processes in one process group); ``node`` is where the
    episodes run, as the rows name it."""

    def __init__(
        self,
        *,
        matrix: Matrix,
        out_dir: Path,
        options: RunOptions,
        node: str,
        make_stack: Callable[..., LocalStack],
    ):
        self.matrix = matrix
        self.out_dir = Path(out_dir)
        self.options = options
        self.node = node
        self._make_stack = make_stack
        self._stopping = threading.Event()

    @property
    def stopping(self) -> bool:
        return self._stopping.is_set()

    def stop(self) -> None:
        """Abandon running episodes (they stay missing, so ``--resume`` runs them) and start no more."""
        self._stopping.set()

    def go_on(self) -> None:
        """Run episodes again after a stop (a Ray slot's watchdog stopped one episode; the slot itself goes on)."""
        self._stopping.clear()

    def make_stack(self, **settings) -> LocalStack:
        """A stack (not started) with the launcher's ``settings`` (run_id, run_dir, brains, router_endpoint, ...)."""
        return self._make_stack(**settings)

    def launches(self, episode: PlannedEpisode) -> list[BrainLaunch]:
        """The brain hosts ``episode`` runs: its brain, then the matrix's shadows."""
        launches = [brain_launch(episode.brain), *(brain_launch(shadow, shadow=True) for shadow in self.matrix.shadows)]
        if self.options.sandbox is None:
            return launches
        scratch = self.out_dir / "scratch" / f"{episode.index:04d}"
        return [
            dataclasses.replace(
                launch, sandbox=dataclasses.replace(self.options.sandbox, scratch_dir=scratch / launch.bus_name)
            )
            for launch in launches
        ]

    def warm_lane(self, *, lane: int, router_endpoint: str) -> WarmLane:
        """A warm stack for one lane (a worker, a slot): its stacks' logs under ``out_dir/stacks/``."""
        settings = {"router_endpoint": router_endpoint, "startup_timeout_s": self.options.startup_timeout_s}
        return WarmLane(lane=lane, stacks_dir=self.out_dir / "stacks", make_stack=self.make_stack, settings=settings)

    def run_fresh(self, episode: PlannedEpisode, *, router_endpoint: str, state: WorkerState) -> EpisodeResult | None:
        """One episode on a fresh stack of its own (``--fresh-stacks``, and every Ray task), on the router at
        ``router_endpoint``; ``state.live`` follows its live metrics."""
        folder = self._episode_folder(episode)
        run_id = f"m{episode.index:04d}-{uuid.uuid4().hex[:6]}"
        started_at = time.time()
        stack = self.make_stack(
            run_id=run_id,
            run_dir=folder,
            brains=self.launches(episode),
            router_endpoint=router_endpoint,
            startup_timeout_s=self.options.startup_timeout_s,
            record=folder / "recording.mcap" if self.options.record else None,
            record_options=(f"image_format={self.options.record_images}",),
        )
        write_episode_config(folder, EpisodeConfig.of(episode, matrix=self.matrix, run_id=run_id))
        trace = Trace()

        def started() -> LocalStack:
            stack.start()
            return stack

        try:
            outcome = self._drive(episode, state, trace, started)
        finally:
            stack.close()
        return self._episode_result(episode, stack, outcome, trace=trace, folder=folder, started_at=started_at)

    def run_warm(self, episode: PlannedEpisode, *, lane: WarmLane, state: WorkerState) -> EpisodeResult | None:
        """One episode on the lane's warm stack (started, or its brain hosts changed, as the episode needs)."""
        folder = self._episode_folder(episode)
        started_at = time.time()
        trace = Trace()
        stacks: list[LocalStack] = []
        marks: dict[Path, int] = {}

        def prepare() -> LocalStack:
            if lane.stack is not None:  # where the episode's log lines begin (a new stack's: at their first line)
                marks.update(log_marks(lane.stack))
            stack = lane.stack_for(self.launches(episode))
            stacks.append(stack)
            stack.record_options = (f"image_format={self.options.record_images}",)
            write_episode_config(folder, EpisodeConfig.of(episode, matrix=self.matrix, run_id=stack.run_id))
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
        lane.after_episode(failed=outcome.status == "failed")
        return result

    def _drive(
        self, episode: PlannedEpisode, state: WorkerState, trace: Trace, prepare: Callable[[], LocalStack]
    ) -> Outcome | None:
        """Prepare a stack and run the episode on it: its outcome, or None when abandoned."""
        outcome = Outcome()
        try:
            stack = prepare()
            trace.attach(stack)
            outcome.score = score = stack.run_episode(
                episode.spec,
                on_live=lambda live: self._on_live(state, trace, live),
                abort=self._stopping.is_set,  # the wall-clock guard is the launcher's one rule (wall_guard_s)
            )
            trace.settle(last_seq=score.metrics.steps, episode=stack.last_episode)
            if score.reason == EndReason.BRAIN_LOST:  # scored, but the stack failed it
                detail = (
                    stack.dead_child_reason(wait_s=BRAIN_EXIT_WAIT_S) or "the active brain lost its liveliness token"
                )
                return Outcome(status="failed", score=score, failure=Failure(FailureKind.BRAIN_DIED, detail))
        except EpisodeAborted:
            return None
        except StackFailure as failure:
            return Outcome(status="failed", score=failure.score, failure=failure.failure)
        except StackError as error:
            why = Failure(FailureKind.START_FAILED, str(error))
            return Outcome(status="failed", score=outcome.score, failure=why)
        except Exception as error:  # one broken episode must not end the matrix
            log.exception("episode %s", episode.key)
            why = Failure(FailureKind.ERROR, f"{type(error).__name__}: {error}")
            return Outcome(status="failed", score=outcome.score, failure=why)
        return outcome

    def _episode_result(
        self,
        episode: PlannedEpisode,
        stack: LocalStack | None,
        outcome: Outcome | None,
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
        if self._stopping.is_set() and outcome.status == "failed":
            return None  # its processes were stopped under it: run it again on resume
        score = outcome.score
        if score is not None:
            (folder / "score.json").write_text(codec.to_json(score, indent=2) + "\n")
        trajectory = trace.save(folder / "trajectory.npz", episode=None if stack is None else stack.last_episode)
        recording = folder / "recording.mcap"
        logs = folder / "logs"  # a warm stack's episode: the lines its processes logged during the episode
        return EpisodeResult.of(
            episode,
            status=outcome.status,
            run_id=run_id,
            started_at=started_at,
            ended_at=time.time(),
            reason=str(score.reason) if score is not None else None,
            failure=outcome.failure,
            score=score,
            recording=self._relative(recording) if recording.is_file() else None,
            trajectory=self._relative(trajectory),
            logs=self._relative(logs),
            node=self.node,
        )

    def _episode_folder(self, episode: PlannedEpisode) -> Path:
        folder = self.out_dir / "episodes" / f"{episode.index:04d}"
        if folder.exists():  # an attempt that never finished (killed or abandoned): not a result, start over
            shutil.rmtree(folder)
        (folder / "logs").mkdir(parents=True)
        return folder

    @staticmethod
    def _on_live(state: WorkerState, trace: Trace, live: LiveMetrics) -> None:
        state.live = live
        trace.add_live(live)

    def _relative(self, path: Path) -> str:
        return str(path.relative_to(self.out_dir))


def write_episode_config(folder: Path, config: EpisodeConfig) -> Path:
    """``<folder>/config.yaml``: ``config`` as :func:`read_episode_config` reads it back (short lists and mappings
    on one line, as matrices have always written it)."""
    path = folder / "config.yaml"
    path.write_text(yaml.safe_dump(msgspec.to_builtins(config), sort_keys=False, default_flow_style=None))
    return path


def read_episode_config(path: Path) -> EpisodeConfig:
    """An episode folder's config.yaml, as :func:`write_episode_config` wrote it (``msgspec.ValidationError``: it
    is not one; ``yaml.YAMLError``: not YAML, e.g. caught half-written)."""
    return msgspec.convert(yaml.safe_load(path.read_text()), EpisodeConfig)


def brain_launch(entry: BrainEntry, *, shadow: bool = False) -> BrainLaunch:
    """The brain host launch of one matrix brain entry (its label is its bus name); ``shadow``: one of ``shadows:``."""
    host = ("shadow=true",) if shadow else ()
    return BrainLaunch(entry.brain, name=entry.label, options=entry.launch_options(), host=host)


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


__all__ = [
    "EpisodeExecutor",
    "Outcome",
    "RunOptions",
    "WarmLane",
    "WorkerState",
    "brain_launch",
    "copy_episode_logs",
    "log_marks",
]
