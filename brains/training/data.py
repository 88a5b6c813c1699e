"""The training run's data: a dataset opened and checked against the network it trains, split into train and
validation, and the evaluation of a model on a split."""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from brains.nets import ModelInfo
from brains.nets.preprocess import IMAGENET_MEAN, IMAGENET_STD, V_SCALE, W_SCALE
from brains.training.augment import augment_batch, to_unit_float
from brains.training.labels import LabelNorm
from brains.training.options import EVAL_BATCH, TrainError, TrainOptions
from recorder.dataset.build import DatasetError, DrivingDataset, describe_offsets

# -- data ------------------------------------------------------------------------------------------------------------


class Split:
    """One split of the dataset as model-ready tensors on the training device."""

    def __init__(self, dataset: DrivingDataset, frames: int, device: torch.device, *, noise_max: float = 0.0):
        self.dataset, self.frames, self.device, self.noise_max = dataset, frames, device, noise_max
        self._mean = torch.tensor(IMAGENET_MEAN, device=device).view(1, 1, 3, 1, 1)
        self._std = torch.tensor(IMAGENET_STD, device=device).view(1, 1, 3, 1, 1)

    def __len__(self) -> int:
        return len(self.dataset)

    def labels(self) -> np.ndarray:
        """Raw labels (N, 2) [v m/s, w rad/s] of this split's samples."""
        return np.asarray(self.dataset.labels[self.dataset.index])

    def batch(
        self, positions: np.ndarray, norm: LabelNorm, generator: torch.Generator | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Inputs (B, 3, H, W) or (B, T, 3, H, W) float32 and normalised labels (B, 2); augmented iff generator."""
        frames, labels = self.dataset.batch(positions)
        pixels = torch.from_numpy(frames).to(self.device)  # uint8 to the device (4x smaller), convert there
        y = torch.from_numpy(labels).to(self.device)
        if generator is not None:
            x, y = augment_batch(pixels, y, generator, noise_max=self.noise_max)
        else:
            x = to_unit_float(pixels)
        x = (x - self._mean) / self._std
        return (x[:, -1] if self.frames == 1 else x).contiguous(), norm.normalise(y)


def open_dataset(options: TrainOptions, info: ModelInfo) -> tuple[DrivingDataset, DrivingDataset | None]:
    """Train and val splits (val None when empty) with the windows the model needs; TrainError on a mismatch."""
    try:
        train = DrivingDataset(options.data, split="train")
        manifest = train.manifest
        if info.frames == 1 and tuple(manifest["offsets_frames"]) != (0,):
            # A one-frame model uses the newest frame of any window: every frame of the split is a sample.
            train = DrivingDataset(options.data, split="train", offsets_frames=(0,))
        val = DrivingDataset(options.data, split="val", offsets_frames=train.offsets_frames)
    except DatasetError as error:
        raise TrainError(str(error)) from None
    _check_compatible(options, info, manifest)
    if len(train) == 0:
        raise TrainError(f"dataset {options.data}: the train split has no sample")
    return train, (val if len(val) else None)


def _check_compatible(options: TrainOptions, info: ModelInfo, manifest: dict[str, Any]) -> None:
    width = options.hyper.get("input_width_px", info.input_width_px)
    height = options.hyper.get("input_height_px", info.input_height_px)
    got = (manifest["image_width_px"], manifest["image_height_px"])
    if got != (width, height):
        crop_flag = f" --crop {info.crop_top_fraction:g}:1" if info.crop_top_fraction else ""
        raise TrainError(
            f"model {info.name} takes {width}x{height} images (WxH) but dataset {options.data} holds "
            f"{got[0]}x{got[1]}; build it with --size {width}x{height}{crop_flag}"
        )
    offsets = manifest["offsets_frames"]
    if info.frames > 1 and len(offsets) != info.frames:
        # "--offsets=": argparse takes a value that starts with "-" for an option of its own
        raise TrainError(
            f"model {info.name} needs {info.frames} frames per sample but dataset {options.data} has "
            f"offsets {describe_offsets(offsets)}; build it with --history {info.frames} or --offsets=-9,-5,0"
        )
    crop = _crop(manifest)
    # Rows above the network's own (the sky above DeepestLSTMTinyPilotNet's lower half) are an error; a narrower crop
    # (the lower half for a whole-frame network, as the paper's recipe trains memDCCP) is a choice, said in a note.
    if crop[0] < info.crop_top_fraction and not options.any_crop:
        raise TrainError(
            f"model {info.name} takes rows {info.crop_top_fraction:g}..1 of the camera frame but dataset "
            f"{options.data} holds rows {crop[0]:g}..{crop[1]:g}; build it with --crop {info.crop_top_fraction:g}:1 "
            f"(or train on the dataset's rows with --any-crop)"
        )


def dataset_circuits(manifest: dict[str, Any]) -> list[str]:
    """Every circuit a dataset's episodes drove (train and validation alike), sorted."""
    return sorted({episode["circuit"] for source in manifest["sources"] for episode in source["episodes"]})


def _crop(manifest: dict[str, Any]) -> tuple[float, float]:
    return float(manifest["options"]["crop_top_fraction"]), float(manifest["options"]["crop_bottom_fraction"])


def crop_notes(info: ModelInfo, manifest: dict[str, Any]) -> list[str]:
    """A crop other than the reference model's, allowed with ``any_crop`` (the checkpoint records the dataset's crop,
    and serving applies that one), is worth saying."""
    crop = _crop(manifest)
    if crop == (info.crop_top_fraction, 1.0):
        return []
    return [
        f"dataset rows {crop[0]:g}..{crop[1]:g} of the camera frame differ from the reference {info.name}'s "
        f"{info.crop_top_fraction:g}..1; the checkpoint records the dataset's crop"
    ]


def input_section(manifest: dict[str, Any], offsets_frames: tuple[int, ...]) -> dict[str, Any]:
    step_s = manifest["step_s"]
    crop = manifest["options"]
    return {
        "width_px": manifest["image_width_px"],
        "height_px": manifest["image_height_px"],
        "crop_top_fraction": float(crop["crop_top_fraction"]),
        "crop_bottom_fraction": float(crop["crop_bottom_fraction"]),
        "offsets_frames": list(offsets_frames),
        "offsets_s": None if step_s is None else [round(o * step_s, 9) for o in offsets_frames],
        "step_s": step_s,
    }


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


# -- evaluation ------------------------------------------------------------------------------------------------------


@torch.no_grad()
def evaluate(model: nn.Module, split: Split, positions: np.ndarray, norm: LabelNorm) -> dict[str, float]:
    """The paper's internal metrics on ``positions`` of ``split``, without augmentation, in eval mode.

    mae_speed_mps, mae_yaw_rate_radps: mean |error| in physical units; mse_normalised: MSE of normalised outputs
    (in the checkpoint's own label normalisation); mae_paper / mse_paper: MAE and MSE of both outputs in the paper's
    fixed normalisation (v / 17.5, w / 14.2), the figures of its Table 1, whatever normalisation trained the model.
    """
    was_training = model.training
    model.eval()
    abs_sum = torch.zeros(2, dtype=torch.float64)
    phys_sq_sum = torch.zeros(2, dtype=torch.float64)
    sq_sum = 0.0
    for start in range(0, len(positions), EVAL_BATCH):
        x, y_n = split.batch(positions[start : start + EVAL_BATCH], norm)
        out = model(x)
        sq_sum += float(((out - y_n) ** 2).sum(dtype=torch.float64))
        error = norm.denormalise(out) - norm.denormalise(y_n)
        abs_sum += error.abs().sum(0, dtype=torch.float64).cpu()
        phys_sq_sum += (error.double() ** 2).sum(0).cpu()
    model.train(was_training)
    n = max(len(positions), 1)
    paper_scale = torch.tensor([V_SCALE, W_SCALE], dtype=torch.float64)
    return {
        "mae_speed_mps": float(abs_sum[0]) / n,
        "mae_yaw_rate_radps": float(abs_sum[1]) / n,
        "mse_normalised": sq_sum / (2 * n),
        "mae_paper": float((abs_sum / paper_scale).sum()) / (2 * n),
        "mse_paper": float((phys_sq_sum / paper_scale**2).sum()) / (2 * n),
    }
