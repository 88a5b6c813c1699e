"""Pairing recorded frames with the commands that answered them, episode by episode, and writing the samples
(``recorder.dataset.build.build_dataset`` streams each recording through a :class:`SourcePairer`)."""

from __future__ import annotations

import math
import sys
from collections import Counter
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import msgspec
import numpy as np
from tqdm import tqdm

from protocol import keys
from protocol.episode_spec import EpisodeSpec
from protocol.images import frame_image
from protocol.messages import CameraFrame, Command, EpisodeEvent, EventKind
from recorder.dataset.format import (
    DatasetError,
    DatasetOptions,
    one_line,
)

if TYPE_CHECKING:  # only for annotations: reading.py may pull in the MCAP library, this module must not
    from recorder.reading import Recorded

MAX_PENDING_FRAMES = 500
MAX_EARLY_COMMANDS = 500


# -- writing ---------------------------------------------------------------------------------------------------------


class _NpyAppender:
    """A .npy file written row by row without knowing the row count in advance.

    numpy leaves spare room in the header for the first axis to grow, so the final shape is written over the
    placeholder on close without moving the data.
    """

    def __init__(self, path: Path, dtype: np.dtype | type, row_shape: tuple[int, ...]):
        self._file = open(path, "wb")
        self._dtype = np.dtype(dtype)
        self._row_shape = row_shape
        self.rows = 0
        self._write_header()
        self._header_bytes = self._file.tell()

    def _write_header(self) -> None:
        np.lib.format.write_array_header_1_0(
            self._file,
            {
                "descr": np.lib.format.dtype_to_descr(self._dtype),
                "fortran_order": False,
                "shape": (self.rows, *self._row_shape),
            },
        )

    def append(self, row: Any) -> None:
        self._file.write(np.asarray(row, dtype=self._dtype).tobytes())
        self.rows += 1

    def close(self) -> None:
        if self._file.closed:
            return
        self._file.seek(0)
        self._write_header()
        if self._file.tell() != self._header_bytes:  # cannot happen below 10**21 rows; never write a corrupt file
            raise RuntimeError("npy header grew while rewriting it")
        self._file.close()


class SampleWriter:
    """The five per-sample arrays of one dataset folder, appended one sample at a time."""

    def __init__(self, folder: Path, height_px: int, width_px: int):
        self.frames = _NpyAppender(folder / "frames.npy", np.uint8, (height_px, width_px, 3))
        self.labels = _NpyAppender(folder / "labels.npy", np.float32, (2,))
        self.episode = _NpyAppender(folder / "episode.npy", np.int32, ())
        self.frame_seq = _NpyAppender(folder / "frame_seq.npy", np.int32, ())
        self.stamp_ns = _NpyAppender(folder / "stamp_ns.npy", np.int64, ())

    def write(self, image: np.ndarray, command: Command, episode: int, seq: int, stamp_ns: int) -> None:
        self.frames.append(image)
        self.labels.append((command.speed_mps, command.yaw_rate_radps))
        self.episode.append(episode)
        self.frame_seq.append(seq)
        self.stamp_ns.append(stamp_ns)

    def close(self) -> int:
        for appender in (self.frames, self.labels, self.episode, self.frame_seq, self.stamp_ns):
            appender.close()
        return self.frames.rows


class _FrameShaper:
    """Crop rows, then resize with INTER_AREA (what the brains do at run time)."""

    def __init__(self, options: DatasetOptions):
        self._options = options

    def __call__(self, frame: CameraFrame) -> np.ndarray:
        image = frame_image(frame)  # ValueError for a bad payload: the caller skips the frame
        height = image.shape[0]
        top = round(self._options.crop_top_fraction * height)
        bottom = round(self._options.crop_bottom_fraction * height)
        if bottom <= top:
            raise DatasetError(
                f"crop {self._options.crop_top_fraction}..{self._options.crop_bottom_fraction} keeps "
                f"no row of a {frame.width_px}x{frame.height_px} frame"
            )
        size = (self._options.width_px, self._options.height_px)
        return cv2.resize(image[top:bottom], size, interpolation=cv2.INTER_AREA)


