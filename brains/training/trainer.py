"""Supervised training of the paper's networks on a drivebench dataset folder (pure core: no Zenoh, no CLI parsing).

``train(TrainOptions(...))`` fits one network of :data:`brains.nets.MODELS` to a dataset built by
``drivebench dataset build|collect`` (:class:`recorder.dataset.build.DrivingDataset`) and writes a run folder:

    model.ckpt    the best weights (lowest validation loss), in the checkpoint format below
    last.ckpt     the latest state, for ``resume``: the same format plus optimizer_state, epoch, rng, resume
    metrics.json  the checkpoint's metrics, training and dataset sections as JSON
    curve.png     training/validation loss and validation MAE per epoch

Checkpoint format ``drivebench.checkpoint.v1`` (``torch.save`` of plain types and tensors; loads with
``torch.load(path, weights_only=True)``)::

    format         "drivebench.checkpoint.v1"
    model          a brains.nets.MODELS key;  hyper: kwargs for make_model;  state_dict: model.state_dict()
    input          width_px, height_px, crop_top_fraction, crop_bottom_fraction, offsets_frames, offsets_s, step_s
    normalisation  image_mean, image_std (ImageNet, on pixels / 255), labels ("zscore" | "paper"),
                   label_mean, label_std: physical [v m/s, w rad/s] = network output * label_std + label_mean
    dataset        path, manifest_sha256, samples_train, samples_val, circuits (every circuit the data drove)
    metrics        train / val: mae_speed_mps, mae_yaw_rate_radps, mse_normalised, mae_paper, mse_paper (val is
                   None without a val split); best_epoch, epochs_run, curve (one dict per epoch), monitor,
                   stopped_early, notes
    training       seed, lr, batch_size, epochs, device, wall_s, samples_per_s, torch (+ the other options)

Pipeline: one gather per batch from the memory-mapped uint8 frames, then everything on torch tensors on the
training device: /255, augmentation (training batches only; one parameter set per sample, shared by its frames),
ImageNet normalisation. Class balance comes from a weighted sampler over |w| histogram bins, never from copies.
Deterministic on CPU for a given seed and thread count; a resumed run ends bit-identical to an uninterrupted one.
"""

from __future__ import annotations

import copy
import json
import math
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from brains.nets import MODELS, make_model
from brains.neural.checkpoint import FORMAT as CHECKPOINT_FORMAT
from brains.neural.checkpoint import CheckpointError, read_checkpoint, write_checkpoint
from brains.training.curve import plot_curve
from brains.training.data import Split, crop_notes, dataset_circuits, evaluate, input_section, open_dataset, sha256
from brains.training.labels import BALANCE_CAP, LabelNorm, balance_weights, label_norm
from brains.training.options import (
    BEST_FILE,
    CURVE_FILE,
    LAST_FILE,
    METRICS_FILE,
    TrainError,
    TrainInterrupted,
    TrainOptions,
    TrainResult,
)
from recorder.dataset.build import MANIFEST_FILE

# -- training --------------------------------------------------------------------------------------------------------


@dataclass
class _Progress:
    """Everything besides weights and optimizer that a resumed run restores."""

    epoch: int = 0  # completed epochs
    best_epoch: int = 0
    best_loss: float = math.inf
    bad_epochs: int = 0
    curve: list[dict[str, Any]] = field(default_factory=list)
    best_metrics: dict[str, Any] = field(default_factory=dict)  # {"train": ..., "val": ...} at best_epoch
    train_seconds: float = 0.0  # time in training batches only (for samples/s)
    train_samples: int = 0
    wall_s: float = 0.0  # wall time of earlier sessions
    partial: dict[str, Any] | None = None  # position inside an interrupted epoch


def _subset(rng: np.random.Generator, size: int, limit: int | None) -> np.ndarray:
    """Sorted positions 0..size-1, or a random choice of ``limit`` of them."""
    if limit is None or limit >= size:
        return np.arange(size)
    return np.sort(rng.choice(size, limit, replace=False))


def _epoch_generator(seed: int, epoch: int, stream: int) -> torch.Generator:
    """A generator per (seed, epoch, stream): epochs can be replayed without storing the sampler's state."""
    return torch.Generator().manual_seed((seed * 1_000_003 + epoch) * 4 + stream)


