"""Small real recordings: every recorded message kind of one run, the schemas each topic is written with, and
episodes of camera frames and commands for the dataset tests."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path

import msgspec
import numpy as np

from protocol import keys
from protocol.episode_spec import CameraSpec, EpisodeSpec, Gaussian
from protocol.episodes import start_event
from protocol.images import image_frame
from protocol.mapping import topics
from protocol.messages import (
    CameraFrame,
    Command,
    EndReason,
    EpisodeEvent,
    EpisodeMetrics,
    EpisodeScore,
    EventKind,
    Header,
    LiveMetrics,
    Pose,
)
from recorder.reading import Recorded
from recorder.writer import RecordingWriter

LEGACY = Path(__file__).resolve().parents[1] / "fixtures" / "legacy-run-topics.mcap"  # see fixtures/README.md


_JSON_SCHEMAS = {
    topics.CAR_STATE: "drivebench.Pose.v1",
    topics.EPISODE_EVENTS: "drivebench.EpisodeEvent.v1",
    topics.METRICS_LIVE: "drivebench.LiveMetrics.v1",
    topics.EPISODE_SCORE: "drivebench.EpisodeScore.v1",
}


_VIEW_SCHEMAS = {
    topics.CAR_POSE: "foxglove.PoseInFrame",
    topics.TF: "foxglove.FrameTransform",
    topics.CIRCUIT: "foxglove.SceneUpdate",
    topics.EPISODE_LOG: "foxglove.Log",
}


def expected_schemas(published: set[str], *, image: str) -> dict[str, str]:
    """Schema name of every topic in ``published``, as recordings (image "raw" or "jpeg") and the live view ("jpeg")
    write them; the recording and live-view tests share it."""
    image_schema = {"raw": "foxglove.RawImage", "jpeg": "foxglove.CompressedImage"}[image]
    schemas = {topics.CAMERA_TRUTH: image_schema, topics.CAMERA_BRAIN: image_schema, **_JSON_SCHEMAS, **_VIEW_SCHEMAS}
    return {t: schemas.get(t, "drivebench.Command.v1" if t.startswith("/brain/") else "?") for t in published}


def zero_metrics() -> EpisodeMetrics:
    """Metrics with every field zero / empty (the values do not matter here)."""
    values = {}
    for field in msgspec.structs.fields(EpisodeMetrics):
        empty = False if field.type is bool else 0
        values[field.name] = [] if "list" in str(field.type) else None if "None" in str(field.type) else empty
    return msgspec.convert(values, EpisodeMetrics)


def one_run(run_id: str, *, brain: str = "explicit", steps: int = 25) -> list[tuple[str, msgspec.Struct]]:
    """Every kind of recorded message of one run: START (a real circuit, so the track is drawn), per step two
    cameras, a pose and a command, live metrics, a lap, END and the score."""
    spec = EpisodeSpec(circuit="simple", active_brain=brain)

    def header(seq: int) -> Header:
        return Header(run_id=run_id, episode=0, seq=seq, stamp_ns=seq * 50_000_000)

    messages: list[tuple[str, msgspec.Struct]] = [(keys.events(run_id), start_event(run_id, 0, spec))]
    for seq in range(steps):
        pixels = np.full((6, 8, 3), seq % 256, np.uint8).tobytes()
        messages += [
            (keys.camera_raw(run_id), CameraFrame(header=header(seq), width_px=8, height_px=6, data=pixels)),
            (keys.camera_perturbed(run_id), CameraFrame(header=header(seq), width_px=8, height_px=6, data=pixels)),
            (
                keys.pose(run_id),
                Pose(
                    header=header(seq),
                    x_m=0.1 * seq,
                    y_m=1.0,
                    yaw_rad=0.1,
                    speed_mps=2.0,
                    yaw_rate_radps=0.3,
                    command_latency_ns=1_000_000,
                ),
            ),
            (
                keys.command(run_id, brain),
                Command(header=header(seq), brain=brain, frame_seq=seq, speed_mps=2.0, yaw_rate_radps=0.3),
            ),
        ]
    messages += [
        (
            keys.live_metrics(run_id),
            LiveMetrics(
                header=header(0),
                progress_laps=0.1,
                laps_target=1,
                completed_laps=0,
                sim_time_s=1.0,
                real_time_factor=3.0,
                cross_track_m=0.02,
                speed_mps=2.0,
            ),
        ),
        (keys.events(run_id), EpisodeEvent(header=header(1), kind=EventKind.LAP, lap=1)),
        (keys.events(run_id), EpisodeEvent(header=header(2), kind=EventKind.END, reason=EndReason.LAPS_COMPLETED)),
        (
            keys.score(run_id),
            EpisodeScore(
                header=header(0), spec=spec, reason=EndReason.LAPS_COMPLETED, brain=brain, metrics=zero_metrics()
            ),
        ),
    ]
    return messages


def write(path: Path, messages, *, run_id: str, image_format: str = "raw") -> Path:
    with RecordingWriter(path, image_format=image_format) as writer:
        writer.add_metadata("drivebench.run", {"run_id": run_id})
        for key, message in messages:
            writer.write(key, message)
    return path


WIDTH, HEIGHT = 40, 20


STEP_NS = 50_000_000


def episode_stream(
    run_id: str = "r1",
    episode: int = 0,
    frames: int = 30,
    *,
    circuit: str = "simple",
    brains: tuple[str, ...] = ("pilot", "other"),
    active: str = "pilot",
    dropped: frozenset = frozenset(),
    unanswered: frozenset = frozenset(),
    resent: frozenset = frozenset(),
    switch_at: int | None = None,
    switch_to: str = "other",
    speed: Callable | None = None,
    lag: int = 1,
    step_s: float = 0.05,
) -> Iterator[Recorded]:
    """One episode as the bus carries it: START, then per step truth frame, perturbed frame, pose, and commands
    that answer a frame ``lag`` steps later (so frames wait for their command); END."""
    spec = EpisodeSpec(
        circuit=circuit,
        active_brain=active,
        seed=7,
        noise=[Gaussian(sigma=3.0)],
        step_s=step_s,
        camera=CameraSpec(width_px=WIDTH, height_px=HEIGHT),
    )
    events = keys.events(run_id)
    event_seq = 0

    def header(seq: int, stamp_ns: int | None = None) -> Header:
        return Header(run_id=run_id, episode=episode, seq=seq, stamp_ns=seq * STEP_NS if stamp_ns is None else stamp_ns)

    yield Recorded(events, EpisodeEvent(header=header(event_seq, 0), kind=EventKind.START, spec=spec), 0)
    event_seq += 1
    waiting: list[int] = []
    for seq in range(frames + lag):
        if seq < frames:
            if seq == switch_at:
                yield Recorded(
                    events,
                    EpisodeEvent(header=header(event_seq), kind=EventKind.BRAIN_SWITCH, brain=switch_to),
                    seq * STEP_NS,
                )
                event_seq += 1
            yield from frame_records(run_id, header(seq), seq, dropped=seq in dropped)
            if seq in resent:  # a lock-step resend: the same frame again
                yield from frame_records(run_id, header(seq), seq, dropped=seq in dropped)
            waiting.append(seq)
        if len(waiting) > lag or seq >= frames:
            answered = waiting.pop(0)
            if answered not in unanswered:
                yield from command_records(run_id, episode, answered, brains, speed)
    yield Recorded(
        events,
        EpisodeEvent(header=header(event_seq), kind=EventKind.END, reason=EndReason.LAPS_COMPLETED),
        frames * STEP_NS,
    )


def frame_records(run_id: str, header: Header, seq: int, *, dropped: bool) -> Iterator[Recorded]:
    truth = image_frame(header, pixels(seq))
    yield Recorded(keys.camera_raw(run_id), truth, header.stamp_ns)
    perturbed = (
        CameraFrame(header=header, width_px=WIDTH, height_px=HEIGHT, data=b"", dropped=True)
        if dropped
        else image_frame(header, pixels(seq))
    )
    yield Recorded(keys.camera_perturbed(run_id), perturbed, header.stamp_ns)
    yield Recorded(keys.pose(run_id), Pose(header=header, x_m=0.1 * seq, y_m=0.0, yaw_rad=0.0), header.stamp_ns)


def command_records(
    run_id: str, episode: int, seq: int, brains: tuple[str, ...], speed: Callable | None
) -> Iterator[Recorded]:
    for count, brain in enumerate(brains):
        v, w = label(brain, episode, seq)
        if speed is not None:
            v = speed(brain, episode, seq)
        header = Header(run_id=run_id, episode=episode, seq=seq, stamp_ns=seq * STEP_NS)
        yield Recorded(
            keys.command(run_id, brain),
            Command(header=header, brain=brain, frame_seq=seq, speed_mps=v, yaw_rate_radps=w),
            seq * STEP_NS + count,
        )


def pixels(seq: int) -> np.ndarray:
    rows = np.arange(HEIGHT, dtype=np.uint8)[:, None] * 10
    cols = np.where(np.isin(np.arange(WIDTH) % 4, (0, 3)), 240, 0).astype(np.uint8)[None, :]
    image = np.empty((HEIGHT, WIDTH, 3), dtype=np.uint8)
    image[..., 0] = seq % 256
    image[..., 1] = np.broadcast_to(rows, (HEIGHT, WIDTH))
    image[..., 2] = np.broadcast_to(cols, (HEIGHT, WIDTH))
    return image


def label(brain: str, episode: int, seq: int) -> tuple[float, float]:
    """Each brain answers differently; values depend on episode and seq so a wrong pairing shows."""
    base = {"pilot": 1.0, "other": 50.0, "second": 20.0}[brain]
    return base + episode + seq * 0.01, (-1) ** seq * (0.05 * (seq % 7)) + episode * 0.001