# -- pairing ---------------------------------------------------------------------------------------------------------


@dataclass
class _Pending:
    image: np.ndarray
    stamp_ns: int
    brain: str  # the brain being labelled when the frame arrived


class _Episode:
    """Pairing state of one episode: frames wait here until the command that answers them arrives."""

    def __init__(self, index: int, run_id: str, number: int, spec: EpisodeSpec, brain: str):
        self.index, self.run_id, self.number, self.spec, self.brain = index, run_id, number, spec, brain
        self.pending: dict[int, _Pending] = {}  # insertion order = seq order: frames arrive in order on a key
        self.early: dict[int, Command] = {}  # commands read before their frame (ties in log-time order)
        self.last_frame_seq = -1
        self.kept = 0
        self.skipped: Counter[str] = Counter()
        self.label_brains: Counter[str] = Counter()
        self.ignored: Counter[str] = Counter()
        self.end_reason: str | None = None

    def drop_pending_before(self, seq: int) -> None:
        """Commands come in frame order, so frames older than an answered one will never be answered."""
        while self.pending and next(iter(self.pending)) < seq:
            del self.pending[next(iter(self.pending))]
            self.skipped["no_command"] += 1

    def close(self, reason: str | None) -> None:
        if self.pending:  # never answered before the episode ended (brain timeout, recording cut)
            self.skipped["no_command"] += len(self.pending)
        self.pending.clear()
        self.early.clear()
        self.end_reason = reason

    def info(self) -> dict[str, Any]:
        spec = self.spec
        return dict(
            index=self.index,
            run_id=self.run_id,
            episode=self.number,
            circuit=spec.circuit,
            world=msgspec.to_builtins(spec.world),
            noise=msgspec.to_builtins(spec.noise),
            camera_width_px=spec.camera.width_px,
            camera_height_px=spec.camera.height_px,
            step_s=spec.step_s,
            seed=spec.seed,
            active_brain=spec.active_brain,
            label_brains=dict(self.label_brains),
            commands_ignored=dict(self.ignored),
            end_reason=self.end_reason,
            frames_kept=self.kept,
            frames_skipped=dict(self.skipped),
        )


