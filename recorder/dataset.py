"""Training datasets from recorded runs: camera frames paired with the commands that answered them.

Pure core: consumes already-decoded bus messages (``recorder.reading.Recorded``), knows nothing of Zenoh, MCAP or
torch. :func:`build_dataset` streams each recording once and writes a folder of memory-mappable arrays;
:class:`DrivingDataset` reads it back with one vectorised gather per batch.

Folder layout (N samples, one per paired frame, episodes stored contiguously in order of their dataset index,
sequence numbers increasing within an episode):

    frames.npy       uint8   (N, H, W, 3)  RGB, cropped and resized as ``DatasetOptions`` says
    labels.npy       float32 (N, 2)        [speed_mps, yaw_rate_radps] of the command that answered the frame (raw)
    episode.npy      int32   (N,)          dataset-wide episode index (``manifest.sources[*].episodes[*].index``)
    frame_seq.npy    int32   (N,)          ``header.seq`` of the frame within its episode
    stamp_ns.npy     int64   (N,)          ``header.stamp_ns`` of the frame (simulated ns since the episode start)
    train_index.npy  int64   (K,)          samples t whose window t + offsets is complete, in train episodes
    val_index.npy    int64   (M,)          the same for validation episodes
    manifest.json                          :class:`DatasetManifest`
"""

from __future__ import annotations

import dataclasses
import datetime
import math
import re
import shutil
import sys
import uuid
from collections import Counter
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import msgspec
import numpy as np
from tqdm import tqdm

from protocol import keys
from protocol.images import frame_image
from protocol.messages import CameraFrame, Command, EpisodeEvent, EpisodeSpec, EventKind
from recorder.dataset_format import (
    ABS_YAW_RATE_EDGES_RADPS,
    ARRAY_FILES,
    FORMAT_VERSION,
    INDEX_FILES,
    LABEL_NAMES,
    MANIFEST_FILE,
    DatasetError,
    DatasetManifest,
    EpisodeInfo,
    Histogram,
    LabelStats,
    SourceInfo,
    SplitInfo,
    Totals,
    TrainStats,
    check_offsets,
    one_line,
    valid_windows,
)
from recorder.dataset_reading import DrivingDataset, samples_per_second

if TYPE_CHECKING:  # only for annotations: reading.py may pull in the MCAP library, this module must not
    from recorder.reading import Recorded

MAX_PENDING_FRAMES = 500
MAX_EARLY_COMMANDS = 500
_SPLIT = re.compile(r"^(none|episode:(?P<fraction>[0-9.]+)|circuit:(?P<circuits>[^,\s]+(,[^,\s]+)*))$")


@dataclass(frozen=True, kw_only=True)
class DatasetOptions:
    """How recordings become samples.

    width_px, height_px: output image size (the paper's models: 100x50; PilotNet 200x66).
    crop_top_fraction, crop_bottom_fraction: rows kept of the source image, as fractions of its height, before
        resizing (DeepestLSTMTinyPilotNet keeps 0.5..1.0, the lower half).
    camera: "perturbed" (``noise/camera``, what the brain saw and answered) or "truth" (``sim/camera``).
    brain: pair with this brain's commands; None = the episode's active brain (START spec, then BRAIN_SWITCH events).
    offsets_frames: history window in frames relative to the labelled frame t, strictly increasing, ending at 0,
        e.g. (-9, -5, 0); seconds = offset x the episode's step_s.
    split: "episode:FRACTION" (a seeded random choice of whole episodes is validation), "circuit:NAME,NAME" (episodes
        on those circuits are validation) or "none" (everything is training).
    seed: seeds the episode split.
    """

    width_px: int = 100
    height_px: int = 50
    crop_top_fraction: float = 0.0
    crop_bottom_fraction: float = 1.0
    camera: str = "perturbed"
    brain: str | None = None
    offsets_frames: tuple[int, ...] = (0,)
    split: str = "episode:0.2"
    seed: int = 0

    def __post_init__(self) -> None:
        object.__setattr__(self, "offsets_frames", check_offsets(self.offsets_frames))
        if not (1 <= self.width_px <= 4096 and 1 <= self.height_px <= 4096):
            raise DatasetError(
                f"bad options: image size must be 1..4096 px per side, got {self.width_px}x{self.height_px}"
            )
        if not 0.0 <= self.crop_top_fraction < self.crop_bottom_fraction <= 1.0:
            raise DatasetError(
                f"bad options: need 0 <= crop_top_fraction < crop_bottom_fraction <= 1, got "
                f"{self.crop_top_fraction} and {self.crop_bottom_fraction}"
            )
        if self.camera not in ("perturbed", "truth"):
            raise DatasetError(f"bad options: camera must be 'perturbed' or 'truth', got {self.camera!r}")
        if self.brain is not None:
            try:
                keys.check_name(self.brain, what="brain name")
            except ValueError as error:
                raise DatasetError(f"bad options: {error}") from None
        parse_split(self.split)

    def to_dict(self) -> dict[str, Any]:
        return {**dataclasses.asdict(self), "offsets_frames": list(self.offsets_frames)}


