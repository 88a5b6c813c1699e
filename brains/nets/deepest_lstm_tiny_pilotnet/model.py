"""DeepestLSTMTinyPilotNet from DeepLearningStudio: 62,470 parameters, on the cropped lower half of the frame."""

from __future__ import annotations

import torch
from torch import nn

from brains.nets.layers import ConvLSTM2d, dense_head, keras_init_


class DeepestLSTMTinyPilotNet(nn.Module):
    """Single (cropped) frame 50x100 -> normalised (v_n, w_n).

    Three 3x3 stride-2 *valid* ReLU convs with 8 filters (50x100 -> 24x49 -> 11x24 -> 5x11), Dropout 0.2, then the
    feature map is reshaped into a sequence of length **one** and passed through three 8-filter 5x5 ConvLSTMs.
    With T = 1 and zero initial state each ConvLSTM is a gated conv, c = σ(i)·tanh(g), h = σ(o)·tanh(c); the
    recurrent kernels (31 % of the parameters) never see anything but zeros. That is the reference model; we keep
    it as is. Then Flatten (440) and Dense 50/10/2. No input BatchNorm in the reference.
    """

    def __init__(self, dropout: float = 0.2, filters: int = 8):
        super().__init__()
        self.features = tiny_convs(filters, dropout)
        self.memory = tiny_conv_lstms(filters)  # with T = 1 Keras' return_sequences True, True, False are equivalent
        self.head = dense_head(8 * 5 * 11, [50, 10, 2])
        keras_init_(self)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x: (B, 3, 50, 100) float32, ImageNet-normalised RGB of rows 240:480 -> (B, 2) = (v_n, w_n), linear."""
        seq = self.features(x).unsqueeze(1)  # (B, T=1, 8, 5, 11): Keras Reshape((1, 5, 11, 8))
        return self.head(torch.flatten(self.memory(seq), 1))


def tiny_convs(filters: int, dropout: float) -> nn.Sequential:
    """Three 3x3 stride-2 valid ReLU convs (50x100 -> 24x49 -> 11x24 -> 5x11) and Dropout."""
    return nn.Sequential(
        nn.Conv2d(3, filters, 3, stride=2),
        nn.ReLU(),
        nn.Conv2d(filters, filters, 3, stride=2),
        nn.ReLU(),
        nn.Conv2d(filters, filters, 3, stride=2),
        nn.ReLU(),
        nn.Dropout(dropout),
    )


def tiny_conv_lstms(filters: int) -> nn.Sequential:
    """Three 8-filter 5x5 ConvLSTMs; the first two return every step, the last only the final one (Keras'
    return_sequences True, True, False)."""
    return nn.Sequential(
        ConvLSTM2d(filters, 8, 5, return_sequences=True),
        ConvLSTM2d(8, 8, 5, return_sequences=True),
        ConvLSTM2d(8, 8, 5, return_sequences=False),
    )