class SourcePairer:
    """Feeds one source's messages through per-run episode state and writes every pair as it is made."""

    def __init__(self, options: DatasetOptions, writer: SampleWriter, first_index: int):
        self._options, self._writer, self._next_index = options, writer, first_index
        self.on_pair: Callable[[], None] = lambda: None  # progress
        self._shape = _FrameShaper(options)
        self._current: dict[str, _Episode] = {}  # run id -> its current episode
        self._camera_keys: dict[str, str] = {}
        self.episodes: list[_Episode] = []
        self.run_ids: list[str] = []
        self.messages = 0
        self.frames_outside = 0

    @property
    def next_index(self) -> int:
        return self._next_index

    def feed(self, record: Recorded) -> None:
        self.messages += 1
        message = record.message
        if isinstance(message, CameraFrame):
            if record.key == self._camera_key(message.header.run_id):
                self._on_frame(message)
        elif isinstance(message, Command):
            self._on_command(message)
        elif isinstance(message, EpisodeEvent):
            self._on_event(message)

    def finish(self) -> None:
        for episode in self._current.values():
            episode.close(None)
        self._current.clear()

    def _camera_key(self, run_id: str) -> str:
        if run_id not in self._camera_keys:
            make = keys.camera_perturbed if self._options.camera == "perturbed" else keys.camera_raw
            self._camera_keys[run_id] = make(run_id)
        return self._camera_keys[run_id]

    def _episode_of(self, header) -> _Episode | None:
        episode = self._current.get(header.run_id)
        return episode if episode is not None and episode.number == header.episode else None

    def _on_event(self, event: EpisodeEvent) -> None:
        run_id = event.header.run_id
        if event.kind == EventKind.START and event.spec is not None:
            if (previous := self._current.pop(run_id, None)) is not None:
                previous.close(None)
            brain = self._options.brain or event.spec.active_brain
            started = _Episode(self._next_index, run_id, event.header.episode, event.spec, brain)
            self._next_index += 1
            self._current[run_id] = started
            self.episodes.append(started)
            if run_id not in self.run_ids:
                self.run_ids.append(run_id)
        elif (episode := self._episode_of(event.header)) is not None:
            if event.kind == EventKind.BRAIN_SWITCH and event.brain and self._options.brain is None:
                episode.brain = event.brain  # label with whatever drove the car, as the scorer scores it
            elif event.kind == EventKind.END:
                episode.close(str(event.reason) if event.reason is not None else None)
                del self._current[run_id]

    def _on_frame(self, frame: CameraFrame) -> None:
        episode = self._episode_of(frame.header)
        if episode is None:
            self.frames_outside += 1
            return
        seq = frame.header.seq
        if seq <= episode.last_frame_seq:  # a lock-step resend of a frame already seen
            episode.skipped["duplicate"] += 1
            return
        episode.last_frame_seq = seq
        if frame.dropped:
            episode.skipped["dropped"] += 1
            return
        try:
            image = self._shape(frame)
        except ValueError:
            episode.skipped["bad_frame"] += 1
            return
        for stale in [s for s in episode.early if s < seq]:  # their frames were dropped or never came
            del episode.early[stale]
        command = episode.early.pop(seq, None)
        if command is not None:  # only the labelled brain's commands are kept early
            self._pair(episode, image, frame.header.stamp_ns, seq, command)
            return
        episode.pending[seq] = _Pending(image, frame.header.stamp_ns, episode.brain)
        if len(episode.pending) > MAX_PENDING_FRAMES:
            episode.drop_pending_before(next(iter(episode.pending)) + 1)

    def _on_command(self, command: Command) -> None:
        episode = self._episode_of(command.header)
        if episode is None:
            return
        seq = command.frame_seq
        pending = episode.pending.get(seq)
        if pending is None:
            if command.brain != episode.brain:
                episode.ignored[command.brain] += 1
            elif seq > episode.last_frame_seq and len(episode.early) < MAX_EARLY_COMMANDS:
                episode.early[seq] = command
            return
        if command.brain != pending.brain:
            episode.ignored[command.brain] += 1
            return
        del episode.pending[seq]
        episode.drop_pending_before(seq)
        self._pair(episode, pending.image, pending.stamp_ns, seq, command)

    def _pair(self, episode: _Episode, image: np.ndarray, stamp_ns: int, seq: int, command: Command) -> None:
        if not (math.isfinite(command.speed_mps) and math.isfinite(command.yaw_rate_radps)):
            episode.skipped["bad_label"] += 1  # a NaN label would poison training and the statistics
            return
        self._writer.write(image, command, episode.index, seq, stamp_ns)
        episode.kept += 1
        episode.label_brains[command.brain] += 1
        self.on_pair()


def read_source(name: str, open_stream: Callable[[], Iterable[Recorded]], pairer: SourcePairer, progress: bool) -> None:
    """Stream one source through ``pairer``; a stream that fails becomes a DatasetError naming the source."""
    with tqdm(desc=name, unit=" pairs", disable=not progress, file=sys.stderr, leave=True) as bar:
        pairer.on_pair = lambda: bar.update(1)
        try:
            iterator = iter(open_stream())
        except Exception as error:
            raise DatasetError(f"source {name}: cannot be opened: {one_line(error)}") from error
        while True:
            try:
                record = next(iterator)
            except StopIteration:
                break
            except Exception as error:
                raise DatasetError(
                    f"source {name}: reading failed after {pairer.messages} messages: {one_line(error)}"
                ) from error
            try:
                pairer.feed(record)
            except DatasetError as error:
                raise DatasetError(f"source {name}: {error}") from None
    pairer.finish()