def parse_split(split: str) -> tuple[str, float | tuple[str, ...] | None]:
    """("none", None), ("episode", fraction) or ("circuit", names); DatasetError for anything else."""
    match = _SPLIT.match(split)
    if match is None:
        raise DatasetError(
            f"bad options: split must be 'episode:FRACTION', 'circuit:NAME,NAME' or 'none', got {split!r}"
        )
    if match["fraction"] is not None:
        try:
            fraction = float(match["fraction"])
        except ValueError:
            fraction = -1.0
        if not 0.0 <= fraction < 1.0:
            raise DatasetError(f"bad options: split fraction must be within 0 <= f < 1, got {split!r}")
        return "episode", fraction
    if match["circuits"] is not None:
        return "circuit", tuple(match["circuits"].split(","))
    return "none", None


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


class _SampleWriter:
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


class _SourcePairer:
    """Feeds one source's messages through per-run episode state and writes every pair as it is made."""

    def __init__(self, options: DatasetOptions, writer: _SampleWriter, first_index: int):
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
            episode = _Episode(self._next_index, run_id, event.header.episode, event.spec, brain)
            self._next_index += 1
            self._current[run_id] = episode
            self.episodes.append(episode)
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


def _read_source(
    name: str, open_stream: Callable[[], Iterable[Recorded]], pairer: _SourcePairer, progress: bool
) -> None:
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


# -- windows, split, statistics --------------------------------------------------------------------------------------


def _choose_val_episodes(options: DatasetOptions, used: list[dict[str, Any]]) -> set[int]:
    """Dataset episode indices that go to validation; DatasetError when the rule leaves a side empty."""
    kind, value = parse_split(options.split)
    indices = [info["index"] for info in used]
    if kind == "none" or (kind == "episode" and value == 0.0):
        return set()
    if kind == "circuit":
        circuits = {info["circuit"] for info in used}
        if missing := [name for name in value if name not in circuits]:
            raise DatasetError(
                f"split {options.split!r}: no episode with samples on circuit(s) {', '.join(missing)} "
                f"(circuits present: {', '.join(sorted(circuits))})"
            )
        val = {info["index"] for info in used if info["circuit"] in value}
    else:
        n_val = max(1, round(value * len(indices)))
        if n_val >= len(indices):
            raise DatasetError(
                f"split {options.split!r}: {len(indices)} episode(s) with samples cannot be split into "
                f"train and val (use 'episode:0' or 'none' for no validation)"
            )
        chosen = np.random.default_rng(options.seed).choice(len(indices), size=n_val, replace=False)
        val = {indices[i] for i in chosen}
    if len(val) == len(indices):
        raise DatasetError(f"split {options.split!r} leaves no episode for training")
    return val


def _label_stats(values: np.ndarray) -> LabelStats:
    q01, q10, q50, q90, q99 = np.quantile(values, (0.01, 0.10, 0.50, 0.90, 0.99))
    return LabelStats(
        mean=float(values.mean()),
        std=float(values.std()),
        min=float(values.min()),
        max=float(values.max()),
        q01=float(q01),
        q10=float(q10),
        q50=float(q50),
        q90=float(q90),
        q99=float(q99),
    )


def train_label_stats(labels: np.ndarray) -> TrainStats:
    """Statistics of an (n, 2) array of [speed_mps, yaw_rate_radps] labels (n >= 1)."""
    values = labels.astype(np.float64)
    edges = np.array(ABS_YAW_RATE_EDGES_RADPS)
    bins = np.searchsorted(edges, np.abs(values[:, 1]), side="right") - 1
    counts = np.bincount(bins, minlength=len(edges))
    return TrainStats(
        samples=len(values),
        speed_mps=_label_stats(values[:, 0]),
        yaw_rate_radps=_label_stats(values[:, 1]),
        abs_yaw_rate_histogram=Histogram(edges_radps=list(ABS_YAW_RATE_EDGES_RADPS), counts=[int(c) for c in counts]),
    )


def _common_step_s(used: list[dict[str, Any]], offsets: tuple[int, ...]) -> float | None:
    steps = sorted({info["step_s"] for info in used})
    if len(steps) == 1:
        return steps[0]
    if len(offsets) > 1:
        raise DatasetError(
            f"episodes have different step_s ({', '.join(map(str, steps))} s): offsets {offsets} "
            f"would span different times; build one dataset per step_s"
        )
    return None


