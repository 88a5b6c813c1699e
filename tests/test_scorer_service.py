"""Integration: the scorer process, fed by hand over a real bus, scores a lock-step episode only once the driver's
last command is in, however late it arrives after the END event (it comes from the brain, END from the simulator)."""

from __future__ import annotations

import math
import subprocess
import sys
import time

import pytest
from support.waits import wait_for, wait_for_subscribers

from circuits import load_circuit
from orchestrator.stack.launcher import free_loopback_port
from protocol import keys
from protocol.bus import Bus, BusConfig, Inbox, Traffic
from protocol.episode_spec import EpisodeSpec
from protocol.messages import Command, EndReason, EpisodeEvent, EpisodeScore, EventKind, Header, LiveMetrics, Pose

pytestmark = pytest.mark.integration
FRAMES = 40
LATE_S = 0.6  # the driver's last command arrives this long after END (well inside the scorer's grace)


@pytest.fixture
def scorer_bus(tmp_path):
    """(bus, run id): a router bus in this process and a scorer process on it, stopped after the test."""
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    run_id = "scorerlate"
    with Bus(BusConfig(mode="router", listen=[endpoint]), name="test", env={}) as bus:
        log = (tmp_path / "scorer.log").open("w")
        process = subprocess.Popen(
            [sys.executable, "-m", "services.scorer", "--router", endpoint, "--run-id", run_id],
            stdout=log,
            stderr=subprocess.STDOUT,
        )
        try:
            alive = bus.watch_alive(keys.alive_all(run_id))
            wait_for(
                lambda: any(keys.parse_alive(k)[1] == "scorer" for k in alive.alive()),
                timeout_s=30,
                what="the scorer's liveliness token",
                alive=lambda: None if process.poll() is None else f"the scorer exited with {process.returncode}",
            )
            yield bus, run_id
        finally:
            process.terminate()
            process.wait(timeout=10)
            log.close()


class ScorerOutput:
    """The scorer's scores, and its live metrics: it publishes those only once it has begun an episode."""

    def __init__(self, bus: Bus, run_id: str):
        self.scores: Inbox = Inbox()
        self.live: Inbox = Inbox()
        # Declared in this order on one session: once a live message arrives, the score subscription (declared
        # first) has reached the scorer too.
        bus.subscribe(keys.score(run_id), EpisodeScore, inbox=self.scores)
        bus.subscribe(keys.live_metrics(run_id), LiveMetrics, inbox=self.live)

    def try_recv(self):
        return self.scores.try_recv()

    def recv(self, *, timeout_s: float):
        return self.scores.recv(timeout_s=timeout_s)


def subscribe_scores_and_wait(bus: Bus, run_id: str, *publishers) -> ScorerOutput:
    """Subscribes to the scorer's output, and waits until the scorer's subscriptions match ``publishers``."""
    output = ScorerOutput(bus, run_id)
    wait_for_subscribers(*publishers)
    return output


def wait_for_episode(output: ScorerOutput, *, timeout_s: float = 10.0) -> None:
    """Until the scorer has begun episode 0 (its first live metrics for it)."""
    wait_for(
        lambda: (received := output.live.try_recv()) is not None and received.message.header.episode == 0,
        timeout_s=timeout_s,
        what="the scorer's live metrics of episode 0 (it begins an episode on its START event)",
    )