@contextmanager
def _sigint_flag() -> Iterator[threading.Event]:
    """The first Ctrl-C sets the event (checked between batches, so no step is cut in half); a second one
    raises KeyboardInterrupt at once. Outside the main thread no handler can be installed: the event stays unset."""
    event = threading.Event()
    if threading.current_thread() is not threading.main_thread():
        yield event
        return

    def handler(signum, frame):
        if event.is_set():
            raise KeyboardInterrupt
        event.set()

    previous = signal.signal(signal.SIGINT, handler)
    try:
        yield event
    finally:
        signal.signal(signal.SIGINT, previous)


@contextmanager
def _torch_settings(threads: int | None, device: torch.device) -> Iterator[None]:
    """Deterministic algorithms (warn-only on CUDA, where some kernels have none) and the thread count, restored
    afterwards: the process may train again with other settings."""
    old_threads = torch.get_num_threads()
    old_deterministic = torch.are_deterministic_algorithms_enabled()
    old_warn = torch.is_deterministic_algorithms_warn_only_enabled()
    if threads is not None:
        torch.set_num_threads(threads)
    torch.use_deterministic_algorithms(True, warn_only=device.type != "cpu")
    try:
        yield
    finally:
        torch.set_num_threads(old_threads)
        torch.use_deterministic_algorithms(old_deterministic, warn_only=old_warn)


def _resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise TrainError("device cuda requested but torch sees no CUDA device (use --device cpu or auto)")
    return torch.device(name)