def _group_by_episode(folder: Path) -> None:
    """Make each episode's samples contiguous (a source holding two runs at once interleaves them). Stable, so
    frame_seq stays increasing within an episode. Rewrites the arrays only when they are interleaved."""
    episode = np.load(folder / "episode.npy")
    if len(episode) == 0 or np.all(np.diff(episode) >= 0):
        return
    order = np.argsort(episode, kind="stable")
    for name in ARRAY_FILES:
        source = np.load(folder / name, mmap_mode="r")
        target = np.lib.format.open_memmap(folder / f"sorted-{name}", mode="w+", dtype=source.dtype, shape=source.shape)
        for start in range(0, len(order), 4096):  # bounded memory for frames
            target[start : start + 4096] = source[order[start : start + 4096]]
        target.flush()
        del source, target
        (folder / f"sorted-{name}").replace(folder / name)


# -- build -----------------------------------------------------------------------------------------------------------


def build_dataset(
    sources: Sequence[tuple[str, Callable[[], Iterable[Recorded]]]],
    *,
    out_dir: Path,
    options: DatasetOptions,
    progress: bool = True,
    overwrite: bool = False,
) -> DatasetManifest:
    """Pair camera frames with the commands that answered them, over every source, into the folder ``out_dir``.

    sources: (name, open) pairs; ``open()`` returns a fresh iterable of one recording's decoded messages. Each source
        is read once, in order; memory stays bounded (frames are resized on arrival and held only until answered).
    A sample is a frame of ``options.camera`` paired by (run id, episode, frame_seq == frame seq) with the command of
    the labelled brain; label = (speed_mps, yaw_rate_radps), raw. The folder is written next to ``out_dir`` and
    renamed into place when complete. Raises DatasetError (one line) for bad input, an existing non-empty
    ``out_dir`` without ``overwrite``, no pairs at all, or a split that leaves train (or val, unless asked) empty.
    """
    out_dir = Path(out_dir)
    _check_out_dir(out_dir, overwrite)
    partial = out_dir.parent / f".{out_dir.name}.partial-{uuid.uuid4().hex[:8]}"
    partial.mkdir(parents=True)
    try:
        manifest = _build_into(partial, sources, options, progress)
        _move_into_place(partial, out_dir)
    except BaseException:
        shutil.rmtree(partial, ignore_errors=True)
        raise
    return manifest


def _check_out_dir(out_dir: Path, overwrite: bool) -> None:
    if out_dir.exists() and not out_dir.is_dir():
        raise DatasetError(f"output {out_dir} exists and is not a folder")
    if out_dir.is_dir() and any(out_dir.iterdir()) and not overwrite:
        raise DatasetError(f"output folder {out_dir} is not empty (pass overwrite=True to replace it)")


def _move_into_place(partial: Path, out_dir: Path) -> None:
    if out_dir.exists():
        old = out_dir.parent / f".{out_dir.name}.old-{uuid.uuid4().hex[:8]}"
        out_dir.rename(old)
        partial.rename(out_dir)
        shutil.rmtree(old, ignore_errors=True)
    else:
        partial.rename(out_dir)


def _build_into(
    folder: Path,
    sources: Sequence[tuple[str, Callable[[], Iterable[Recorded]]]],
    options: DatasetOptions,
    progress: bool,
) -> DatasetManifest:
    if not sources:
        raise DatasetError("no sources given")
    writer = _SampleWriter(folder, options.height_px, options.width_px)
    pairers: list[tuple[str, _SourcePairer]] = []
    try:
        next_index = 0
        for name, open_stream in sources:
            pairer = _SourcePairer(options, writer, next_index)
            _read_source(name, open_stream, pairer, progress)
            pairers.append((name, pairer))
            next_index = pairer.next_index
    finally:
        samples = writer.close()
    if samples == 0:
        raise DatasetError(_no_pairs_message(options, pairers))
    _group_by_episode(folder)
    return _finish(folder, options, pairers, samples)


def _no_pairs_message(options: DatasetOptions, pairers: list[tuple[str, _SourcePairer]]) -> str:
    brain = options.brain or "the active brain"
    parts = []
    for name, pairer in pairers:
        skipped = sum((episode.skipped for episode in pairer.episodes), Counter())
        parts.append(
            f"{name}: {len(pairer.episodes)} episode(s), frames skipped {dict(skipped)}, "
            f"{pairer.frames_outside} frame(s) of episodes without a START event"
        )
    return f"no {options.camera} camera frame was paired with a command of {brain} in any source ({'; '.join(parts)})"


