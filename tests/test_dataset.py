"""recorder.dataset.build: recorded bus messages -> memory-mapped training datasets, and reading them back.

Streams are built from real protocol messages. Every camera frame encodes who it is in its pixels: channel 0 is
``seq % 256`` everywhere, channel 1 is a row gradient (10 per row), channel 2 repeats columns (240, 0, 0, 240) (its
4-column mean, 120, is what area averaging gives and bilinear sampling does not), so pairing, cropping and resizing
can be checked from pixel content alone.
"""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
from support.recordings import HEIGHT, STEP_NS, WIDTH, episode_stream, label

from protocol import keys
from protocol.messages import (
    Command,
    EpisodeEvent,
)
from recorder.dataset.build import (
    DatasetError,
    DatasetOptions,
    DrivingDataset,
    build_dataset,
    samples_per_second,
    valid_windows,
)
from recorder.reading import Recorded


def source(name: str, *streams: Callable[[], Iterator[Recorded]]) -> tuple[str, Callable[[], Iterator[Recorded]]]:
    def open_stream() -> Iterator[Recorded]:
        for stream in streams:
            yield from stream()

    return name, open_stream


def ep(**kwargs) -> Callable[[], Iterator[Recorded]]:
    return lambda: episode_stream(**kwargs)


def build(tmp_path: Path, *sources, name: str = "ds", **options) -> tuple[Path, dict]:
    out = tmp_path / name
    options = {"width_px": WIDTH, "height_px": HEIGHT, "split": "none", **options}
    build_dataset(list(sources), out_dir=out, options=DatasetOptions(**options), progress=False)
    return out, json.loads((out / "manifest.json").read_text())


def arrays(out: Path) -> dict[str, np.ndarray]:
    return {
        name: np.load(out / f"{name}.npy")
        for name in ("frames", "labels", "episode", "frame_seq", "stamp_ns", "train_index", "val_index")
    }


# -- pairing -----------------------------------------------------------------------------------------------------------


def test_labels_are_the_commands_that_answered_exactly_those_frames(tmp_path):
    out, manifest = build(tmp_path, source("a.mcap", ep(frames=30, lag=2)))
    a = arrays(out)
    assert len(a["labels"]) == 30
    assert a["frame_seq"].tolist() == list(range(30))
    for i, seq in enumerate(a["frame_seq"]):
        assert int(a["frames"][i, 0, 0, 0]) == seq  # the image is the frame with that seq
        np.testing.assert_allclose(a["labels"][i], label("pilot", 0, int(seq)), rtol=1e-6)
        assert a["stamp_ns"][i] == seq * STEP_NS
    assert a["labels"].dtype == np.float32 and a["labels"].shape == (30, 2)
    assert a["frames"].dtype == np.uint8 and a["frames"].shape == (30, HEIGHT, WIDTH, 3)
    assert manifest["sources"][0]["episodes"][0]["label_brains"] == {"pilot": 30}


def test_commands_of_a_brain_that_is_not_active_are_ignored(tmp_path):
    out, manifest = build(tmp_path, source("a.mcap", ep(frames=20, active="pilot", brains=("other", "pilot"))))
    labels = arrays(out)["labels"]
    assert np.all(labels[:, 0] < 2.0)  # pilot's speeds are ~1, the other brain's ~50
    assert manifest["sources"][0]["episodes"][0]["commands_ignored"] == {"other": 20}


def test_an_explicit_brain_is_paired_instead_of_the_active_one(tmp_path):
    out, _ = build(tmp_path, source("a.mcap", ep(frames=10)), brain="other")
    labels = arrays(out)["labels"]
    np.testing.assert_allclose(labels[:, 0], [label("other", 0, s)[0] for s in range(10)], rtol=1e-6)


def test_a_brain_switch_changes_which_brain_labels_the_frames(tmp_path):
    out, manifest = build(tmp_path, source("a.mcap", ep(frames=20, switch_at=12)))
    a = arrays(out)
    assert np.all(a["labels"][a["frame_seq"] < 12, 0] < 2.0)
    assert np.all(a["labels"][a["frame_seq"] >= 12, 0] > 49.0)
    assert manifest["sources"][0]["episodes"][0]["label_brains"] == {"pilot": 12, "other": 8}


