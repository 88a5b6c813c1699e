"""Training the paper's networks on datasets collected from the simulator: overfitting, checkpoints, resume,
determinism, class balance, augmentation, and one-line errors."""

from __future__ import annotations

import json
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from needs import require

torch = require("torch")

import cv2  # noqa: E402

from brains.nets.preprocess import prepare_batch  # noqa: E402
from brains.neural.checkpoint import build_model, load_checkpoint, read_checkpoint  # noqa: E402
from brains.training import trainer as training  # noqa: E402
from brains.training.augment import augment_batch, mirror, to_unit_float  # noqa: E402
from brains.training.trainer import (  # noqa: E402
    CHECKPOINT_FORMAT,
    CheckpointError,
    TrainError,
    TrainInterrupted,
    TrainOptions,
    balance_weights,
    label_norm,
    train,
)
from orchestrator.cli import main  # noqa: E402
from orchestrator.cli import train as train_cli  # noqa: E402
from recorder.dataset.build import DrivingDataset  # noqa: E402

TINY = "deepest_lstm_tiny_pilotnet"


def drivebench(*args: str) -> None:
    result = subprocess.run(
        [sys.executable, "-m", "orchestrator.cli", *map(str, args)], capture_output=True, text=True, timeout=150
    )
    assert result.returncode == 0, result.stderr


@pytest.fixture(scope="session")
def datasets(tmp_path_factory) -> dict[str, Path]:
    """Two 12 s episodes of the explicit brain (simple, many_curves), ~240 frames each, stored twice:
    "seq3": 100x50 full frame, offsets (-4, -2, 0), one episode each side of the split;
    "crop": 100x50 lower half (DeepestLSTMTinyPilotNet), one frame, everything in train."""
    root = tmp_path_factory.mktemp("training-data")
    drivebench(
        "dataset",
        "collect",
        "--circuits",
        "simple,many_curves",
        "--max-sim-seconds",
        "12",
        "-o",
        root / "seq3",
        "--history",
        "3",
        "--stride",
        "2",
        "--split",
        "episode:0.5",
    )
    recordings = sorted((root / "seq3.recordings").glob("*.mcap"))
    drivebench("dataset", "build", *recordings, "-o", root / "crop", "--crop", "0.5:1", "--split", "none")
    return {"seq3": root / "seq3", "crop": root / "crop"}


def options(data: Path, output: Path, **overrides) -> TrainOptions:
    """Small, fast, single-threaded (the results then do not depend on the machine's core count)."""
    settings = dict(
        model=TINY,
        data=data,
        output=output,
        epochs=4,
        batch_size=16,
        lr=1e-3,
        threads=1,
        max_samples_per_epoch=64,
        eval_train_samples=32,
        seed=0,
    )
    return TrainOptions(**{**settings, **overrides})


def state_dict(path: Path) -> dict[str, torch.Tensor]:
    return torch.load(path, map_location="cpu", weights_only=True)["state_dict"]


