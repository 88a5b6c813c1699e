"""Training labels: how (speed, yaw rate) are normalised for a network (saved in its checkpoint), and how samples
are weighted so that the rare sharp turns are drawn as often as the straights."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from brains.nets.preprocess import IMAGENET_MEAN, IMAGENET_STD, V_OFFSET, V_SCALE, W_OFFSET, W_SCALE
from recorder.dataset.build import ABS_YAW_RATE_EDGES_RADPS

# A bin's sampling weight is at most this many times that of the most common bin: a lone sample in an otherwise
# empty bin would otherwise be drawn as often as a whole common bin. DLS added up to 50 copies of rare samples.
BALANCE_CAP = 50.0


@dataclass(frozen=True)
class LabelNorm:
    """y_n = (y - mean) / std per label, y = [v m/s, w rad/s]; the network predicts y_n."""

    kind: str
    mean: tuple[float, float]
    std: tuple[float, float]

    def normalise(self, y: torch.Tensor) -> torch.Tensor:
        return (y - y.new_tensor(self.mean)) / y.new_tensor(self.std)

    def denormalise(self, y_n: torch.Tensor) -> torch.Tensor:
        return y_n * y_n.new_tensor(self.std) + y_n.new_tensor(self.mean)

    def to_dict(self) -> dict[str, Any]:
        return {
            "image_mean": [float(v) for v in IMAGENET_MEAN],
            "image_std": [float(v) for v in IMAGENET_STD],
            "labels": self.kind,
            "label_mean": list(self.mean),
            "label_std": list(self.std),
        }


def label_norm(kind: str, train_labels: np.ndarray, *, mirrored: bool = False) -> LabelNorm:
    """ "zscore": mean/std of the training labels (N, 2); "paper": DLS's v_n = (v-6.5)/17.5, w_n = (w+7.1)/14.2.

    mirrored: training mirrors half the samples (w -> -w), so the yaw rates the network learns are the symmetric
    mixture of w and -w: its mean is 0 and its std sqrt(mean(w²)). The paper's labels are not clipped to [0, 1]
    here, so de-normalisation stays the exact inverse.
    """
    if kind == "paper":
        return LabelNorm("paper", (V_OFFSET, W_OFFSET), (V_SCALE, W_SCALE))
    values = train_labels.astype(np.float64)
    if mirrored:
        values = np.concatenate([values, values * np.array([1.0, -1.0])])
    std = values.std(axis=0)
    std = np.where(std > 1e-6, std, 1.0)  # a constant label (e.g. a fixed speed) would divide by zero
    mean = values.mean(axis=0)
    return LabelNorm("zscore", (float(mean[0]), float(mean[1])), (float(std[0]), float(std[1])))


def balance_weights(
    yaw_rate_radps: np.ndarray, edges_radps=ABS_YAW_RATE_EDGES_RADPS, cap: float = BALANCE_CAP
) -> np.ndarray:
    """Sampling weights (N,) float64 summing to 1: ∝ 1 / (training samples in the sample's |w| bin).

    Bins as in the manifest histogram: edges[i] <= |w| < edges[i + 1], the last open-ended. Every occupied bin is
    then drawn about equally often, except that no weight exceeds ``cap`` times the most common bin's.
    """
    edges = np.asarray(edges_radps, dtype=np.float64)
    bins = np.searchsorted(edges, np.abs(np.asarray(yaw_rate_radps, dtype=np.float64)), side="right") - 1
    counts = np.bincount(bins, minlength=len(edges)).astype(np.float64)
    weights = np.minimum(1.0 / counts[bins], cap / counts.max())
    return weights / weights.sum()