def test_truth_camera_pairs_ground_truth_frames_even_where_the_perturbed_one_was_dropped(tmp_path):
    stream = ep(frames=10, dropped=frozenset({4}))
    _, perturbed = build(tmp_path, source("a", stream), name="p")
    out, truth = build(tmp_path, source("a", stream), name="t", camera="truth")
    assert perturbed["totals"]["samples"] == 9 and perturbed["totals"]["frames_skipped"] == {"dropped": 1}
    assert truth["totals"]["samples"] == 10
    assert arrays(out)["frame_seq"].tolist() == list(range(10))


def test_resent_frames_give_one_sample_and_unanswered_frames_are_skipped(tmp_path):
    out, manifest = build(tmp_path, source("a", ep(frames=12, resent=frozenset({3}), unanswered=frozenset({7}))))
    assert arrays(out)["frame_seq"].tolist() == [0, 1, 2, 3, 4, 5, 6, 8, 9, 10, 11]
    assert manifest["sources"][0]["episodes"][0]["frames_skipped"] == {"duplicate": 1, "no_command": 1}


def test_a_command_read_before_its_frame_still_pairs(tmp_path):
    def commands_first() -> Iterator[Recorded]:  # equal log times may come back in either order
        held = None
        for record in episode_stream(frames=10, lag=0):
            if record.key == keys.camera_perturbed("r1"):
                held = record
                continue
            yield record
            if isinstance(record.message, Command) and record.message.brain == "other":
                yield held

    out, manifest = build(tmp_path, source("a", commands_first))
    a = arrays(out)
    assert a["frame_seq"].tolist() == list(range(10))
    np.testing.assert_allclose(a["labels"][:, 0], [label("pilot", 0, s)[0] for s in range(10)], rtol=1e-6)
    assert manifest["totals"]["frames_skipped"] == {}


def test_progress_bar_names_the_source_on_stderr(tmp_path, capsys):
    options = DatasetOptions(width_px=WIDTH, height_px=HEIGHT, split="none")
    build_dataset([source("run-42.mcap", ep(frames=5))], out_dir=tmp_path / "ds", options=options, progress=True)
    captured = capsys.readouterr()
    assert "run-42.mcap" in captured.err and "run-42.mcap" not in captured.out


def test_frames_before_a_start_event_are_counted_not_paired(tmp_path):
    def late_start() -> Iterator[Recorded]:  # the recorder joined mid-episode: no START for episode 0
        yield from (r for r in episode_stream(episode=0, frames=5) if not isinstance(r.message, EpisodeEvent))
        yield from episode_stream(episode=1, frames=6)

    _, manifest = build(tmp_path, source("late", late_start))
    assert manifest["totals"]["samples"] == 6
    assert manifest["sources"][0]["frames_outside_episodes"] == 5


# -- images ------------------------------------------------------------------------------------------------------------


def test_frames_are_cropped_then_resized_with_area_averaging(tmp_path):
    out, _ = build(
        tmp_path, source("a", ep(frames=3)), width_px=10, height_px=5, crop_top_fraction=0.5, crop_bottom_fraction=1.0
    )
    frames = arrays(out)["frames"]
    assert frames.shape == (3, 5, 10, 3)
    # rows 10..19 kept, 2 source rows per output row: mean of 10*r and 10*(r+1) for r = 10, 12, ...
    assert frames[0, :, 0, 1].tolist() == [105, 125, 145, 165, 185]
    # 40 -> 10 columns: the mean of (240, 0, 0, 240)
    assert np.all(frames[0, :, :, 2] == 120)
    assert np.all(frames[2, ..., 0] == 2)


# -- windows -----------------------------------------------------------------------------------------------------------


