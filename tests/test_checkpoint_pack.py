"""Packed checkpoints (``drivebench pack``): float16 state dict in shard files small enough for git, read back by
read_checkpoint as an ordinary checkpoint; missing or changed shards are one-line errors naming the file."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from needs import require

torch = require("torch")

from brains import Observation  # noqa: E402
from brains.neural.brain import NeuralBrain, Preprocessor  # noqa: E402
from brains.neural.checkpoint import (  # noqa: E402
    SHARDS_KEY,
    CheckpointError,
    build_model,
    load_checkpoint,
    make_random_checkpoint,
    pack_checkpoint,
    read_checkpoint,
)
from orchestrator.cli import main  # noqa: E402

SHARD_BYTES = 4 * 2**20  # PilotNet's ~34 MB of float16 -> 9 shards
SMALL = "deepest_lstm_tiny_pilotnet"  # 0.26 MB: for the tests that do not need the big one


@pytest.fixture(scope="module")
def pilotnet(tmp_path_factory) -> tuple[Path, list[Path]]:
    folder = tmp_path_factory.mktemp("pack")
    original = make_random_checkpoint(folder / "pilotnet.pt", "pilotnet", seed=3)
    return original, pack_checkpoint(original, folder / "packed" / "model.ckpt", shard_bytes=SHARD_BYTES)


def copy_pack(written: list[Path], folder: Path) -> Path:
    """The packed files copied into ``folder``; returns the copy of the checkpoint (the last file)."""
    folder.mkdir(parents=True, exist_ok=True)
    for path in written:
        shutil.copy(path, folder / path.name)
    return folder / written[-1].name


def test_pack_writes_small_shards_beside_a_small_checkpoint(pilotnet):
    original, written = pilotnet
    packed, shards = written[-1], written[:-1]
    assert len(shards) >= 5 and all(path.stat().st_size <= SHARD_BYTES for path in written)
    assert packed.stat().st_size < 100_000
    assert sum(path.stat().st_size for path in written) < 0.55 * original.stat().st_size  # float16: half
    meta = torch.load(packed, weights_only=True)[SHARDS_KEY]
    assert meta["files"] == [path.name for path in shards] and meta["dtype"] == "float16"
    assert meta["bytes"] == sum(path.stat().st_size for path in shards)


def test_packed_pilotnet_serves_like_the_original_on_a_camera_frame(pilotnet, road_frame):
    original, written = pilotnet
    a, b = load_checkpoint(original), load_checkpoint(written[-1])
    assert b.model == "pilotnet" and b.input == a.input and b.normalisation == a.normalisation
    assert a.state_dict.keys() == b.state_dict.keys()
    assert all(b.state_dict[k].dtype == v.dtype for k, v in a.state_dict.items())  # float32 again; int64 untouched
    x = torch.from_numpy(Preprocessor(a.input, a.normalisation)(road_frame))[None]
    with torch.inference_mode():
        expected, got = build_model(a)(x), build_model(b)(x)
    assert expected.abs().min() > 0.05  # outputs of O(1): the relative comparison means something
    assert torch.allclose(got, expected, rtol=1e-2, atol=0.0), (expected, got)
    assert not torch.equal(got, expected)  # float16 did round


def test_packed_checkpoint_drives_a_neural_brain(pilotnet, road_frame):
    original, written = pilotnet
    frame = road_frame

    def act(weights: Path):
        action = NeuralBrain(weights=str(weights), backend="torch").act(Observation(image_rgb=frame, stamp_ns=0, seq=0))
        return np.array([action.speed_mps, action.yaw_rate_radps])

    np.testing.assert_allclose(act(written[-1]), act(original), rtol=1e-2)


@pytest.mark.parametrize(
    "case, message",
    [
        ("missing", r"shard file .*model\.ckpt\.shard2 is missing"),
        ("truncated", r"shard file .*model\.ckpt\.shard2 does not match its sha256"),
        ("changed", r"shard file .*model\.ckpt\.shard2 does not match its sha256"),
        ("lfs", r"shard file .*model\.ckpt\.shard2 is a git LFS pointer"),
    ],
)
def test_missing_or_changed_shard_is_one_line_naming_the_file(case, message, pilotnet, tmp_path):
    packed = copy_pack(pilotnet[1], tmp_path / "copy")
    shard = packed.with_name("model.ckpt.shard2")
    data = shard.read_bytes()
    if case == "missing":
        shard.unlink()
    elif case == "truncated":
        shard.write_bytes(data[:1000])
    elif case == "changed":
        shard.write_bytes(data[:500] + bytes([data[500] ^ 1]) + data[501:])
    else:
        shard.write_bytes(b"version https://git-lfs.github.com/spec/v1\noid sha256:" + b"0" * 64 + b"\nsize 4194304\n")
    for read in (read_checkpoint, load_checkpoint):
        with pytest.raises(CheckpointError, match=message) as error:
            read(packed)
        assert "\n" not in str(error.value) and str(error.value).startswith(f"{packed}: ")


def test_float32_pack_of_a_training_checkpoint_is_exact_and_drops_resume_state(tmp_path):
    source = make_random_checkpoint(tmp_path / "small.pt", SMALL)
    raw = read_checkpoint(source)
    raw.update(
        optimizer_state={"state": {}, "param_groups": []},
        epoch=3,
        rng={"torch": torch.get_rng_state()},
        resume={"best_state_dict": raw["state_dict"]},
    )
    torch.save(raw, tmp_path / "last.ckpt")
    written = pack_checkpoint(tmp_path / "last.ckpt", tmp_path / "model.ckpt", half=False)
    assert [path.name for path in written] == ["model.ckpt.shard0", "model.ckpt"]  # fits one shard: still one
    packed = torch.load(written[-1], weights_only=True)
    assert set(packed) == {
        "format",
        "model",
        "hyper",
        "input",
        "normalisation",
        "dataset",
        "metrics",
        "training",
        "state_dict",
        SHARDS_KEY,
    }
    assert packed["state_dict"] == {} and packed[SHARDS_KEY]["dtype"] == "float32"
    back = read_checkpoint(written[-1])["state_dict"]
    assert all(torch.equal(back[k], v) for k, v in raw["state_dict"].items())


def test_repacking_is_stable_and_removes_stale_shards(tmp_path):
    source = make_random_checkpoint(tmp_path / "small.pt", SMALL)
    first = pack_checkpoint(source, tmp_path / "a" / "m.ckpt", shard_bytes=20_000)
    again = pack_checkpoint(first[-1], tmp_path / "b" / "m.ckpt", shard_bytes=20_000)  # packed -> packed
    assert [p.read_bytes() for p in first[:-1]] == [p.read_bytes() for p in again[:-1]]
    fewer = pack_checkpoint(source, tmp_path / "a" / "m.ckpt", shard_bytes=100_000)
    assert sorted(p.name for p in (tmp_path / "a").iterdir()) == sorted(p.name for p in fewer)
    assert len(fewer) < len(first)


def test_joined_shards_are_checked_without_per_file_hashes(tmp_path):
    """A pack whose entry carries only the joined sha256 (the minimal form) still detects a changed shard."""
    written = pack_checkpoint(
        make_random_checkpoint(tmp_path / "small.pt", SMALL), tmp_path / "m.ckpt", shard_bytes=50_000
    )
    raw = torch.load(written[-1], weights_only=True)
    del raw[SHARDS_KEY]["file_sha256"]
    torch.save(raw, written[-1])
    read_checkpoint(written[-1])  # intact: reads
    written[0].write_bytes(written[0].read_bytes()[:-1])
    with pytest.raises(CheckpointError, match=r"m\.ckpt: its shards m\.ckpt\.shard0, .* do not match"):
        read_checkpoint(written[-1])


def test_pack_command_errors_are_one_line(tmp_path, capsys):
    assert main(["pack", str(tmp_path / "none.pt"), "-o", str(tmp_path / "o.ckpt")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("drivebench: error: ") and "none.pt: no such checkpoint file" in err
    assert err.count("\n") == 1 and not (tmp_path / "o.ckpt").exists()


@pytest.mark.slow  # over 9 s: out of the quick tier
def test_pack_command_end_to_end(pilotnet, tmp_path):
    out = tmp_path / "git" / "pilotnet.ckpt"
    done = subprocess.run(
        [sys.executable, "-m", "orchestrator.cli", "pack", str(pilotnet[0]), "-o", str(out)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr
    files = sorted(out.parent.iterdir())
    assert len(files) == 5 and all(path.stat().st_size <= 9 * 2**20 for path in files)  # default 9 MiB shards
    for path in files:
        assert f"wrote {path} (" in done.stdout
    assert "max |packed - original| = " in done.stdout
    assert float(done.stdout.rsplit("= ", 1)[1].split()[0]) < 1e-2


def test_a_file_that_is_no_checkpoint_of_tensors_is_told_by_what_it_holds_without_torchs_advice(tmp_path):
    """What the file holds decides the message (torch reads its pickle without running it), never torch's words, and
    torch's advice to load with weights_only=False (which runs the file) is never passed on."""
    torch.save({"model": print}, tmp_path / "pickled.ckpt")
    (tmp_path / "random.ckpt").write_bytes(bytes(range(256)) * 8)
    with pytest.raises(CheckpointError) as pickled:
        read_checkpoint(tmp_path / "pickled.ckpt")
    assert "not a torch checkpoint of tensors and plain data" in str(pickled.value)
    assert "builtins.print" in str(pickled.value)
    with pytest.raises(CheckpointError) as random:
        read_checkpoint(tmp_path / "random.ckpt")
    assert "not a torch checkpoint (" in str(random.value) and "weights_only" not in str(random.value)