def test_a_late_last_command_still_counts(scorer_bus):
    bus, run_id = scorer_bus
    spec = EpisodeSpec(circuit="simple", max_sim_seconds=FRAMES * 0.05)
    events = bus.publisher(keys.events(run_id), EpisodeEvent, Traffic.EVENTS)
    poses = bus.publisher(keys.pose(run_id), Pose, Traffic.EVENTS)
    commands = bus.publisher(keys.command(run_id, spec.active_brain), Command, Traffic.COMMANDS)
    scores = subscribe_scores_and_wait(bus, run_id, events, poses, commands)

    def header(seq: int) -> Header:
        return Header(run_id=run_id, episode=0, seq=seq, stamp_ns=seq * spec.step_ns)

    def command(seq: int, speed_mps: float) -> Command:
        return Command(
            header=header(seq), brain=spec.active_brain, frame_seq=seq, speed_mps=speed_mps, yaw_rate_radps=0.0
        )

    points = load_circuit("simple").centreline.points_m
    events.publish(EpisodeEvent(header=header(0), kind=EventKind.START, spec=spec))
    # The scorer's callbacks run on a thread per subscription, so a pose sent at once could be handled before START,
    # and with no simulator to ask for the spec it would be dropped: wait until the scorer has begun the episode.
    wait_for_episode(scores)
    for seq in range(FRAMES + 1):
        x_m, y_m = points[seq % len(points)]
        poses.publish(Pose(header=header(seq), x_m=float(x_m), y_m=float(y_m), yaw_rad=0.0, speed_mps=1.0))
        if seq < FRAMES - 1:
            commands.publish(command(seq, 1.0))  # the same command every frame: no suddenness at all
    events.publish(
        EpisodeEvent(header=header(FRAMES), kind=EventKind.END, reason=EndReason.TIME_LIMIT, last_pose_seq=FRAMES)
    )
    time.sleep(LATE_S)
    assert scores.try_recv() is None, "scored before the driver's last command came"
    commands.publish(command(FRAMES - 1, 3.0))  # the driver's answer to the last frame: a jump of 2 m/s
    received = scores.recv(timeout_s=10.0)
    assert received is not None, "no score"
    assert received.message.metrics.suddenness_distance > 0


@pytest.mark.parametrize(
    "bad_m, said",
    [(math.nan, "got nan - at `$.x_m`"), (1e300, "pose at (1e+300, 1e+300) m: beyond +-1e+06 m")],
    ids=["nan", "1e300"],
)
def test_a_pose_of_nan_from_any_client_is_dropped_and_the_episode_still_scored(scorer_bus, tmp_path, bad_m, said):
    """A client that publishes one Pose with x = y = NaN among the simulator's: the scorer drops it at decode (its
    splines would fail on it at the episode's end), says so once, and scores the episode from the real poses. A
    finite 1e300 decodes, but overflowed the metrics: dropped too."""
    bus, run_id = scorer_bus
    spec = EpisodeSpec(circuit="simple", max_sim_seconds=FRAMES * 0.05)
    events = bus.publisher(keys.events(run_id), EpisodeEvent, Traffic.EVENTS)
    poses = bus.publisher(keys.pose(run_id), Pose, Traffic.EVENTS)
    commands = bus.publisher(keys.command(run_id, spec.active_brain), Command, Traffic.COMMANDS)
    scores = subscribe_scores_and_wait(bus, run_id, events, poses, commands)

    def header(seq: int) -> Header:
        return Header(run_id=run_id, episode=0, seq=seq, stamp_ns=seq * spec.step_ns)

    points = load_circuit("simple").centreline.points_m
    events.publish(EpisodeEvent(header=header(0), kind=EventKind.START, spec=spec))
    wait_for_episode(scores)
    for seq in range(FRAMES + 1):
        x_m, y_m = points[seq % len(points)]
        if seq == FRAMES // 2:  # the intruder's pose for this frame comes first
            poses.publish(Pose(header=header(seq), x_m=bad_m, y_m=bad_m, yaw_rad=0.0))
        poses.publish(Pose(header=header(seq), x_m=float(x_m), y_m=float(y_m), yaw_rad=0.0, speed_mps=1.0))
        if seq < FRAMES:
            commands.publish(
                Command(header=header(seq), brain=spec.active_brain, frame_seq=seq, speed_mps=1.0, yaw_rate_radps=0.0)
            )
    events.publish(
        EpisodeEvent(header=header(FRAMES), kind=EventKind.END, reason=EndReason.TIME_LIMIT, last_pose_seq=FRAMES)
    )
    received = scores.recv(timeout_s=10.0)
    assert received is not None, "no score: " + (tmp_path / "scorer.log").read_text()[-2000:]
    metrics = received.message.metrics
    assert metrics.steps == FRAMES and math.isfinite(metrics.position_deviation_mae) and metrics.progress_m > 0
    log = (tmp_path / "scorer.log").read_text()
    assert log.count("dropped bad message") == 1 and said in log, log