def test_windows_never_cross_episodes_nor_span_a_dropped_frame(tmp_path):
    out, manifest = build(
        tmp_path,
        source("a", ep(episode=0, frames=30, dropped=frozenset({10})), ep(episode=1, frames=30)),
        offsets_frames=(-2, -1, 0),
    )
    a = arrays(out)
    train = a["train_index"]
    # episode 0: seq 2..9 and 13..29 (10 is missing); episode 1: seq 2..29
    assert len(train) == 8 + 17 + 28 and len(a["val_index"]) == 0
    for t in train:
        window = t + np.array([-2, -1, 0])
        assert len(set(a["episode"][window])) == 1
        assert a["frame_seq"][window].tolist() == [a["frame_seq"][t] - 2, a["frame_seq"][t] - 1, a["frame_seq"][t]]
    first_of_episode_1 = int(np.flatnonzero(a["episode"] == 1)[0])
    assert not {first_of_episode_1, first_of_episode_1 + 1} & set(train.tolist())
    assert [e["windows"] for e in manifest["sources"][0]["episodes"]] == [25, 28]
    assert manifest["offsets_s"] == pytest.approx([-0.1, -0.05, 0.0])


def test_valid_windows_checks_episode_and_contiguous_sequence():
    episode = np.array([0, 0, 0, 0, 1, 1, 1])
    seq = np.array([0, 1, 3, 4, 0, 1, 2])
    assert valid_windows(episode, seq, (-1, 0)).tolist() == [1, 3, 5, 6]
    assert valid_windows(episode, seq, (0,)).tolist() == list(range(7))
    # contiguous numbers across an episode boundary (episode 1's first frames unanswered) still break the window
    assert valid_windows(np.array([0, 0, 1, 1]), np.array([0, 1, 2, 3]), (-1, 0)).tolist() == [1, 3]


def test_runs_interleaved_in_one_source_are_stored_episode_by_episode(tmp_path):
    def interleaved() -> Iterator[Recorded]:
        a, b = episode_stream("ra", frames=10), episode_stream("rb", frames=10)
        for pair in zip(a, b, strict=False):
            yield from pair
        yield from a
        yield from b

    out, manifest = build(tmp_path, source("both", interleaved), offsets_frames=(-1, 0))
    arr = arrays(out)
    assert arr["episode"].tolist() == [0] * 10 + [1] * 10
    assert arr["frame_seq"].tolist() == list(range(10)) * 2
    assert all(int(arr["frames"][i, 0, 0, 0]) == arr["frame_seq"][i] for i in range(20))
    assert len(arr["train_index"]) == 18
    assert manifest["sources"][0]["run_ids"] == ["ra", "rb"]


# -- split and statistics ----------------------------------------------------------------------------------------------


def test_episode_split_keeps_whole_episodes_on_one_side(tmp_path):
    streams = [ep(episode=e, frames=15) for e in range(6)]
    out, manifest = build(tmp_path, source("a", *streams), split="episode:0.34", seed=3, offsets_frames=(-1, 0))
    a = arrays(out)
    train_eps, val_eps = set(a["episode"][a["train_index"]]), set(a["episode"][a["val_index"]])
    assert len(val_eps) == 2 and len(train_eps) == 4 and not train_eps & val_eps
    assert val_eps == set(manifest["split"]["val_episodes"]) and train_eps == set(manifest["split"]["train_episodes"])
    _, again = build(tmp_path, source("a", *streams), name="again", split="episode:0.34", seed=3)
    assert again["split"]["val_episodes"] == manifest["split"]["val_episodes"]  # seeded


def test_circuit_split_holds_out_those_circuits(tmp_path):
    streams = [ep(episode=e, frames=10, circuit=c) for e, c in enumerate(["simple", "monaco", "simple", "montreal"])]
    out, manifest = build(tmp_path, source("a", *streams), split="circuit:monaco,montreal")
    a = arrays(out)
    assert set(a["episode"][a["val_index"]]) == {1, 3} and set(a["episode"][a["train_index"]]) == {0, 2}
    splits = {e["index"]: (e["circuit"], e["split"]) for e in manifest["sources"][0]["episodes"]}
    assert splits == {0: ("simple", "train"), 1: ("monaco", "val"), 2: ("simple", "train"), 3: ("montreal", "val")}


