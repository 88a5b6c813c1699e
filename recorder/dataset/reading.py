"""Reading a dataset folder back (``drivebench train``): memory-mapped arrays, one vectorised gather per batch."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import msgspec
import numpy as np

from recorder.dataset.format import (
    ARRAY_FILES,
    FORMAT_VERSION,
    INDEX_FILES,
    MANIFEST_FILE,
    DatasetError,
    DatasetManifest,
    check_offsets,
    one_line,
    valid_windows,
)

# -- reading ---------------------------------------------------------------------------------------------------------


class DrivingDataset:
    """One split of a dataset folder: sample i = (frames at t + offsets, label at t), t = the split's i-th window.

    split: "train", "val" or "all" (both). offsets_frames: None = the manifest's (the stored index); other offsets
    (strictly increasing, ending at 0) recompute the valid windows from the episode and frame_seq arrays.
    Frames are memory-mapped, never loaded whole. Raises DatasetError (one line) for a missing file or bad manifest.
    """

    def __init__(self, path: Path, *, split: str = "train", offsets_frames: tuple[int, ...] | None = None):
        self.path = Path(path)
        if split not in ("train", "val", "all"):
            raise DatasetError(f"dataset {self.path}: split must be 'train', 'val' or 'all', got {split!r}")
        self.split = split
        self._typed = _load_manifest(self.path)
        self.manifest: dict[str, Any] = msgspec.to_builtins(self._typed)
        self.frames, self.labels, self.episode, self.frame_seq, self.stamp_ns = _load_arrays(self.path, self._typed)
        if offsets_frames is None:
            self.offsets_frames = tuple(self._typed.offsets_frames)
            self._index = self._stored_index()
        else:
            self.offsets_frames = check_offsets(offsets_frames)
            self._index = self._recomputed_index()
        self._offsets = np.asarray(self.offsets_frames, dtype=np.int64)

    def _stored_index(self) -> np.ndarray:
        names = ("train", "val") if self.split == "all" else (self.split,)
        parts = [_load_index(self.path, INDEX_FILES[name], len(self.frames)) for name in names]
        return np.sort(np.concatenate(parts))

    def _recomputed_index(self) -> np.ndarray:
        split = self._typed.split
        episodes = {
            "train": split.train_episodes,
            "val": split.val_episodes,
            "all": split.train_episodes + split.val_episodes,
        }[self.split]
        windows = valid_windows(self.episode, self.frame_seq, self.offsets_frames)
        return windows[np.isin(self.episode[windows], episodes)]

    @property
    def index(self) -> np.ndarray:
        """Sample indices t (into the arrays) of this split's windows."""
        return self._index

    def __len__(self) -> int:
        return len(self._index)

    def __getitem__(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """(frames uint8 (T, H, W, 3) oldest first, label float32 (2,) [speed_mps, yaw_rate_radps] at the last)."""
        t = int(self._index[i])
        return np.asarray(self.frames[t + self._offsets]), np.asarray(self.labels[t])

    def batch(self, indices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One gather for many items: (frames uint8 (B, T, H, W, 3), labels float32 (B, 2))."""
        t = self._index[np.asarray(indices, dtype=np.int64)]
        rows = (t[:, None] + self._offsets[None, :]).reshape(-1)
        frames = np.asarray(self.frames[rows]).reshape(len(t), len(self._offsets), *self.frames.shape[1:])
        return frames, np.asarray(self.labels[t])


def _load_manifest(path: Path) -> DatasetManifest:
    if not path.is_dir():
        raise DatasetError(f"dataset {path}: not a folder")
    try:
        raw = (path / MANIFEST_FILE).read_bytes()
    except OSError as error:
        raise DatasetError(f"dataset {path}: cannot read {MANIFEST_FILE}: {error.strerror or error}") from None
    try:
        version = json.loads(raw).get("format_version")
    except (ValueError, AttributeError) as error:
        raise DatasetError(f"dataset {path}: {MANIFEST_FILE} is not a JSON object: {one_line(error)}") from None
    if version != FORMAT_VERSION:
        raise DatasetError(
            f"dataset {path}: {MANIFEST_FILE} format_version {version!r}, this reader knows {FORMAT_VERSION}"
        )
    try:
        return msgspec.json.decode(raw, type=DatasetManifest)
    except (msgspec.ValidationError, msgspec.DecodeError) as error:
        raise DatasetError(f"dataset {path}: bad {MANIFEST_FILE}: {one_line(error)}") from None


def _load_arrays(path: Path, manifest: DatasetManifest) -> tuple[np.ndarray, ...]:
    if missing := [name for name in (*ARRAY_FILES, *INDEX_FILES.values()) if not (path / name).is_file()]:
        raise DatasetError(f"dataset {path}: missing {', '.join(missing)}")
    n = manifest.totals.samples
    expected = {
        "frames.npy": (np.uint8, (n, manifest.image_height_px, manifest.image_width_px, 3)),
        "labels.npy": (np.float32, (n, 2)),
        "episode.npy": (np.int32, (n,)),
        "frame_seq.npy": (np.int32, (n,)),
        "stamp_ns.npy": (np.int64, (n,)),
    }
    arrays = []
    for name, (dtype, shape) in expected.items():
        array = _load_npy(path, name, mmap=name == "frames.npy")
        if array.dtype != dtype or array.shape != shape:
            raise DatasetError(
                f"dataset {path}: {name} is {array.dtype} {array.shape}, the manifest says {np.dtype(dtype)} {shape}"
            )
        arrays.append(array)
    return tuple(arrays)


def _load_npy(path: Path, name: str, *, mmap: bool) -> np.ndarray:
    try:
        return np.load(path / name, mmap_mode="r" if mmap else None, allow_pickle=False)
    except (OSError, ValueError) as error:
        raise DatasetError(f"dataset {path}: cannot read {name}: {one_line(error)}") from None


def _load_index(path: Path, name: str, samples: int) -> np.ndarray:
    index = _load_npy(path, name, mmap=False)
    if index.dtype != np.int64 or index.ndim != 1 or (len(index) and not 0 <= index.min() <= index.max() < samples):
        raise DatasetError(f"dataset {path}: {name} is not an int64 index into {samples} samples")
    return index


def samples_per_second(dataset: DrivingDataset, batch_size: int = 64, seconds: float = 2.0, seed: int = 0) -> float:
    """Items per second that ``dataset.batch`` delivers for random batches of ``batch_size``, over ``seconds``
    (after one warm-up batch)."""
    if len(dataset) == 0:
        raise DatasetError(f"dataset {dataset.path}: the {dataset.split} split is empty")
    rng = np.random.default_rng(seed)
    dataset.batch(rng.integers(0, len(dataset), batch_size))
    items = 0
    start = time.perf_counter()
    while (elapsed := time.perf_counter() - start) < seconds:
        dataset.batch(rng.integers(0, len(dataset), batch_size))
        items += batch_size
    return items / elapsed
