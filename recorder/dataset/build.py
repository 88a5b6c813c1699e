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

import datetime
import shutil
import uuid
from collections import Counter
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import msgspec
import numpy as np

from recorder.dataset.format import (
    ABS_YAW_RATE_EDGES_RADPS,
    ARRAY_FILES,
    FORMAT_VERSION,
    INDEX_FILES,
    LABEL_NAMES,
    MANIFEST_FILE,
    CircuitSplit,
    DatasetError,
    DatasetManifest,
    DatasetOptions,
    EpisodeInfo,
    EpisodeSplit,
    Histogram,
    LabelStats,
    SourceInfo,
    SplitInfo,
    Totals,
    TrainStats,
    check_offsets,
    describe_offsets,
    parse_split,
    valid_windows,
)
from recorder.dataset.pairing import SampleWriter, SourcePairer, read_source
from recorder.dataset.reading import DrivingDataset, samples_per_second

if TYPE_CHECKING:  # only for annotations: reading.py may pull in the MCAP library, this module must not
    from recorder.reading import Recorded


# -- windows, split, statistics --------------------------------------------------------------------------------------


def _choose_val_episodes(options: DatasetOptions, used: list[dict[str, Any]]) -> set[int]:
    """Dataset episode indices that go to validation; DatasetError when the rule leaves a side empty."""
    rule = parse_split(options.split)
    indices = [info["index"] for info in used]
    if rule is None or (isinstance(rule, EpisodeSplit) and rule.fraction == 0.0):
        return set()
    if isinstance(rule, CircuitSplit):
        circuits = {info["circuit"] for info in used}
        if missing := [name for name in rule.circuits if name not in circuits]:
            raise DatasetError(
                f"split {options.split!r}: no episode with samples on circuit(s) {', '.join(missing)} "
                f"(circuits present: {', '.join(sorted(circuits))})"
            )
        val = {info["index"] for info in used if info["circuit"] in rule.circuits}
    else:
        n_val = max(1, round(rule.fraction * len(indices)))
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
            f"episodes have different step_s ({', '.join(map(str, steps))} s): offsets {describe_offsets(offsets)} "
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
    out_dir = Path(out_dir).resolve()  # "." has no name to put a partial folder beside
    _check_out_dir(out_dir, overwrite)
    # Inside an existing folder, so that nothing is written beside it; beside a new one, so that it appears whole.
    home = out_dir if out_dir.is_dir() else out_dir.parent
    partial = home / f".{out_dir.name}.partial-{uuid.uuid4().hex[:8]}"
    try:
        partial.mkdir(parents=True)
        manifest = _build_into(partial, sources, options, progress)
        _move_into_place(partial, out_dir)
    except OSError as error:
        raise DatasetError(f"cannot write dataset {out_dir}: {error.strerror or error}") from None
    finally:
        shutil.rmtree(partial, ignore_errors=True)
    return manifest


def _check_out_dir(out_dir: Path, overwrite: bool) -> None:
    if out_dir.exists() and not out_dir.is_dir():
        raise DatasetError(f"output {out_dir} exists and is not a folder")
    if out_dir.is_dir() and any(out_dir.iterdir()) and not overwrite:
        raise DatasetError(
            f"output folder {out_dir} is not empty (--overwrite replaces the dataset files in it and keeps the others)"
        )


def _move_into_place(partial: Path, out_dir: Path) -> None:
    """Rename ``partial`` to ``out_dir``, or, where that folder exists, replace only the files a build writes: a
    user's other files there (recordings, notes) are never a dataset's to delete."""
    if not out_dir.exists():
        partial.rename(out_dir)
        return
    # The manifest goes first and comes back last: a build stopped in between leaves no manifest, so the folder never
    # reads as a dataset that mixes two builds.
    (out_dir / MANIFEST_FILE).unlink(missing_ok=True)
    for name in (*ARRAY_FILES, *INDEX_FILES.values(), MANIFEST_FILE):
        (partial / name).replace(out_dir / name)


def _build_into(
    folder: Path,
    sources: Sequence[tuple[str, Callable[[], Iterable[Recorded]]]],
    options: DatasetOptions,
    progress: bool,
) -> DatasetManifest:
    if not sources:
        raise DatasetError("no sources given")
    writer = SampleWriter(folder, options.height_px, options.width_px)
    pairers: list[tuple[str, SourcePairer]] = []
    try:
        next_index = 0
        for name, open_stream in sources:
            pairer = SourcePairer(options, writer, next_index)
            read_source(name, open_stream, pairer, progress)
            _check_runs_unique(name, pairer, pairers)
            pairers.append((name, pairer))
            next_index = pairer.next_index
    finally:
        samples = writer.close()
    if samples == 0:
        raise DatasetError(_no_pairs_message(options, pairers))
    _group_by_episode(folder)
    return _finish(folder, options, pairers, samples)


def _check_runs_unique(name: str, pairer: SourcePairer, earlier: list[tuple[str, SourcePairer]]) -> None:
    """Two sources holding one run (a copied or repaired file) would put the same episode in train and validation."""
    for other_name, other in earlier:
        if shared := [run_id for run_id in pairer.run_ids if run_id in other.run_ids]:
            raise DatasetError(
                f"{name} and {other_name} both hold run {shared[0]!r} (a copy of one recording?): its episodes "
                f"would be in the dataset twice, on both sides of the split; give each run once"
            )


def _no_pairs_message(options: DatasetOptions, pairers: list[tuple[str, SourcePairer]]) -> str:
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
    folder: Path, options: DatasetOptions, pairers: list[tuple[str, SourcePairer]], samples: int
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
    window = f"offsets {describe_offsets(options.offsets_frames)}"
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


# Building is this module's; the format and the reader are re-exported so that ``recorder.dataset.build`` is the one
# name.
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
    "describe_offsets",
    "parse_split",
    "samples_per_second",
    "train_label_stats",
    "valid_windows",
]
