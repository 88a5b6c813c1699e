"""``drivebench train`` and ``drivebench export`` through the real CLI: a dataset that does not fit the network, and a
bad option, are one line (exit 2) before any work, and the fix a message suggests is a command line that runs."""

from __future__ import annotations

import json
import re
import shlex
from pathlib import Path

import pytest
from support.datasets import build, drivebench, one_line_error, record

pytest.importorskip("torch")
WEIGHTS = Path(__file__).resolve().parents[1] / "brains" / "weights" / "deepest_lstm_tiny_pilotnet.ckpt"


@pytest.fixture(scope="module")
def recordings(tmp_path_factory) -> tuple[Path, Path]:
    folder = tmp_path_factory.mktemp("recordings")
    return record(folder / "a.mcap", "ra"), record(folder / "b.mcap", "rb")


def train(data: Path, output: Path, *options: str, model: str = "deepest_lstm_tiny_pilotnet"):
    return drivebench(
        "train", "--model", model, "--data", data, "-o", output, "--epochs", "1", "--threads", "1",
        "--max-samples-per-epoch", "8", "--batch-size", "4", *options,
    )  # fmt: skip


@pytest.mark.slow  # over 9 s: out of the quick tier
def test_the_whole_frame_for_a_network_of_the_lower_half_is_an_error_unless_asked(recordings, tmp_path):
    data = tmp_path / "whole"
    assert build(*recordings, "-o", data, "--split", "none", size="100x50").returncode == 0
    error = one_line_error(train(data, tmp_path / "run"))
    assert "--crop 0.5:1" in error and "0..1" in error
    assert not (tmp_path / "run").exists()
    result = train(data, tmp_path / "run", "--any-crop")
    assert result.returncode == 0, result.stderr
    assert (tmp_path / "run" / "model.ckpt").is_file()
    assert "differ from the reference" in result.stderr  # still said


@pytest.mark.slow  # over 9 s: out of the quick tier
def test_the_lower_half_for_a_whole_frame_network_trains_with_a_note(recordings, tmp_path):
    """The paper's recipe trains memDCCP on the lower half (brains/weights/README.md): a narrower crop than the
    network's is a choice, not an error."""
    data = tmp_path / "lower"
    built = build(*recordings, "-o", data, "--split", "none", "--offsets=-9,-5,0", "--crop", "0.5:1", size="100x50")
    assert built.returncode == 0, built.stderr
    result = train(data, tmp_path / "run", model="memdccp")
    assert result.returncode == 0, result.stderr
    assert "differ from the reference" in result.stderr and (tmp_path / "run" / "model.ckpt").is_file()


def test_the_offsets_a_message_suggests_are_accepted_as_written(recordings, tmp_path):
    data = tmp_path / "single"
    assert build(*recordings, "-o", data, "--split", "none", size="100x50").returncode == 0
    error = one_line_error(train(data, tmp_path / "run", model="memdccp"))
    suggested = re.search(r"or (--offsets\S*(?: \S+)?)", error)
    assert suggested, error
    result = build(*recordings, "-o", tmp_path / "seq", *shlex.split(suggested[1]), size="100x50")
    assert result.returncode == 0, result.stderr
    assert json.loads((tmp_path / "seq" / "manifest.json").read_text())["offsets_frames"] == [-9, -5, 0]


@pytest.mark.parametrize("command", ["export", "pack"])
def test_parity_batch_zero_is_refused_before_anything_is_written(tmp_path, command):
    out = tmp_path / ("m.onnx" if command == "export" else "m.ckpt")
    error = one_line_error(drivebench(command, WEIGHTS, "-o", out, "--parity-batch", "0"))
    assert "--parity-batch" in error
    assert list(tmp_path.iterdir()) == []