class _Trainer:
    """One training session; ``run`` returns the result or raises TrainInterrupted after saving last.ckpt."""

    def __init__(
        self,
        options: TrainOptions,
        *,
        progress: bool,
        log: Callable[[str], None] | None,
        on_batch: Callable[[int, int], None] | None,
    ):
        self.options, self.show_progress, self.log, self.on_batch = options, progress, log, on_batch
        self.info = MODELS[options.model]
        self.device = _resolve_device(options.device)
        self.output = Path(options.output)
        train, val = open_dataset(options, self.info)
        self.train_split = Split(train, self.info.frames, self.device, noise_max=options.augment_noise)
        self.val_split = Split(val, self.info.frames, self.device) if val is not None else None
        labels = self.train_split.labels()
        self.norm = label_norm(options.labels, labels, mirrored=options.augment)
        rng = np.random.default_rng(options.seed)
        self.pool = _subset(rng, len(train), options.limit_train_samples)  # positions in the train split we draw
        self.weights = torch.from_numpy(
            balance_weights(labels[self.pool, 1]) if options.balance else np.full(len(self.pool), 1 / len(self.pool))
        )
        # A fixed subset: the per-epoch training metric then compares like with like across epochs.
        self.train_eval = self.pool[_subset(rng, len(self.pool), options.eval_train_samples)]
        self.epoch_size = min(len(train), options.max_samples_per_epoch or len(train))
        self.notes = crop_notes(self.info, train.manifest)
        self.state = _Progress()
        self.session_start = time.perf_counter()

    # -- set-up

    def build(self) -> None:
        """Model and optimizer, fresh or restored from last.ckpt."""
        self._prepare_output()
        torch.manual_seed(self.options.seed)  # initial weights, then dropout draws from the global generator
        try:
            self.model = make_model(self.options.model, **self.options.hyper).to(self.device)
        except (TypeError, ValueError) as error:
            raise TrainError(f"bad hyper-parameters {self.options.hyper} for {self.options.model}: {error}") from None
        self.optimizer = torch.optim.Adam(self.model.parameters(), lr=self.options.lr)
        self.best_state = copy.deepcopy(self.model.state_dict())
        if self.options.resume:
            self._restore(self.output / LAST_FILE)

    def _prepare_output(self) -> None:
        existing = [name for name in (BEST_FILE, LAST_FILE) if (self.output / name).exists()]
        if self.options.resume and not (self.output / LAST_FILE).is_file():
            raise TrainError(f"cannot resume: {self.output / LAST_FILE} does not exist")
        if existing and not self.options.resume and not self.options.overwrite:
            raise TrainError(
                f"run folder {self.output} already holds {', '.join(existing)}; resume it (--resume) or "
                f"start again (--overwrite)"
            )
        try:
            self.output.mkdir(parents=True, exist_ok=True)
            for name in existing if self.options.overwrite and not self.options.resume else ():
                (self.output / name).unlink()
        except OSError as error:
            raise TrainError(f"cannot use run folder {self.output}: {error.strerror or error}") from None

    def _restore(self, path: Path) -> None:
        try:
            last = read_checkpoint(path)
            resume = last["resume"]
            if resume["options"] != self.options.fixed():
                diff = {
                    k: (resume["options"].get(k), v)
                    for k, v in self.options.fixed().items()
                    if resume["options"].get(k) != v
                }
                raise TrainError(f"cannot resume {path}: options differ (saved, now): {diff}")
            if last["dataset"]["manifest_sha256"] != sha256(Path(self.options.data) / MANIFEST_FILE):
                raise TrainError(f"cannot resume {path}: the dataset {self.options.data} changed since")
            self.model.load_state_dict(last["state_dict"])
            self.optimizer.load_state_dict(last["optimizer_state"])
            self.best_state = last["resume"]["best_state_dict"]
        except (CheckpointError, KeyError) as error:
            raise TrainError(f"cannot resume from {path}: {error}") from None
        self.state = _Progress(**{k: v for k, v in resume["progress"].items()})
        torch.set_rng_state(last["rng"]["torch"])
        if self.device.type == "cuda" and last["rng"].get("cuda") is not None:
            torch.cuda.set_rng_state(last["rng"]["cuda"], self.device)

    # -- loop

    def run(self) -> TrainResult:
        if self.log is not None:
            for note in self._metrics()["notes"]:
                self.log(f"note: {note}")
        with _sigint_flag() as stop:
            self.stop = stop
            for epoch in range(self.state.epoch + 1, self.options.epochs + 1):
                if self.state.bad_epochs >= self.options.patience:
                    break
                self._epoch(epoch)
                self._end_epoch(epoch)
        return self._finish()

    def _epoch(self, epoch: int) -> None:
        """Train one epoch (or its rest, after an interrupted one) on weighted draws of the train split."""
        positions = self.pool[
            torch.multinomial(
                self.weights, self.epoch_size, replacement=True, generator=_epoch_generator(self.options.seed, epoch, 0)
            ).numpy()
        ]
        augment = _epoch_generator(self.options.seed, epoch, 1) if self.options.augment else None
        partial = self.state.partial or {"epoch": epoch, "batches": 0, "loss_sum": 0.0, "samples": 0}
        if partial["batches"] and augment is not None:
            augment.set_state(partial["augment_rng"])
        self.state.partial = None
        self.model.train()
        size = self.options.batch_size
        bar = tqdm(
            total=self.epoch_size,
            initial=partial["samples"],
            desc=f"epoch {epoch}/{self.options.epochs}",
            unit="sample",
            file=sys.stderr,
            disable=not self.show_progress,
            leave=False,
            dynamic_ncols=True,
        )
        with bar:
            for batch in range(partial["batches"], math.ceil(self.epoch_size / size)):
                loss = self._step(positions[batch * size : (batch + 1) * size], augment)
                samples = min((batch + 1) * size, self.epoch_size)
                partial = {
                    **partial,
                    "batches": batch + 1,
                    "samples": samples,
                    "loss_sum": partial["loss_sum"] + loss * (samples - partial["samples"]),
                }
                bar.update(partial["samples"] - bar.n)
                bar.set_postfix(loss=f"{loss:.4f}", refresh=False)
                if self.on_batch is not None:
                    self.on_batch(epoch, batch + 1)
                if self.stop.is_set():
                    self._interrupt(epoch, partial, augment)
        self.epoch_train_loss = partial["loss_sum"] / partial["samples"]

    def _step(self, positions: np.ndarray, augment: torch.Generator | None) -> float:
        start = time.perf_counter()
        x, y_n = self.train_split.batch(positions, self.norm, augment)
        loss = F.mse_loss(self.model(x), y_n)
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.optimizer.step()
        value = float(loss.detach())  # synchronises a GPU, so the time below is real
        self.state.train_seconds += time.perf_counter() - start
        self.state.train_samples += len(positions)
        return value

    def _interrupt(self, epoch: int, partial: dict[str, Any], augment: torch.Generator | None) -> None:
        self.state.partial = {**partial, "augment_rng": augment.get_state() if augment is not None else None}
        self._save_last()
        raise TrainInterrupted(self.output / LAST_FILE, epoch, partial["batches"])

    def _end_epoch(self, epoch: int) -> None:
        """Evaluate, keep the best weights, extend the curve, save model.ckpt (if better) and last.ckpt."""
        train_metrics = evaluate(self.model, self.train_split, self.train_eval, self.norm)
        val_metrics = (
            evaluate(self.model, self.val_split, np.arange(len(self.val_split)), self.norm)
            if self.val_split is not None
            else None
        )
        monitored = (val_metrics or train_metrics)["mse_normalised"]
        state = self.state
        state.epoch = epoch
        state.curve.append(
            {
                "epoch": epoch,
                "train_loss": self.epoch_train_loss,
                "train_eval_loss": train_metrics["mse_normalised"],
                "val_loss": val_metrics and val_metrics["mse_normalised"],
                "val_mae_speed_mps": val_metrics and val_metrics["mae_speed_mps"],
                "val_mae_yaw_rate_radps": val_metrics and val_metrics["mae_yaw_rate_radps"],
                "wall_s": self._wall_s(),
            }
        )
        improved = monitored < state.best_loss
        if improved:
            state.best_loss, state.best_epoch, state.bad_epochs = monitored, epoch, 0
            state.best_metrics = {"train": train_metrics, "val": val_metrics}
            self.best_state = copy.deepcopy(self.model.state_dict())
            write_checkpoint(self._checkpoint(self.best_state), self.output / BEST_FILE)
        else:
            state.bad_epochs += 1
        self._save_last()
        self._write_reports()
        if self.log is not None:
            self.log(self._epoch_line(epoch, improved))

    def _epoch_line(self, epoch: int, improved: bool) -> str:
        point = self.state.curve[-1]
        val = (
            f"val loss {point['val_loss']:.4f} MAE v {point['val_mae_speed_mps']:.3f} m/s w "
            f"{point['val_mae_yaw_rate_radps']:.3f} rad/s"
            if point["val_loss"] is not None
            else "no val split"
        )
        return (
            f"epoch {epoch}/{self.options.epochs}: train loss {point['train_loss']:.4f} (eval "
            f"{point['train_eval_loss']:.4f}), {val}, {self._samples_per_s():.0f} samples/s"
            f"{' *best' if improved else ''}"
        )

    def _finish(self) -> TrainResult:
        self.model.load_state_dict(self.best_state)
        checkpoint = self._checkpoint(self.best_state)
        if self.state.epoch:
            write_checkpoint(checkpoint, self.output / BEST_FILE)
            self._write_reports()
        return TrainResult(
            output=self.output,
            checkpoint=self.output / BEST_FILE,
            metrics=checkpoint["metrics"],
            epochs_run=self.state.epoch,
            best_epoch=self.state.best_epoch,
            samples_per_s=self._samples_per_s(),
            model=self.model.eval(),
        )

    # -- outputs

    def _wall_s(self) -> float:
        return self.state.wall_s + time.perf_counter() - self.session_start

    def _samples_per_s(self) -> float:
        return self.state.train_samples / self.state.train_seconds if self.state.train_seconds else 0.0

    def _metrics(self) -> dict[str, Any]:
        state = self.state
        notes = self.notes + (
            []
            if self.val_split is not None
            else [
                "dataset has no validation split: early stopping and the best checkpoint use the training-subset loss"
            ]
        )
        return {
            "train": state.best_metrics.get("train"),
            "val": state.best_metrics.get("val"),
            "best_epoch": state.best_epoch,
            "epochs_run": state.epoch,
            "curve": copy.deepcopy(state.curve),
            "monitor": "val_loss" if self.val_split is not None else "train_eval_loss",
            "stopped_early": state.bad_epochs >= self.options.patience and state.epoch < self.options.epochs,
            "notes": notes,
        }

    def _checkpoint(self, state_dict: dict[str, torch.Tensor]) -> dict[str, Any]:
        options = self.options
        manifest_path = Path(options.data) / MANIFEST_FILE
        return {
            "format": CHECKPOINT_FORMAT,
            "model": options.model,
            "hyper": dict(options.hyper),
            "state_dict": {k: v.detach().cpu() for k, v in state_dict.items()},
            "input": input_section(self.train_split.dataset.manifest, self.train_split.dataset.offsets_frames),
            "normalisation": self.norm.to_dict(),
            "dataset": {
                "path": str(Path(options.data).resolve()),
                "manifest_sha256": sha256(manifest_path),
                "samples_train": len(self.pool),
                "samples_val": len(self.val_split) if self.val_split is not None else 0,
                # Every circuit the dataset drove (both splits): a held-out matrix draw refuses these.
                "circuits": dataset_circuits(self.train_split.dataset.manifest),
            },
            "metrics": self._metrics(),
            "training": {
                "seed": options.seed,
                "lr": options.lr,
                "batch_size": options.batch_size,
                "epochs": options.epochs,
                "device": str(self.device),
                "wall_s": self._wall_s(),
                "samples_per_s": self._samples_per_s(),
                "torch": str(torch.__version__),
                "patience": options.patience,
                "labels": options.labels,
                "augment": options.augment,
                "augment_noise": options.augment_noise,
                "balance": options.balance,
                "max_samples_per_epoch": options.max_samples_per_epoch,
                "limit_train_samples": options.limit_train_samples,
                "threads": torch.get_num_threads(),
            },
        }

    def _save_last(self) -> None:
        last = self._checkpoint(self.model.state_dict())
        progress = {**asdict(self.state), "wall_s": self._wall_s()}
        last.update(
            {
                "optimizer_state": self.optimizer.state_dict(),
                "epoch": self.state.epoch,
                "rng": {
                    "torch": torch.get_rng_state(),
                    "cuda": torch.cuda.get_rng_state(self.device) if self.device.type == "cuda" else None,
                },
                "resume": {
                    "options": self.options.fixed(),
                    "progress": progress,
                    "best_state_dict": {k: v.detach().cpu() for k, v in self.best_state.items()},
                },
            }
        )
        write_checkpoint(last, self.output / LAST_FILE)

    def _write_reports(self) -> None:
        checkpoint = self._checkpoint(self.best_state)
        report = {
            key: checkpoint[key]
            for key in ("model", "hyper", "metrics", "training", "dataset", "input", "normalisation")
        }
        temporary = self.output / f".{METRICS_FILE}.tmp"
        temporary.write_text(json.dumps(report, indent=2) + "\n")
        os.replace(temporary, self.output / METRICS_FILE)
        if not plot_curve(self.state.curve, self.output / CURVE_FILE):
            raise TrainError(f"cannot write {self.output / CURVE_FILE}")


def train(
    options: TrainOptions,
    *,
    progress: bool = True,
    log: Callable[[str], None] | None = None,
    on_batch: Callable[[int, int], None] | None = None,
) -> TrainResult:
    """Train ``options.model`` on ``options.data``, writing the run folder ``options.output``.

    progress: a tqdm bar per epoch on stderr (loss, samples/s). log: called with one summary line per epoch.
    on_batch(epoch, batch): called after every training batch (1-based), e.g. for a GUI or a test.
    Raises TrainError (one line) for a request that cannot run, TrainInterrupted after Ctrl-C (last.ckpt saved).
    """
    trainer = _Trainer(options, progress=progress, log=log, on_batch=on_batch)
    with _torch_settings(options.threads, trainer.device):
        trainer.build()
        return trainer.run()


__all__ = [
    "CHECKPOINT_FORMAT",
    "CheckpointError",
    "LabelNorm",
    "TrainError",
    "TrainInterrupted",
    "TrainOptions",
    "TrainResult",
    "BALANCE_CAP",
    "balance_weights",
    "evaluate",
    "label_norm",
    "train",
]