def assert_same_tensors(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> None:
    assert a.keys() == b.keys()
    for key in a:
        assert torch.equal(a[key], b[key]), key


def without_wall(curve: list[dict]) -> list[dict]:
    return [{k: v for k, v in point.items() if k != "wall_s"} for point in curve]


# -- end to end ------------------------------------------------------------------------------------------------------


@pytest.mark.slow
def test_tiny_model_overfits_a_small_real_dataset(datasets, tmp_path):
    out = tmp_path / "run"
    result = train(
        options(
            datasets["crop"],
            out,
            epochs=20,
            batch_size=16,
            max_samples_per_epoch=None,
            limit_train_samples=16,
            augment=False,
        ),
        progress=False,
    )
    metrics = result.metrics
    first = metrics["curve"][0]
    # After epoch 1 (already 30 steps in) versus the best epoch: the 16 samples are memorised.
    assert metrics["train"]["mse_normalised"] * 10 <= first["train_eval_loss"], metrics["curve"]
    assert metrics["curve"][-1]["train_loss"] * 10 <= first["train_loss"]
    assert metrics["val"] is None and metrics["monitor"] == "train_eval_loss"
    assert any("no validation split" in note for note in metrics["notes"])
    assert {p.name for p in out.iterdir()} == {"model.ckpt", "last.ckpt", "metrics.json", "curve.png"}
    curve_png = cv2.imread(str(out / "curve.png"))
    assert curve_png is not None and curve_png.std() > 0
    report = json.loads((out / "metrics.json").read_text())
    assert report["metrics"]["best_epoch"] == result.best_epoch and report["metrics"]["epochs_run"] == 20


@pytest.fixture(scope="module")
def memdccp_run(datasets, tmp_path_factory):
    out = tmp_path_factory.mktemp("memdccp") / "run"
    return train(options(datasets["seq3"], out, model="memdccp", epochs=1, max_samples_per_epoch=32), progress=False)


@pytest.mark.slow
def test_memdccp_checkpoint_reproduces_the_trained_model_and_its_metrics(memdccp_run, datasets):
    checkpoint = read_checkpoint(memdccp_run.checkpoint)
    model = build_model(load_checkpoint(memdccp_run.checkpoint))
    assert not model.training
    val = DrivingDataset(datasets["seq3"], split="val")
    frames, labels = val.batch(np.arange(len(val)))
    x = torch.from_numpy(prepare_batch(frames))  # the serving side's preprocessing, not the trainer's
    with torch.no_grad():
        out = model(x)
        assert torch.equal(out, memdccp_run.model(x))
    norm = checkpoint["normalisation"]
    physical = out.numpy() * np.array(norm["label_std"]) + np.array(norm["label_mean"])
    mae = np.abs(physical - labels).mean(axis=0)
    val_metrics = checkpoint["metrics"]["val"]
    assert mae == pytest.approx([val_metrics["mae_speed_mps"], val_metrics["mae_yaw_rate_radps"]], rel=1e-4)


@pytest.mark.slow
def test_checkpoint_format(memdccp_run, datasets):
    raw = torch.load(memdccp_run.checkpoint, map_location="cpu", weights_only=True)
    assert raw["format"] == CHECKPOINT_FORMAT and raw["model"] == "memdccp" and raw["hyper"] == {}
    manifest = json.loads((datasets["seq3"] / "manifest.json").read_text())
    assert raw["input"] == {
        "width_px": 100,
        "height_px": 50,
        "crop_top_fraction": 0.0,
        "crop_bottom_fraction": 1.0,
        "offsets_frames": [-4, -2, 0],
        "offsets_s": [-0.2, -0.1, 0.0],
        "step_s": 0.05,
    }
    speed, yaw = manifest["train_label_stats"]["speed_mps"], manifest["train_label_stats"]["yaw_rate_radps"]
    norm = raw["normalisation"]
    assert norm["labels"] == "zscore" and norm["image_mean"] == pytest.approx([0.485, 0.456, 0.406])
    # Train-split statistics; yaw rate symmetrised because training mirrors half the samples (w -> -w).
    assert norm["label_mean"] == pytest.approx([speed["mean"], 0.0])
    assert norm["label_std"] == pytest.approx([speed["std"], np.hypot(yaw["std"], yaw["mean"])])
    assert raw["dataset"]["samples_train"] == manifest["split"]["train_samples"]
    assert raw["dataset"]["samples_val"] == manifest["split"]["val_samples"]
    assert len(raw["dataset"]["manifest_sha256"]) == 64
    driven = {episode["circuit"] for source in manifest["sources"] for episode in source["episodes"]}
    assert raw["dataset"]["circuits"] == sorted(driven) and driven  # what a held-out draw must avoid
    metrics = raw["metrics"]
    assert (
        set(metrics["train"])
        == set(metrics["val"])
        == {"mae_speed_mps", "mae_yaw_rate_radps", "mse_normalised", "mae_paper", "mse_paper"}
    )
    assert metrics["best_epoch"] == metrics["epochs_run"] == 1
    assert set(metrics["curve"][0]) >= {
        "epoch",
        "train_loss",
        "val_loss",
        "val_mae_speed_mps",
        "val_mae_yaw_rate_radps",
        "wall_s",
    }
    assert raw["training"]["torch"] == torch.__version__ and raw["training"]["samples_per_s"] > 0
    assert {"seed", "lr", "batch_size", "epochs", "device", "wall_s"} <= set(raw["training"])
    last = torch.load(memdccp_run.output / "last.ckpt", map_location="cpu", weights_only=True)
    assert {"optimizer_state", "epoch", "rng"} <= set(last) and last["epoch"] == 1


# -- resume and determinism ------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def straight(datasets, tmp_path_factory) -> Path:
    """4 epochs in one go, with augmentation, balance and dropout (every random stream in use)."""
    out = tmp_path_factory.mktemp("straight") / "run"
    train(options(datasets["crop"], out), progress=False)
    return out


@pytest.mark.slow
def test_resume_ends_exactly_where_an_uninterrupted_run_does(straight, datasets, tmp_path):
    out = tmp_path / "run"
    train(options(datasets["crop"], out, epochs=2), progress=False)
    assert torch.load(out / "last.ckpt", weights_only=True)["epoch"] == 2
    result = train(options(datasets["crop"], out, epochs=4, resume=True), progress=False)
    assert result.epochs_run == 4
    assert_same_tensors(state_dict(out / "last.ckpt"), state_dict(straight / "last.ckpt"))
    assert_same_tensors(state_dict(out / "model.ckpt"), state_dict(straight / "model.ckpt"))
    assert without_wall(result.metrics["curve"]) == without_wall(
        read_checkpoint(straight / "model.ckpt")["metrics"]["curve"]
    )


@pytest.mark.slow
def test_ctrl_c_between_batches_saves_and_resume_continues_exactly(straight, datasets, tmp_path):
    out = tmp_path / "run"

    def press_ctrl_c(epoch: int, batch: int) -> None:
        if (epoch, batch) == (2, 2):
            signal.raise_signal(signal.SIGINT)

    with pytest.raises(TrainInterrupted) as stop:
        train(options(datasets["crop"], out), progress=False, on_batch=press_ctrl_c)
    assert (stop.value.epoch, stop.value.batch) == (2, 2) and stop.value.last_checkpoint == out / "last.ckpt"
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # our handler is gone again
    train(options(datasets["crop"], out, resume=True), progress=False)
    assert_same_tensors(state_dict(out / "last.ckpt"), state_dict(straight / "last.ckpt"))


@pytest.mark.slow
def test_same_seed_same_weights_other_seed_other_weights(straight, datasets, tmp_path):
    train(options(datasets["crop"], tmp_path / "again"), progress=False)
    assert_same_tensors(state_dict(tmp_path / "again" / "last.ckpt"), state_dict(straight / "last.ckpt"))
    train(options(datasets["crop"], tmp_path / "seed1", epochs=1, seed=1), progress=False)
    train(options(datasets["crop"], tmp_path / "seed0", epochs=1, seed=0), progress=False)
    a, b = state_dict(tmp_path / "seed0" / "last.ckpt"), state_dict(tmp_path / "seed1" / "last.ckpt")
    assert any(not torch.equal(a[key], b[key]) for key in a)


@pytest.mark.slow
def test_an_existing_run_is_neither_overwritten_nor_resumed_with_other_options(straight, datasets):
    with pytest.raises(TrainError, match="already holds"):
        train(options(datasets["crop"], straight), progress=False)
    with pytest.raises(TrainError, match="options differ.*lr"):
        train(options(datasets["crop"], straight, lr=0.01, resume=True), progress=False)


# -- pieces ----------------------------------------------------------------------------------------------------------


@pytest.mark.slow
def test_training_inputs_equal_the_serving_preprocessing(datasets):
    """What the network sees in training (without augmentation) is what brains.nets.preprocess gives at run time."""
    for name, frames_per_sample in (("seq3", 3), ("crop", 1)):
        dataset = DrivingDataset(datasets[name], split="train")
        split = training.Split(dataset, frames_per_sample, torch.device("cpu"))
        norm = label_norm("zscore", split.labels())
        positions = np.arange(0, len(dataset), 25)
        x, y_n = split.batch(positions, norm)
        frames, labels = dataset.batch(positions)
        expected = prepare_batch(frames if frames_per_sample == 3 else frames[:, -1])
        assert x.shape == expected.shape and torch.allclose(x, torch.from_numpy(expected), atol=1e-6)
        assert torch.allclose(norm.denormalise(y_n), torch.from_numpy(labels), atol=1e-5)


def test_rare_yaw_rate_bins_get_larger_sampling_weights():
    w = np.array([0.05] * 90 + [-1.2] * 10)  # bins [0, 0.1) and [1.0, 1.5)
    weights = balance_weights(w)
    assert weights.sum() == pytest.approx(1.0)
    assert weights[-1] == pytest.approx(9 * weights[0])  # 1 / frequency: each bin drawn equally often
    lone = balance_weights(np.array([0.05] * 1000 + [5.0]))
    assert lone[-1] == pytest.approx(training.BALANCE_CAP * lone[0])  # capped, not 1000x


def test_mirror_flips_images_and_negates_yaw_rate_only_where_asked():
    frames = (torch.arange(2 * 3 * 4 * 5 * 3) % 251).to(torch.uint8).view(2, 3, 4, 5, 3)  # (B, T, H, W, RGB)
    labels = torch.tensor([[7.0, 0.4], [8.0, -0.3]])
    out, new = mirror(frames, labels, torch.tensor([True, False]))
    assert torch.equal(out[0, :, :, 0], frames[0, :, :, 4]) and torch.equal(out[0, :, :, 4], frames[0, :, :, 0])
    assert torch.equal(out[0], frames[0].flip(-2)) and not torch.equal(out[0], frames[0])
    assert torch.equal(out[1], frames[1])
    assert torch.equal(new, torch.tensor([[7.0, -0.4], [8.0, -0.3]]))
    only_mirror = dict(jitter=0.0, blur_p=0.0)
    out, new = augment_batch(frames, labels, torch.Generator().manual_seed(0), mirror_p=1.0, **only_mirror)
    assert torch.allclose(out, to_unit_float(frames.flip(-2))) and torch.equal(new[:, 1], -labels[:, 1])


def test_augmentation_shares_its_parameters_across_the_frames_of_a_sample():
    frame = torch.randint(0, 256, (16, 1, 8, 10, 3), dtype=torch.uint8, generator=torch.Generator().manual_seed(1))
    frames = frame.expand(16, 3, 8, 10, 3).contiguous()  # three identical frames per sample
    out, _ = augment_batch(frames, torch.zeros(16, 2), torch.Generator().manual_seed(2), blur_p=0.5)
    assert torch.equal(out[:, 0], out[:, 1]) and torch.equal(out[:, 0], out[:, 2])
    assert not torch.allclose(out, to_unit_float(frames), atol=0.01)  # it did change the images


def test_label_normalisations():
    labels = np.array([[6.0, -0.5], [8.0, 0.5]], dtype=np.float32)
    z = label_norm("zscore", labels + np.float32([0.0, 0.1]))
    assert z.mean == pytest.approx((7.0, 0.1)) and z.std == pytest.approx((1.0, 0.5))
    mirrored = label_norm("zscore", labels + np.float32([0.0, 0.1]), mirrored=True)  # w and -w: mean 0
    assert mirrored.mean == pytest.approx((7.0, 0.0)) and mirrored.std == pytest.approx((1.0, np.sqrt(0.26)))
    y = torch.tensor(labels)
    assert torch.allclose(z.denormalise(z.normalise(y)), y)
    paper = label_norm("paper", labels)
    assert paper.to_dict()["label_mean"] == [6.5, -7.1] and paper.to_dict()["label_std"] == [17.5, 14.2]
    assert torch.allclose(paper.normalise(torch.tensor([[24.0, 7.1]])), torch.tensor([[1.0, 1.0]]))


# -- errors ----------------------------------------------------------------------------------------------------------


def one_line_error(kind, call) -> str:
    with pytest.raises(kind) as caught:
        call()
    message = str(caught.value)
    assert "\n" not in message and message
    return message


@pytest.mark.slow
def test_model_and_dataset_mismatches_are_one_line_errors(datasets, tmp_path):
    message = one_line_error(TrainError, lambda: train(options(datasets["crop"], tmp_path / "a", model="pilotnet")))
    assert "200x66" in message and "100x50" in message
    message = one_line_error(TrainError, lambda: train(options(datasets["crop"], tmp_path / "b", model="memdccp")))
    assert "3 frames" in message and "(0)" in message
    message = one_line_error(TrainError, lambda: options(datasets["crop"], tmp_path / "c", model="alexnet"))
    assert "alexnet" in message and TINY in message
    message = one_line_error(
        TrainError, lambda: train(options(datasets["seq3"], tmp_path / "d", model="memdccp", hyper={"warp": 9}))
    )
    assert "warp" in message
    message = one_line_error(TrainError, lambda: train(options(tmp_path / "nothing", tmp_path / "e")))
    assert "nothing" in message


def test_read_checkpoint_refuses_missing_garbage_and_incomplete_files(tmp_path):
    message = one_line_error(CheckpointError, lambda: read_checkpoint(tmp_path / "absent.ckpt"))
    assert "absent.ckpt" in message
    garbage = tmp_path / "garbage.ckpt"
    garbage.write_bytes(b"\x00not a checkpoint" * 100)
    assert "garbage.ckpt" in one_line_error(CheckpointError, lambda: read_checkpoint(garbage))
    other = tmp_path / "other.ckpt"
    torch.save({"weights": torch.zeros(3)}, other)
    assert "format" in one_line_error(CheckpointError, lambda: read_checkpoint(other))
    partial = tmp_path / "partial.ckpt"
    torch.save({"format": CHECKPOINT_FORMAT, "model": "memdccp", "input": {"width_px": 100}}, partial)
    message = one_line_error(CheckpointError, lambda: read_checkpoint(partial))
    assert "state_dict" in message and "input.offsets_frames" in message and "partial.ckpt" in message


def cli(*argv: str) -> int:
    """``drivebench train ARGV...``: its exit code."""
    return main(["train", *argv])


def test_cli_errors_are_one_line_with_exit_code_2(tmp_path, capsys):
    assert cli("--model", TINY, "--data", str(tmp_path / "missing"), "-o", str(tmp_path / "run")) == 2
    err = capsys.readouterr().err
    assert err.startswith("drivebench: error: ") and err.count("\n") == 1 and "missing" in err
    assert cli("--model", TINY, "--data", str(tmp_path), "-o", str(tmp_path / "run"), "--hyper", "dropout") == 2
    assert "KEY=VALUE" in capsys.readouterr().err


def test_cli_ctrl_c_says_how_to_resume(tmp_path, capsys, monkeypatch):
    def interrupted(*args, **kwargs):
        raise TrainInterrupted(tmp_path / "last.ckpt", 3, 7)

    monkeypatch.setattr(training, "train", interrupted)
    assert cli("--model", TINY, "--data", str(tmp_path), "-o", str(tmp_path)) == 130
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--resume" in err and "last.ckpt" in err


def test_hyper_values_are_typed():
    assert train_cli.parse_hyper(["clean=true", "lstm_units=16", "dropout=0.1", "name=x"]) == {
        "clean": True,
        "lstm_units": 16,
        "dropout": 0.1,
        "name": "x",
    }
    with pytest.raises(train_cli.HyperError):
        train_cli.parse_hyper(["=3"])


def test_salt_and_pepper_augmentation_looks_like_the_injectors_noise_after_the_resize():
    from brains.training.augment import augment_batch, salt_pepper_resized

    generator = torch.Generator().manual_seed(0)
    x = torch.full((2, 3, 3, 50, 100), 0.3)
    noisy = salt_pepper_resized(x, torch.tensor([0.0, 0.6]), generator)
    assert torch.equal(noisy[0], x[0])  # density 0: untouched
    # each pixel mixes its kept share of the image with replaced pixels, half of them white
    assert float(noisy[1].mean()) == pytest.approx(0.3 * 0.4 + 0.6 * 0.5, abs=0.01)
    assert torch.equal(noisy[1, :, 0], noisy[1, :, 2])  # whole pixels replaced: the same in every channel
    assert float(noisy[1].std()) > 0.1  # speckled, not a uniform shift
    frames = torch.randint(0, 256, (4, 3, 50, 100, 3), dtype=torch.uint8)
    labels = torch.zeros(4, 2)
    plain = augment_batch(frames, labels, torch.Generator().manual_seed(1))
    zero = augment_batch(frames, labels, torch.Generator().manual_seed(1), noise_max=0.0)
    assert torch.equal(plain[0], zero[0])  # off: the same batch, the same random sequence as before
    with_noise = augment_batch(frames, labels, torch.Generator().manual_seed(1), noise_max=0.7)
    assert not torch.equal(plain[0], with_noise[0])


# -- training seeds as an axis (drivebench train --seeds) ----------------------------------------------------------


def train_seeds(data: Path, output: Path, *extra: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "orchestrator.cli", "train", "--model", TINY, "--data", str(data), "-o", str(output),
         "--epochs", "1", "--max-samples-per-epoch", "16", "--batch-size", "8", "--threads", "1", *extra],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip


@pytest.mark.slow  # over 9 s: out of the quick tier
def test_seeds_train_one_run_each_with_a_manifest_and_a_rerun_keeps_them(datasets, tmp_path):
    out = tmp_path / "tiny"
    first = train_seeds(datasets["crop"], out, "--seeds", "0-2", "--workers", "2")
    assert first.returncode == 0, first.stderr[-2000:]
    manifest = json.loads((out / "training.json").read_text())
    assert [(r["seed"], r["status"], r["best_epoch"]) for r in manifest["runs"]] == [(s, "done", 1) for s in range(3)]
    assert manifest["data_manifest_sha256"] and "--seed" not in manifest["recipe"]
    weights = [state_dict(out / f"seed-{seed}" / "model.ckpt") for seed in range(3)]
    assert [read_checkpoint(out / f"seed-{s}" / "model.ckpt")["training"]["seed"] for s in range(3)] == [0, 1, 2]
    assert any(not torch.equal(weights[0][name], weights[1][name]) for name in weights[0])  # other seed, other run
    kept = (out / "seed-0" / "model.ckpt").stat().st_mtime_ns
    shutil.rmtree(out / "seed-1")
    again = train_seeds(datasets["crop"], out, "--seeds", "0-2")
    assert again.returncode == 0, again.stderr[-2000:]
    assert "seed 0: already trained" in again.stderr and "seed 1: training" in again.stderr
    assert (out / "seed-0" / "model.ckpt").stat().st_mtime_ns == kept
    assert_same_tensors(state_dict(out / "seed-1" / "model.ckpt"), weights[1])  # the same seed trains the same


def processes_naming(text: str) -> list[str]:
    """The command lines of this machine's processes that contain ``text`` (read from /proc)."""
    found = []
    for cmdline in Path("/proc").glob("[0-9]*/cmdline"):
        try:
            line = cmdline.read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:  # the process ended while we looked
            continue
        if text in line:
            found.append(line)
    return found


@pytest.mark.slow
def test_sigterm_to_a_seeds_training_stops_every_seed_and_a_rerun_resumes(datasets, tmp_path):
    """`kill PID` of `train --seeds 0-1 --workers 2` (a SIGTERM to it alone, as a job scheduler sends): it exits at
    once, no seed's training outlives it, and the manifest says both were interrupted. It used to wait, holding the
    SIGTERM, while both trainings ran to their end (a rerun would then train the same seed twice at once)."""
    out = tmp_path / "tiny"
    command = [sys.executable, "-m", "orchestrator.cli", "train", "--model", TINY, "--data", str(datasets["crop"]),
               "-o", str(out), "--epochs", "500", "--max-samples-per-epoch", "16", "--batch-size", "8",
               "--threads", "1", "--seeds", "0-1", "--workers", "2"]  # fmt: skip
    parent = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 120
        while not all((out / f"seed-{seed}" / "last.ckpt").is_file() for seed in (0, 1)):  # both are training
            assert parent.poll() is None and time.monotonic() < deadline, "the seeds never started training"
            time.sleep(0.2)
        parent.send_signal(signal.SIGTERM)
        _, stderr = parent.communicate(timeout=60)
    finally:
        parent.kill()
    assert processes_naming(str(out)) == [], "a seed's training outlived its parent"
    assert parent.returncode != 0, stderr[-2000:]
    manifest = json.loads((out / "training.json").read_text())
    assert [(run["seed"], run["status"]) for run in manifest["runs"]] == [(0, "interrupted"), (1, "interrupted")]
    rerun = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        assert rerun.stderr is not None
        said = [rerun.stderr.readline() for _ in range(2)]  # each seed says what it does before it starts
        rerun.send_signal(signal.SIGTERM)
        rerun.communicate(timeout=60)
    finally:
        rerun.kill()
    assert sorted(line.split(" ->")[0] for line in said) == ["seed 0: resuming", "seed 1: resuming"], said


@pytest.mark.slow
def test_seeds_refuse_a_changed_recipe_and_say_the_wall_time_the_manifest_keeps(datasets, tmp_path):
    """A folder's seeds all share one recipe: another --epochs or --model over it is one line naming the difference
    (exit 2), training.json stays as it was, and no seed starts; the console's time is training.json's wall_s."""
    out = tmp_path / "R"
    first = train_seeds(datasets["crop"], out, "--seeds", "0")
    assert first.returncode == 0, first.stderr[-2000:]
    manifest = (out / "training.json").read_text()
    wall_s = json.loads(manifest)["runs"][0]["wall_s"]
    assert f"seed 0: done in {wall_s:.1f} s" in first.stderr, first.stderr  # one definition, both places
    for extra, difference in (
        (["--epochs", "3"], "--epochs was 1, now 3"),
        (["--model", "pilotnet"], f"--model was {TINY}, now pilotnet"),
        (["--no-augment"], "--no-augment was absent, now given"),
    ):
        changed = train_seeds(datasets["crop"], out, "--seeds", "0-1", *extra)
        assert changed.returncode == 2 and difference in changed.stderr, changed.stderr
        assert len(changed.stderr.strip().splitlines()) == 1 and "another -o folder" in changed.stderr
        assert (out / "training.json").read_text() == manifest and not (out / "seed-1").exists()
    added = train_seeds(datasets["crop"], out, "--seeds", "0-1")  # the same recipe, one seed more: kept + trained
    assert added.returncode == 0 and "seed 0: already trained" in added.stderr, added.stderr[-2000:]
    assert [run["seed"] for run in json.loads((out / "training.json").read_text())["runs"]] == [0, 1]


@pytest.mark.parametrize(
    ("seeds", "message"),
    [
        (["--seeds", "4-0"], "is empty"),
        (["--seeds", "a"], "not a seed"),
        (["--seeds", "1,1"], "named twice"),
        (["--seeds", "0-2", "--seed", "3"], "drop --seed"),
        (["--seeds", "0-2", "--workers", "0"], "--workers must be >= 1"),
    ],
)
def test_bad_seed_lists_are_one_line_before_anything_starts(datasets, tmp_path, seeds, message):
    result = train_seeds(datasets["crop"], tmp_path / "out", *seeds)
    assert result.returncode == 2 and message in result.stderr, result.stderr
    assert len(result.stderr.strip().splitlines()) == 1 and not (tmp_path / "out").exists()


@pytest.mark.slow
@pytest.mark.integration
@pytest.mark.timeout(600)
def test_seeds_train_as_ray_tasks_on_a_cluster_and_match_the_local_runs(datasets, tmp_path, monkeypatch):
    """`train --seeds 0-1 --ray ADDRESS`: one task per seed on a real local Ray cluster (a head with no CPU, one
    worker node), files landed in OUT/seed-N with the manifest; the same seed trains the same weights as locally."""
    require("ray")
    from ray.cluster_utils import Cluster

    monkeypatch.setenv("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")  # loopback only (see tests/test_ray_matrix.py)
    cluster = Cluster(
        initialize_head=True, connect=False, head_node_args={"num_cpus": 0, "node_ip_address": "127.0.0.1"}
    )
    try:
        cluster.add_node(num_cpus=1, node_ip_address="127.0.0.1")
        cluster.wait_for_nodes()
        out = tmp_path / "on-ray"
        done = train_seeds(datasets["crop"], out, "--seeds", "0-1", "--ray", cluster.address)
        assert done.returncode == 0, done.stderr[-2000:]
        assert "seed 0: done on" in done.stderr and "seed 1: done on" in done.stderr
        manifest = json.loads((out / "training.json").read_text())
        assert [(r["seed"], r["status"]) for r in manifest["runs"]] == [(0, "done"), (1, "done")]
        assert (out / "seed-1" / "train.log").is_file() and (out / "seed-1" / "metrics.json").is_file()
        local = train_seeds(datasets["crop"], tmp_path / "local", "--seeds", "1")
        assert local.returncode == 0, local.stderr[-2000:]
        assert_same_tensors(
            state_dict(out / "seed-1" / "model.ckpt"), state_dict(tmp_path / "local" / "seed-1" / "model.ckpt")
        )
        again = train_seeds(datasets["crop"], out, "--seeds", "0-1", "--ray", cluster.address)
        assert again.returncode == 0 and again.stderr.count("already trained") == 2, again.stderr[-2000:]
    finally:
        cluster.shutdown()


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--ray-resource", "GPU=1"], "--ray-resource goes with --ray"),
        (["--ray", "127.0.0.1:9", "--ray-resource", "GPU=0"], "expected NAME=AMOUNT with AMOUNT > 0"),
        (["--ray", "127.0.0.1:9", "--workers", "2"], "--workers is for a local run"),
    ],
)
def test_seed_ray_mistakes_are_one_line(datasets, tmp_path, extra, message):
    done = train_seeds(datasets["crop"], tmp_path / "out", "--seeds", "0-1", *extra)
    assert done.returncode == 2 and message in done.stderr and done.stderr.count("\n") == 1, done.stderr
