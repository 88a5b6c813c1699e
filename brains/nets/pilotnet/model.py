"""PilotNet as in DeepLearningStudio's Keras model (the paper's baseline), 17,016,206 Keras parameters."""

from __future__ import annotations

import torch
from torch import nn

from brains.nets.layers import (
    BN_EPS,
    BN_MOMENTUM,
    KerasSameConv2d,
    dense_head,
    keras_init_,
    pilotnet_convs,
    pilotnet_feature_map,
)


class PilotNet(nn.Module):
    """Single frame 66x200 -> normalised (v_n, w_n).

    BN on the input, five ReLU convs with Keras "same" padding (66x200 -> 33x100 -> 17x50 -> 9x25 -> 9x25 -> 9x25),
    Flatten (64·9·25 = 14,400) and Dense 1164/100/50/10/2. The 14,400 x 1164 Dense holds 98.5 % of the weights.
    Flatten order is channels-first, so Keras Dense weights would need a row permutation to be ported.
    """

    def __init__(self, input_height_px: int = 66, input_width_px: int = 200):
        super().__init__()
        self.input_norm = nn.BatchNorm2d(3, eps=BN_EPS, momentum=BN_MOMENTUM)
        self.features = pilotnet_convs(KerasSameConv2d)
        h, w = pilotnet_feature_map(input_height_px, input_width_px)
        self.head = dense_head(64 * h * w, [1164, 100, 50, 10, 2])
        keras_init_(self)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x: (B, 3, H, W) float32, ImageNet-normalised RGB -> (B, 2) = (v_n, w_n), linear."""
        return self.head(torch.flatten(self.features(self.input_norm(x)), 1))
