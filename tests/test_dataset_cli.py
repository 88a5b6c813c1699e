"""``drivebench dataset build`` through the real CLI, on real MCAP recordings (written by the recorder's own writer
from the streams of test_dataset): where it writes, what it refuses, and how it says so."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from support.datasets import build, drivebench, one_line_error, record

from recorder.dataset.build import DrivingDataset

ROOT = Path(__file__).resolve().parents[1]
DATASET_FILES = (
    "frames.npy",
    "labels.npy",
    "episode.npy",
    "frame_seq.npy",
    "stamp_ns.npy",
    "train_index.npy",
    "val_index.npy",
    "manifest.json",
)


# -- item 1: --overwrite replaces a dataset, nothing else --------------------------------------------------------------


def test_overwrite_replaces_the_dataset_and_keeps_every_other_file(tmp_path):
    a, b = record(tmp_path / "a.mcap", "ra"), record(tmp_path / "b.mcap", "rb")
    out = tmp_path / "data"
    assert build(a, "-o", out, "--split", "none").returncode == 0
    (out / "notes.txt").write_text("mine")
    (out / "keep").mkdir()
    (out / "keep" / "other.mcap").write_bytes(a.read_bytes())

    refused = one_line_error(build(a, b, "-o", out, "--split", "none"))
    assert "--overwrite" in refused and "overwrite=True" not in refused
    assert len(DrivingDataset(out)) == 24  # untouched: still the first build

    result = build(a, b, "-o", out, "--split", "none", "--overwrite")
    assert result.returncode == 0, result.stderr
    assert len(DrivingDataset(out)) == 48  # the new build, both recordings
    assert (out / "notes.txt").read_text() == "mine"
    assert (out / "keep" / "other.mcap").read_bytes() == a.read_bytes()
    assert sorted(p.name for p in out.iterdir()) == sorted([*DATASET_FILES, "notes.txt", "keep"])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.mcap", "b.mcap", "data"]  # no partial left beside


def test_an_output_folder_that_holds_an_input_is_refused_and_nothing_is_deleted(tmp_path):
    inputs = tmp_path / "recordings"
    a, b = record(inputs / "a.mcap", "ra"), record(inputs / "b.mcap", "rb")
    before = {p.name: p.read_bytes() for p in inputs.iterdir()}
    for out in (inputs, inputs / "."):
        error = one_line_error(build(a, b, "-o", out, "--overwrite"))
        assert "holds the input" in error
    error = one_line_error(build("a.mcap", "b.mcap", "-o", ".", "--overwrite", cwd=inputs))
    assert "holds the input" in error
    assert {p.name: p.read_bytes() for p in inputs.iterdir()} == before


def test_output_dot_builds_into_the_current_folder_next_to_its_files(tmp_path):
    a, b = record(tmp_path / "a.mcap", "ra"), record(tmp_path / "b.mcap", "rb")
    here = tmp_path / "here"
    here.mkdir()
    (here / "readme.txt").write_text("mine")
    result = build(a, b, "-o", ".", "--overwrite", "--split", "episode:0.5", cwd=here)
    assert result.returncode == 0, result.stderr
    assert (here / "readme.txt").read_text() == "mine"
    assert len(DrivingDataset(here, split="all")) == 48
    assert sorted(p.name for p in here.iterdir()) == sorted([*DATASET_FILES, "readme.txt"])


# -- item 7: one run given twice ---------------------------------------------------------------------------------------


def test_two_recordings_of_one_run_are_refused_naming_both(tmp_path):
    a = record(tmp_path / "a.mcap", "ra", episodes=4)
    copy = tmp_path / "copy.mcap"
    copy.write_bytes(a.read_bytes())
    out = tmp_path / "data"
    error = one_line_error(build(a, copy, "-o", out, "--split", "episode:0.5"))
    assert "'ra'" in error and "a.mcap" in error and "copy.mcap" in error
    assert not out.exists() and sorted(p.name for p in tmp_path.iterdir()) == ["a.mcap", "copy.mcap"]
    # Different runs still build, with every episode on one side of the split only.
    result = build(a, record(tmp_path / "b.mcap", "rb", episodes=4), "-o", out, "--split", "episode:0.5")
    assert result.returncode == 0, result.stderr
    manifest = json.loads((out / "manifest.json").read_text())
    episodes = [(e["run_id"], e["episode"]) for s in manifest["sources"] for e in s["episodes"]]
    assert len(episodes) == len(set(episodes)) == 8
    train, val = DrivingDataset(out, split="train"), DrivingDataset(out, split="val")
    assert not set(np.unique(train.episode[train.index])) & set(np.unique(val.episode[val.index]))


# -- item 17: options named, in one short line -------------------------------------------------------------------------


@pytest.fixture(scope="module")
def recordings(tmp_path_factory) -> tuple[Path, Path]:
    folder = tmp_path_factory.mktemp("recordings")
    return record(folder / "a.mcap", "ra"), record(folder / "b.mcap", "rb")


def test_a_negative_seed_names_the_option(recordings, tmp_path):
    error = one_line_error(build(*recordings, "-o", tmp_path / "d", "--seed", "-3"))
    assert "--seed" in error and "-3" in error
    assert not (tmp_path / "d").exists()


def test_a_long_history_is_summarised_not_printed_whole(recordings, tmp_path):
    error = one_line_error(build(*recordings, "-o", tmp_path / "d", "--history", "1000"))
    assert "1000 frames" in error and "-999" in error and len(error) < 300


def test_stride_with_offsets_is_refused_instead_of_ignored(recordings, tmp_path):
    error = one_line_error(build(*recordings, "-o", tmp_path / "d", "--offsets=-2,0", "--stride", "5"))
    assert "--stride" in error and "--offsets" in error
    assert not (tmp_path / "d").exists()
    # --stride with --history still shapes the windows
    result = build(*recordings, "-o", tmp_path / "h", "--history", "3", "--stride", "2")
    assert result.returncode == 0, result.stderr
    assert json.loads((tmp_path / "h" / "manifest.json").read_text())["offsets_frames"] == [-4, -2, 0]


@pytest.mark.integration
def test_collect_into_the_current_folder_keeps_its_files_and_records_beside_it(tmp_path):
    here = tmp_path / "here"
    here.mkdir()
    (here / "notes.txt").write_text("mine")
    (tmp_path / "file").write_text("not a folder")
    options = (
        "--circuits",
        "simple",
        "--max-sim-seconds",
        "1",
        "--camera",
        "64x48",
        "--size",
        "40x20",
        "--split",
        "none",
    )
    error = one_line_error(drivebench("dataset", "collect", *options, "-o", tmp_path / "file"))
    assert "not a folder" in error
    error = one_line_error(drivebench("dataset", "collect", *options, "-o", ".", cwd=here))
    assert "--overwrite" in error
    result = drivebench("dataset", "collect", *options, "-o", ".", "--overwrite", cwd=here)
    assert result.returncode == 0, result.stderr
    assert (here / "notes.txt").read_text() == "mine" and len(DrivingDataset(here)) == 20
    assert sorted(p.name for p in here.iterdir()) == sorted([*DATASET_FILES, "notes.txt"])
    assert [p.name for p in (tmp_path / "here.recordings").glob("*.mcap")] == ["simple.mcap"]