def _finish(
    folder: Path, options: DatasetOptions, pairers: list[tuple[str, _SourcePairer]], samples: int
) -> DatasetManifest:
    episode = np.load(folder / "episode.npy")
    windows = valid_windows(episode, np.load(folder / "frame_seq.npy"), options.offsets_frames)
    infos = [(name, pairer, [e.info() for e in pairer.episodes]) for name, pairer in pairers]
    used = [info for _, _, episodes in infos for info in episodes if info["frames_kept"] > 0]
    step_s = _common_step_s(used, options.offsets_frames)
    val_episodes = _choose_val_episodes(options, used)
    train_episodes = {info["index"] for info in used} - val_episodes
    train_index = windows[np.isin(episode[windows], sorted(train_episodes))]
    val_index = windows[np.isin(episode[windows], sorted(val_episodes))]
    _check_split_sides(options, train_index, val_index, val_episodes)
    np.save(folder / INDEX_FILES["train"], train_index)
    np.save(folder / INDEX_FILES["val"], val_index)
    _annotate_episodes([info for _, _, episodes in infos for info in episodes], episode[windows], val_episodes)
    manifest = _manifest(
        options,
        infos,
        samples,
        step_s,
        train_index,
        val_index,
        train_episodes,
        val_episodes,
        np.load(folder / "labels.npy")[train_index],
    )
    (folder / MANIFEST_FILE).write_bytes(msgspec.json.format(msgspec.json.encode(manifest), indent=2))
    return manifest


def _annotate_episodes(infos: list[dict[str, Any]], window_episodes: np.ndarray, val_episodes: set[int]) -> None:
    """Add each episode's window count and split side to its manifest entry."""
    counts = dict(zip(*(u.tolist() for u in np.unique(window_episodes, return_counts=True))))
    for info in infos:
        info["windows"] = counts.get(info["index"], 0)
        info["split"] = "unused" if info["frames_kept"] == 0 else "val" if info["index"] in val_episodes else "train"


def _check_split_sides(
    options: DatasetOptions, train_index: np.ndarray, val_index: np.ndarray, val_episodes: set[int]
) -> None:
    window = f"offsets {options.offsets_frames}"
    if len(train_index) == 0:
        raise DatasetError(f"split {options.split!r}: no training sample has a complete window for {window}")
    if val_episodes and len(val_index) == 0:
        raise DatasetError(
            f"split {options.split!r}: validation episodes {sorted(val_episodes)} have no complete window for {window}"
        )


def _manifest(
    options: DatasetOptions,
    infos,
    samples: int,
    step_s: float | None,
    train_index: np.ndarray,
    val_index: np.ndarray,
    train_episodes: set[int],
    val_episodes: set[int],
    train_labels: np.ndarray,
) -> DatasetManifest:
    sources = [
        SourceInfo(
            name=name,
            run_ids=list(pairer.run_ids),
            messages=pairer.messages,
            frames_outside_episodes=pairer.frames_outside,
            episodes=[msgspec.convert(info, EpisodeInfo) for info in episodes],
        )
        for name, pairer, episodes in infos
    ]
    skipped: Counter[str] = Counter()
    for _, pairer, _ in infos:
        for episode in pairer.episodes:
            skipped.update(episode.skipped)
    return DatasetManifest(
        format_version=FORMAT_VERSION,
        created_utc=datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        options=options.to_dict(),
        image_width_px=options.width_px,
        image_height_px=options.height_px,
        label_names=list(LABEL_NAMES),
        offsets_frames=list(options.offsets_frames),
        step_s=step_s,
        offsets_s=None if step_s is None else [round(o * step_s, 9) for o in options.offsets_frames],
        sources=sources,
        totals=Totals(samples=samples, episodes=sum(len(s.episodes) for s in sources), frames_skipped=dict(skipped)),
        split=SplitInfo(
            rule=options.split,
            seed=options.seed,
            train_episodes=sorted(train_episodes),
            val_episodes=sorted(val_episodes),
            train_samples=len(train_index),
            val_samples=len(val_index),
        ),
        train_label_stats=train_label_stats(train_labels),
    )


# Building is this module's; the format and the reader are re-exported so that ``recorder.dataset`` is the one name.
__all__ = [
    "ABS_YAW_RATE_EDGES_RADPS",
    "ARRAY_FILES",
    "FORMAT_VERSION",
    "INDEX_FILES",
    "LABEL_NAMES",
    "MANIFEST_FILE",
    "DatasetError",
    "DatasetManifest",
    "DatasetOptions",
    "DrivingDataset",
    "EpisodeInfo",
    "Histogram",
    "LabelStats",
    "SourceInfo",
    "SplitInfo",
    "Totals",
    "TrainStats",
    "build_dataset",
    "check_offsets",
    "parse_split",
    "samples_per_second",
    "train_label_stats",
    "valid_windows",
]