def test_label_statistics_come_from_the_train_split_only(tmp_path):
    def speed(brain, episode, seq):
        return 100.0 if episode == 1 else 1.0 + seq * 0.1  # validation episode: wildly different

    streams = [
        ep(episode=0, frames=20, circuit="simple", speed=speed),
        ep(episode=1, frames=20, circuit="monaco", speed=speed),
    ]
    out, manifest = build(tmp_path, source("a", *streams), split="circuit:monaco")
    a = arrays(out)
    train_labels = a["labels"][a["train_index"]].astype(np.float64)
    stats = manifest["train_label_stats"]
    assert stats["samples"] == 20
    assert stats["speed_mps"]["max"] == pytest.approx(2.9) and stats["speed_mps"]["min"] == pytest.approx(1.0)
    assert stats["speed_mps"]["mean"] == pytest.approx(train_labels[:, 0].mean())
    assert stats["speed_mps"]["q50"] == pytest.approx(np.median(train_labels[:, 0]))
    assert stats["yaw_rate_radps"]["std"] == pytest.approx(train_labels[:, 1].std(), rel=1e-6)
    histogram = stats["abs_yaw_rate_histogram"]
    assert sum(histogram["counts"]) == 20 and len(histogram["counts"]) == len(histogram["edges_radps"])
    expected_first_bin = int(np.sum(np.abs(train_labels[:, 1]) < histogram["edges_radps"][1]))
    assert histogram["counts"][0] == expected_first_bin


def test_one_episode_cannot_be_split_unless_validation_is_off(tmp_path):
    with pytest.raises(DatasetError, match="cannot be split"):
        build(tmp_path, source("one", ep(frames=10)), split="episode:0.2")
    assert not (tmp_path / "ds").exists()
    out, manifest = build(tmp_path, source("one", ep(frames=10)), name="ok", split="episode:0")
    assert manifest["split"]["val_episodes"] == [] and len(np.load(out / "val_index.npy")) == 0


def test_history_over_episodes_of_different_step_s_is_refused(tmp_path):
    streams = source("a", ep(episode=0, frames=5), ep(episode=1, frames=5, step_s=0.1))
    with pytest.raises(DatasetError, match="different step_s"):
        build(tmp_path, streams, offsets_frames=(-1, 0))
    _, manifest = build(tmp_path, streams, name="single")  # one frame per sample: no time span to disagree on
    assert manifest["step_s"] is None and manifest["offsets_s"] is None


def test_circuit_split_naming_an_absent_circuit_is_an_error(tmp_path):
    with pytest.raises(DatasetError, match="montmelo"):
        build(tmp_path, source("a", ep(episode=0, frames=5), ep(episode=1, frames=5)), split="circuit:montmelo")


# -- manifest and errors -----------------------------------------------------------------------------------------------


def test_manifest_records_sources_and_their_episodes(tmp_path):
    out, manifest = build(
        tmp_path,
        source("first.mcap", ep(episode=0, frames=8, unanswered=frozenset({2}))),
        source("second.mcap", ep(run_id="r2", episode=0, frames=6, circuit="monaco")),
        offsets_frames=(-1, 0),
    )
    assert [s["name"] for s in manifest["sources"]] == ["first.mcap", "second.mcap"]
    assert [s["run_ids"] for s in manifest["sources"]] == [["r1"], ["r2"]]
    first, second = manifest["sources"][0]["episodes"][0], manifest["sources"][1]["episodes"][0]
    assert (first["index"], second["index"]) == (0, 1)  # the same episode number in two runs: two episodes
    assert first["circuit"] == "simple" and second["circuit"] == "monaco"
    assert first["frames_kept"] == 7 and first["frames_skipped"] == {"no_command": 1}
    assert first["noise"] == [{"model": "gaussian", "sigma": 3.0}]
    assert (first["camera_width_px"], first["camera_height_px"], first["step_s"]) == (WIDTH, HEIGHT, 0.05)
    assert first["end_reason"] == "laps_completed" and first["world"]["line"] == "red"
    assert manifest["totals"] == {"samples": 13, "episodes": 2, "frames_skipped": {"no_command": 1}}
    assert manifest["options"]["offsets_frames"] == [-1, 0] and manifest["offsets_frames"] == [-1, 0]
    assert set(np.load(out / "episode.npy").tolist()) == {0, 1}


