"""One ``drivebench run`` episode on a stack of its own, into its run folder: the run's config.yaml, the stack
started, the episode driven and scored, ``score.json``, and the failure records when something died. The CLI
(``orchestrator/cli/run.py``) parses the options into a :class:`LocalRun` and prints what :meth:`LocalRun.drive`
returns; this module is the pipeline in between."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from orchestrator.stack import run_folder
from orchestrator.stack.failures import StackFailure
from orchestrator.stack.launcher import BrainLaunch, LocalStack, render_threads_for
from orchestrator.stack.run_folder import LaunchedBrain, RunConfig
from protocol.episode_spec import EpisodeSpec
from protocol.messages import EndReason, EpisodeScore, LiveMetrics

# A brain whose episode ended brain_lost: how long to wait for its process to exit, so that the run names its last
# log line (a raising brain's traceback is written after its bus session, and so its token, is gone).
BRAIN_EXIT_WAIT_S = 5.0


@dataclass(frozen=True, kw_only=True)
class RunOutcome:
    """What a local run ended with: its ``score``; ``brain_died``, the dead brain's last words when the episode
    ended ``brain_lost``; ``recording_failure`` when the recorder died (the episode was scored, its recording is
    incomplete: ``recording_failure.json`` says so)."""

    score: EpisodeScore
    brain_died: str | None = None
    recording_failure: StackFailure | None = None


@dataclass(frozen=True, kw_only=True)
class LocalRun:
    """One episode (``spec``) with its ``brains`` on a local stack of its own, into ``run_dir``. ``record``: an MCAP
    file to record into, images as ``record_images`` ("raw" or "jpeg"); ``ros2``: the ROS 2 bridge's options (None:
    no bridge)."""

    run_id: str
    run_dir: Path
    spec: EpisodeSpec
    brains: list[BrainLaunch]
    record: Path | None = None
    record_images: str = "raw"
    ros2: tuple[str, ...] | None = None

    def write_config(self) -> Path:
        """``<run_dir>/config.yaml``: the episode and every brain, as ``drivebench run --config`` reads them."""
        brains = [LaunchedBrain.of(launch) for launch in self.brains]
        return run_folder.write_run_config(
            self.run_dir, RunConfig(run_id=self.run_id, episode=self.spec, brains=brains)
        )

    def drive(
        self,
        *,
        on_live: Callable[[LiveMetrics], None] | None = None,
        on_failure_record: Callable[[dict], None] | None = None,
    ) -> RunOutcome:
        """Start the stack, run the episode, write ``score.json`` (and ``recording_failure.json``) and return the
        outcome. A failed stack leaves ``failure.json`` (also handed to ``on_failure_record``) and raises its
        StackFailure; a failure while the stack comes up is recorded too (a sandboxed brain's is typed)."""
        brain_died = None
        with (
            run_folder.recorded_failure(self.run_dir, run_id=self.run_id, on_record=on_failure_record),
            self._stack() as stack,
        ):
            stack.write_stack_file()  # drivebench swap finds the running stack through it
            score = stack.run_episode(self.spec, on_live=on_live)
            if score.reason == EndReason.BRAIN_LOST:  # scored up to its death: what killed it (its last line)
                brain_died = stack.dead_child_reason(wait_s=BRAIN_EXIT_WAIT_S) or "the brain lost its liveliness token"
        run_folder.write_score(self.run_dir, score)
        if stack.recording_failure is not None:
            run_folder.write_recording_failure(self.run_dir, stack.recording_failure, run_id=self.run_id)
        return RunOutcome(score=score, brain_died=brain_died, recording_failure=stack.recording_failure)

    def _stack(self) -> LocalStack:
        return LocalStack(
            run_id=self.run_id,
            run_dir=self.run_dir,
            brains=self.brains,
            record=self.record,
            record_options=(f"image_format={self.record_images}",),
            ros2=self.ros2,
            render_threads=render_threads_for(stacks=1),
        )
