"""What ``drivebench train`` is asked (:class:`TrainOptions`), what it gives back (:class:`TrainResult`), its errors,
and the names of the files a training run writes."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from torch import nn

from brains.nets import MODELS

BEST_FILE, LAST_FILE, METRICS_FILE, CURVE_FILE = "model.ckpt", "last.ckpt", "metrics.json", "curve.png"
LABEL_KINDS = ("zscore", "paper")
DEVICES = ("auto", "cpu", "cuda")
EVAL_BATCH = 256
# Options a resumed run must share with the run that wrote last.ckpt; epochs, patience, device, threads may change.
RESUME_FIXED = (
    "model",
    "data",
    "hyper",
    "seed",
    "lr",
    "batch_size",
    "labels",
    "max_samples_per_epoch",
    "augment",
    "augment_noise",
    "balance",
    "eval_train_samples",
    "limit_train_samples",
)


class TrainError(RuntimeError):
    """A training request that cannot run (bad options, dataset, model/dataset mismatch): one line."""


class TrainInterrupted(KeyboardInterrupt):
    """Ctrl-C during training: last.ckpt was saved at ``epoch``/``batch``; resume continues from there."""

    def __init__(self, last_checkpoint: Path, epoch: int, batch: int):
        super().__init__(f"interrupted in epoch {epoch} after batch {batch}; state saved to {last_checkpoint}")
        self.last_checkpoint, self.epoch, self.batch = last_checkpoint, epoch, batch


@dataclass(frozen=True, kw_only=True)
class TrainOptions:
    """What ``train`` does.

    model: a brains.nets.MODELS key. data: dataset folder. output: run folder.
    epochs: maximum epochs (an epoch = len(train split) samples, or max_samples_per_epoch if smaller).
    lr: Adam learning rate. device: "auto" (cuda if available), "cpu" or "cuda".
    patience: epochs without a lower monitored loss before stopping early.
    labels: "zscore" (train-split mean/std) or "paper" (DLS's fixed ranges).
    hyper: make_model keyword arguments (int, float, bool or str values). threads: torch intra-op threads.
    augment: mirror/colour-jitter/blur training batches. balance: sample ∝ 1/frequency of the |w| bin.
    augment_noise: with augment, salt and pepper noise of density up to this on half the training samples (as the
        camera's noise looks after the network's resize: see ``salt_pepper_resized``); 0 = off.
    resume: continue from output/last.ckpt. overwrite: replace an existing run in output.
    any_crop: train on a dataset whose rows are not the model's (its crop is recorded and served); else an error.
    eval_train_samples: size of the fixed training subset evaluated each epoch (no augmentation).
    limit_train_samples: draw from a fixed random subset of this many training samples only (overfitting sanity
        checks, quick experiments); an epoch keeps the train split's size.
    """

    model: str
    data: Path
    output: Path
    epochs: int = 50
    batch_size: int = 64
    lr: float = 1e-3
    device: str = "auto"
    seed: int = 0
    patience: int = 10
    labels: str = "zscore"
    hyper: dict[str, Any] = field(default_factory=dict)
    threads: int | None = None
    max_samples_per_epoch: int | None = None
    augment: bool = True
    augment_noise: float = 0.0
    balance: bool = True
    resume: bool = False
    overwrite: bool = False
    eval_train_samples: int = 2000
    limit_train_samples: int | None = None
    any_crop: bool = False

    def __post_init__(self) -> None:
        for name in ("epochs", "batch_size", "patience", "eval_train_samples"):
            if getattr(self, name) < 1:
                raise TrainError(f"{name} must be >= 1, got {getattr(self, name)}")
        for name in ("threads", "max_samples_per_epoch", "limit_train_samples"):
            if getattr(self, name) is not None and getattr(self, name) < 1:
                raise TrainError(f"{name} must be >= 1, got {getattr(self, name)}")
        if not 0.0 <= self.augment_noise <= 1.0:
            raise TrainError(f"augment_noise must be within 0..1, got {self.augment_noise}")
        if not (self.lr > 0 and math.isfinite(self.lr)):
            raise TrainError(f"lr must be a positive number, got {self.lr}")
        if self.labels not in LABEL_KINDS:
            raise TrainError(f"labels must be one of {', '.join(LABEL_KINDS)}, got {self.labels!r}")
        if self.device not in DEVICES:
            raise TrainError(f"device must be one of {', '.join(DEVICES)}, got {self.device!r}")
        if self.model not in MODELS:
            raise TrainError(f"unknown model {self.model!r} (known: {', '.join(sorted(MODELS))})")
        if bad := {k: v for k, v in self.hyper.items() if not isinstance(v, (bool, int, float, str))}:
            raise TrainError(f"hyper-parameters must be int, float, bool or str, got {bad!r}")

    def fixed(self) -> dict[str, Any]:
        """The options that identify a run for resuming, as plain types."""
        plain = {**asdict(self), "data": str(Path(self.data).resolve())}
        return {name: plain[name] for name in RESUME_FIXED}


@dataclass(frozen=True)
class TrainResult:
    """A finished run: paths, the best checkpoint's metrics, throughput (training samples per second) and the
    model with the best weights (eval mode, on the training device)."""

    output: Path
    checkpoint: Path
    metrics: dict[str, Any]
    epochs_run: int
    best_epoch: int
    samples_per_s: float
    model: nn.Module