def test_a_source_that_raises_mid_stream_names_the_source(tmp_path):
    def broken() -> Iterator[Recorded]:
        yield from episode_stream(frames=5)
        raise OSError("truncated chunk at byte 1234")

    with pytest.raises(DatasetError, match=r"source bad\.mcap: reading failed .*truncated chunk") as caught:
        build(tmp_path, source("good.mcap", ep(frames=5)), ("bad.mcap", broken))
    assert "\n" not in str(caught.value)
    assert list(tmp_path.iterdir()) == []  # no output and no leftover partial folder


def test_no_pairs_at_all_is_an_error(tmp_path):
    with pytest.raises(DatasetError, match="no perturbed camera frame was paired with a command of ghost"):
        build(tmp_path, source("a", ep(frames=5)), brain="ghost")


def test_a_non_empty_output_folder_is_refused_unless_overwriting(tmp_path):
    out = tmp_path / "ds"
    out.mkdir()
    (out / "precious.txt").write_text("keep")
    options = DatasetOptions(width_px=WIDTH, height_px=HEIGHT, split="none")
    with pytest.raises(DatasetError, match="not empty"):
        build_dataset([source("a", ep(frames=5))], out_dir=out, options=options, progress=False)
    assert (out / "precious.txt").read_text() == "keep"
    build_dataset([source("a", ep(frames=5))], out_dir=out, options=options, progress=False, overwrite=True)
    assert (out / "precious.txt").read_text() == "keep" and len(DrivingDataset(out)) == 5
    build_dataset([source("a", ep(frames=7))], out_dir=out, options=options, progress=False, overwrite=True)
    assert (out / "precious.txt").read_text() == "keep" and len(DrivingDataset(out)) == 7


def test_one_run_in_two_sources_is_refused(tmp_path):
    with pytest.raises(DatasetError, match=r"copy and a both hold run 'r1'"):
        build(tmp_path, source("a", ep(run_id="r1")), source("copy", ep(run_id="r1", episode=1)))
    assert not (tmp_path / "ds").exists() and list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    "options, message",
    [
        ({"offsets_frames": (-2, -1)}, "end at 0"),
        ({"offsets_frames": (-1, -2, 0)}, "strictly increasing"),
        ({"offsets_frames": ()}, "non-empty"),
        ({"split": "frames:0.2"}, "split must be"),
        ({"split": "episode:1.5"}, "within"),
        ({"camera": "raw"}, "camera must be"),
        ({"crop_top_fraction": 0.6, "crop_bottom_fraction": 0.5}, "crop"),
        ({"brain": "a/b"}, "brain name"),
    ],
)
def test_bad_options_are_refused(options, message):
    with pytest.raises(DatasetError, match=message):
        DatasetOptions(**options)


# -- reading -----------------------------------------------------------------------------------------------------------


@pytest.fixture
def two_episode_dataset(tmp_path) -> Path:
    streams = [ep(episode=e, frames=25, dropped=frozenset({9}) if e == 1 else frozenset()) for e in range(4)]
    out, _ = build(tmp_path, source("a", *streams), split="episode:0.25", offsets_frames=(-2, -1, 0))
    return out


