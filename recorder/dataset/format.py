"""The on-disk form of a training dataset (``recorder.dataset.build`` builds it, ``recorder.dataset.reading`` reads it):
its file names, format version, label names, the yaw-rate bins it balances on, its manifest, and the options that
shape its samples (size, crop, frame offsets, split)."""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import msgspec
import numpy as np

from protocol import keys

FORMAT_VERSION = 1
LABEL_NAMES = ("speed_mps", "yaw_rate_radps")
ARRAY_FILES = ("frames.npy", "labels.npy", "episode.npy", "frame_seq.npy", "stamp_ns.npy")
INDEX_FILES = {"train": "train_index.npy", "val": "val_index.npy"}
MANIFEST_FILE = "manifest.json"
# Bin edges of the |yaw rate| histogram (rad/s): DLS's oversampling thresholds (0.3, 0.5, 1, 2, 3, 4) refined below
# 1 rad/s, where a pure-pursuit expert spends most of its time. The last bin is open-ended.
ABS_YAW_RATE_EDGES_RADPS = (0.0, 0.1, 0.2, 0.3, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0, 4.0)
# Unanswered frames held per episode at most: a brain that skips frames (real-time mode) or never answers must not
# grow memory; a lock-step answer comes one frame later, so this is generous (~7.5 MB at 100x50).


class DatasetError(RuntimeError):
    """A dataset that cannot be built or opened: one line naming the source or folder and what is wrong."""


# -- manifest --------------------------------------------------------------------------------------------------------


