"""End to end: a dataset collected from the simulator with the explicit brain, checked against its recordings."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from protocol import keys
from protocol.images import frame_image
from protocol.messages import CameraFrame, Command
from recorder.dataset.build import DrivingDataset
from recorder.reading import read_messages

pytestmark = [pytest.mark.integration, pytest.mark.slow]
ROOT = Path(__file__).resolve().parents[1]


def drivebench(*argv: str, timeout: float = 170) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "orchestrator.cli", *argv], capture_output=True, text=True, timeout=timeout, cwd=ROOT
    )


@pytest.fixture(scope="module")
def collected(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("collect") / "data"
    result = drivebench(
        "dataset",
        "collect",
        "--circuits",
        "simple,many_curves",
        "--max-sim-seconds",
        "4",
        "--camera",
        "160x120",
        "--size",
        "40x20",
        "--crop",
        "0.5:1",
        "--history",
        "3",
        "--stride",
        "2",
        "--split",
        "circuit:many_curves",
        "-o",
        str(out),
    )
    assert result.returncode == 0, result.stderr
    return out


def test_labels_are_the_commands_that_answered_the_frames(collected):
    manifest = json.loads((collected / "manifest.json").read_text())
    assert [Path(s["name"]).name for s in manifest["sources"]] == ["simple.mcap", "many_curves.mcap"]
    data = DrivingDataset(collected, split="all", offsets_frames=(0,))
    checked = 0
    for source in manifest["sources"]:
        episode = source["episodes"][0]
        frames, commands = {}, {}
        for item in read_messages(Path(source["name"])):
            if item.key == keys.camera_perturbed(episode["run_id"]):
                frames[item.message.header.seq] = item.message
            elif item.key == keys.command(episode["run_id"], "explicit"):
                commands[item.message.frame_seq] = item.message
        rows = np.flatnonzero(data.episode == episode["index"])
        assert len(rows) == len(commands) == 80  # 4 s at 20 Hz: every frame answered and kept
        for row in rows:
            seq = int(data.frame_seq[row])
            command: Command = commands[seq]
            assert tuple(data.labels[row]) == pytest.approx((command.speed_mps, command.yaw_rate_radps), abs=1e-6)
            frame: CameraFrame = frames[seq]
            image = frame_image(frame)[60:]  # --crop 0.5:1 of 120 rows
            expected = cv2.resize(image, (40, 20), interpolation=cv2.INTER_AREA)
            assert np.array_equal(data.frames[row], expected)
            checked += 1
    assert checked == 160


def test_windows_stay_inside_one_episode_and_split_by_circuit(collected):
    manifest = json.loads((collected / "manifest.json").read_text())
    train, val = DrivingDataset(collected, split="train"), DrivingDataset(collected, split="val")
    assert manifest["offsets_frames"] == [-4, -2, 0]
    for dataset in (train, val):
        for offset in (-4, -2):
            assert np.all(dataset.episode[dataset.index + offset] == dataset.episode[dataset.index])
            assert np.all(dataset.frame_seq[dataset.index + offset] == dataset.frame_seq[dataset.index] + offset)
    circuits = {e["index"]: e["circuit"] for s in manifest["sources"] for e in s["episodes"]}
    assert {circuits[e] for e in np.unique(train.episode[train.index])} == {"simple"}
    assert {circuits[e] for e in np.unique(val.episode[val.index])} == {"many_curves"}
    assert len(train) == len(val) == 76  # 80 frames less the first 4 of each episode
    frames, labels = train.batch(np.arange(8))
    assert frames.shape == (8, 3, 20, 40, 3) and labels.shape == (8, 2)


def test_build_reports_bad_recordings_in_one_line(tmp_path):
    (tmp_path / "bad.mcap").write_bytes(b"\x89MCAP0\r\n" + b"\x00" * 100)
    result = drivebench("dataset", "build", str(tmp_path / "bad.mcap"), "-o", str(tmp_path / "out"))
    assert result.returncode == 2
    assert "Traceback" not in result.stderr and len(result.stderr.strip().splitlines()) == 1
    assert "bad.mcap" in result.stderr
    assert not (tmp_path / "out").exists()