def test_batch_equals_getitem(two_episode_dataset):
    dataset = DrivingDataset(two_episode_dataset)
    assert dataset.offsets_frames == (-2, -1, 0)
    picks = np.array([0, 5, len(dataset) - 1, 5, 17])
    frames, labels = dataset.batch(picks)
    assert frames.shape == (5, 3, HEIGHT, WIDTH, 3) and frames.dtype == np.uint8
    assert labels.shape == (5, 2) and labels.dtype == np.float32
    for row, i in enumerate(picks):
        item_frames, item_label = dataset[int(i)]
        np.testing.assert_array_equal(frames[row], item_frames)
        np.testing.assert_array_equal(labels[row], item_label)
    seqs = frames[:, :, 0, 0, 0].astype(int)  # each window holds consecutive frames, oldest first
    assert np.all(np.diff(seqs, axis=1) == 1)


def test_train_and_val_are_disjoint_and_cover_the_stored_windows(two_episode_dataset):
    train, val = DrivingDataset(two_episode_dataset), DrivingDataset(two_episode_dataset, split="val")
    both = DrivingDataset(two_episode_dataset, split="all")
    assert len(train) + len(val) == len(both) == 3 * 23 + 20
    assert not set(train.episode[train.index]) & set(val.episode[val.index])


def test_other_offsets_at_load_time_recompute_windows(two_episode_dataset):
    stored = DrivingDataset(two_episode_dataset, split="all")
    same = DrivingDataset(two_episode_dataset, split="all", offsets_frames=(-2, -1, 0))
    np.testing.assert_array_equal(stored.index, same.index)
    longer = DrivingDataset(two_episode_dataset, split="all", offsets_frames=(-9, -5, 0))
    # 25 frames per episode: seq 9..24 -> 16 windows; episode 1 lost frame 9: only seq 19..24 avoid it -> 6 (seq
    # 9 itself is missing, 10..18 reach back over it)
    assert len(longer) == 3 * 16 + 6
    frames, label = longer[0]
    assert frames.shape == (3, HEIGHT, WIDTH, 3) and frames[:, 0, 0, 0].tolist() == [0, 4, 9]
    single = DrivingDataset(two_episode_dataset, offsets_frames=(0,))  # every sample of the train episodes
    assert len(single) == int(np.isin(single.episode, single.manifest["split"]["train_episodes"]).sum())
    assert len(single) > len(DrivingDataset(two_episode_dataset))
    with pytest.raises(DatasetError, match="end at 0"):
        DrivingDataset(two_episode_dataset, offsets_frames=(-1,))


def test_opening_a_broken_folder_is_a_one_line_error(two_episode_dataset, tmp_path):
    with pytest.raises(DatasetError, match="not a folder"):
        DrivingDataset(tmp_path / "nowhere")
    (two_episode_dataset / "labels.npy").unlink()
    with pytest.raises(DatasetError, match="missing labels.npy"):
        DrivingDataset(two_episode_dataset)
    manifest = two_episode_dataset / "manifest.json"
    manifest.write_text("{not json")
    with pytest.raises(DatasetError, match="manifest.json") as caught:
        DrivingDataset(two_episode_dataset)
    assert "\n" not in str(caught.value)
    manifest.write_text(json.dumps({"format_version": 1, "options": {}}))
    with pytest.raises(DatasetError, match="bad manifest.json"):
        DrivingDataset(two_episode_dataset)


def test_a_truncated_frames_file_is_refused(two_episode_dataset):
    frames = np.load(two_episode_dataset / "frames.npy")
    np.save(two_episode_dataset / "frames.npy", frames[:-1])
    with pytest.raises(DatasetError, match="frames.npy is uint8"):
        DrivingDataset(two_episode_dataset)


def test_samples_per_second_is_measured(two_episode_dataset):
    rate = samples_per_second(DrivingDataset(two_episode_dataset), batch_size=8, seconds=0.05)
    assert rate > 0


def test_the_core_imports_neither_zenoh_nor_torch_nor_mcap():
    code = (
        "import sys, recorder.dataset.build; "
        "print(sorted(m for m in sys.modules if m.split('.')[0] in ('zenoh', 'torch', 'mcap')))"
    )
    result = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        check=True,
        cwd=Path(__file__).resolve().parents[1],
    )
    assert result.stdout.strip() == "[]"