class _Struct(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """The manifest's base. msgspec passes ``frozen`` on to subclasses, but mypy's dataclass_transform does not: each
    subclass says ``frozen=True`` again, as ``protocol/episode_spec.py``'s noise models do."""


class EpisodeInfo(_Struct, frozen=True):
    """One episode of one source. ``index`` is its dataset-wide episode index (``episode.npy``)."""

    index: int
    run_id: str
    episode: int
    circuit: str
    world: dict[str, Any]
    noise: list[dict[str, Any]]
    camera_width_px: int
    camera_height_px: int
    step_s: float
    seed: int
    active_brain: str
    label_brains: dict[str, int]  # brain -> frames labelled with its commands
    commands_ignored: dict[str, int]  # brain -> commands of brains that were not being labelled
    end_reason: str | None  # None: the recording holds no END event for it
    frames_kept: int
    frames_skipped: dict[str, int]  # reason -> frames: dropped, no_command, duplicate (lock-step resend),
    # bad_frame (payload not rgb8 of its size), bad_label (non-finite command)
    windows: int  # samples whose whole history window lies in this episode
    split: str  # "train", "val" or "unused" (no sample kept)


class SourceInfo(_Struct, frozen=True):
    name: str
    run_ids: list[str]
    messages: int
    frames_outside_episodes: int  # camera frames of an episode whose START is not in this source
    episodes: list[EpisodeInfo]


class LabelStats(_Struct, frozen=True):
    mean: float
    std: float
    min: float
    max: float
    q01: float
    q10: float
    q50: float
    q90: float
    q99: float


class Histogram(_Struct, frozen=True):
    """counts[i]: samples with edges[i] <= |w| < edges[i + 1]; the last bin is open-ended (>= edges[-1])."""

    edges_radps: list[float]
    counts: list[int]


class TrainStats(_Struct, frozen=True):
    """Label statistics of the TRAIN split only (the labels at ``train_index``), raw physical units."""

    samples: int
    speed_mps: LabelStats
    yaw_rate_radps: LabelStats
    abs_yaw_rate_histogram: Histogram


class SplitInfo(_Struct, frozen=True):
    rule: str
    seed: int
    train_episodes: list[int]
    val_episodes: list[int]
    train_samples: int
    val_samples: int


class Totals(_Struct, frozen=True):
    samples: int
    episodes: int
    frames_skipped: dict[str, int]


class DatasetManifest(_Struct, frozen=True):
    """Everything about a dataset folder, as written to ``manifest.json``.

    offsets_s: offsets_frames x step_s, or None when the episodes have different step_s (then only offsets (0,) are
    allowed). image_width_px / image_height_px: the stored frame size.
    """

    format_version: int
    created_utc: str
    options: dict[str, Any]
    image_width_px: int
    image_height_px: int
    label_names: list[str]
    offsets_frames: list[int]
    step_s: float | None
    offsets_s: list[float] | None
    sources: list[SourceInfo]
    totals: Totals
    split: SplitInfo
    train_label_stats: TrainStats


def one_line(error: BaseException) -> str:
    """An exception as one line: its type and the first line of its message."""
    text = str(error).strip().splitlines()
    return f"{type(error).__name__}: {text[0] if text else ''}".rstrip(": ")


def describe_offsets(offsets_frames: Sequence[int]) -> str:
    """Offsets for a message: all of them when few, else the ends and the count (``--history 1000`` is 1,000)."""
    offsets = [int(o) for o in offsets_frames]
    if len(offsets) <= 6:
        return f"({', '.join(map(str, offsets))})"
    return f"({offsets[0]}, {offsets[1]}, ..., {offsets[-2]}, {offsets[-1]}: {len(offsets)} frames)"


def check_offsets(offsets_frames: Sequence[int]) -> tuple[int, ...]:
    """The offsets as a tuple of ints; DatasetError unless they are strictly increasing and end at 0."""
    offsets = tuple(offsets_frames)
    if not offsets or not all(isinstance(o, (int, np.integer)) and not isinstance(o, bool) for o in offsets):
        raise DatasetError(f"bad options: offsets_frames must be a non-empty sequence of ints, got {offsets_frames!r}")
    offsets = tuple(int(o) for o in offsets)
    if offsets[-1] != 0 or any(b <= a for a, b in zip(offsets, offsets[1:])):
        raise DatasetError(
            f"bad options: offsets_frames must be strictly increasing and end at 0, got {describe_offsets(offsets)}"
        )
    return offsets


def valid_windows(episode: np.ndarray, frame_seq: np.ndarray, offsets_frames: Sequence[int]) -> np.ndarray:
    """Indices t (int64) whose samples t + o, for every offset o, exist, lie in t's episode and have
    frame_seq[t + o] == frame_seq[t] + o: a window never crosses an episode or spans a skipped or dropped frame."""
    count = len(episode)
    t = np.arange(count)
    ok = np.ones(count, dtype=bool)
    for offset in offsets_frames:
        if offset == 0:
            continue
        source = t + offset
        ok &= (source >= 0) & (source < count)
        source = np.clip(source, 0, max(count - 1, 0))
        ok &= (episode[source] == episode) & (frame_seq[source] == frame_seq + offset)
    return np.flatnonzero(ok).astype(np.int64)


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
    seed: seeds the episode split (>= 0).
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
        if self.seed < 0:  # numpy's generator would refuse it later, without saying which value
            raise DatasetError(f"bad options: seed must be >= 0, got {self.seed}")

    def to_dict(self) -> dict[str, Any]:
        return {**dataclasses.asdict(self), "offsets_frames": list(self.offsets_frames)}


@dataclass(frozen=True)
class EpisodeSplit:
    """``episode:FRACTION``: this fraction of the episodes with samples, drawn with the dataset's seed, validates."""

    fraction: float


@dataclass(frozen=True)
class CircuitSplit:
    """``circuit:NAME,NAME``: the episodes on these circuits validate."""

    circuits: tuple[str, ...]


def parse_split(split: str) -> EpisodeSplit | CircuitSplit | None:
    """The rule ``split`` names (None for ``none``: no validation); DatasetError for anything else."""
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
        return EpisodeSplit(fraction=fraction)
    if match["circuits"] is not None:
        return CircuitSplit(circuits=tuple(match["circuits"].split(",")))
    return None
