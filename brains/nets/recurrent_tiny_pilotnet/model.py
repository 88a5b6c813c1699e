"""RecurrentTinyPilotNet: ours, not the paper's. DeepestLSTMTinyPilotNet whose ConvLSTMs recur over three frames.

Why it exists: the paper's "memory" networks never carry state from one frame to the next. DeepestLSTMTinyPilotNet
feeds its ConvLSTMs a sequence of length one, and memDCCP's Conv3Ds collapse its three frames to one step before
its ConvLSTMs, so their recurrent kernels only ever multiply zeros (brains/nets/layers.py). On the domain-randomised
data memDCCP and PilotNet x3 did not learn at all (brains/weights/README.md), while the tiny network learned from its
first epoch. This network keeps exactly the tiny network's layers, which learn there, and gives them real memory:
the same convs see each of the frames t-9, t-5 and t, and the three ConvLSTMs run over that three-step sequence,
so the recurrent kernels carry what the older frames showed into the answer for the newest one.
"""

from __future__ import annotations

import torch
from torch import nn

from brains.nets.deepest_lstm_tiny_pilotnet.model import tiny_conv_lstms, tiny_convs
from brains.nets.layers import dense_head, keras_init_


class RecurrentTinyPilotNet(nn.Module):
    """Three frames (t-9, t-5, t) of 50x100 -> normalised (v_n, w_n); 62,470 parameters, all of them used.

    Per frame, shared weights: three 3x3 stride-2 valid ReLU convs with 8 filters (50x100 -> 24x49 -> 11x24 ->
    5x11) and Dropout 0.2. Over time: three 8-filter 5x5 ConvLSTMs on the (B, T=3, 8, 5, 11) sequence, the first two
    returning every step, the last only the final one. Then Flatten (440) and Dense 50/10/2. No input BatchNorm:
    the networks that start with one learned far slower on the randomised data.
    """

    def __init__(self, dropout: float = 0.2, filters: int = 8):
        super().__init__()
        self.features = tiny_convs(filters, dropout)  # the tiny network's own layers, shared over the frames
        self.memory = tiny_conv_lstms(filters)  # now over a real three-step sequence
        self.head = dense_head(8 * 5 * 11, [50, 10, 2])
        keras_init_(self)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x: (B, T=3, 3, 50, 100) float32, ImageNet-normalised RGB, oldest first -> (B, 2) = (v_n, w_n), linear."""
        b, t, c, h, w = x.shape
        per_frame = self.features(x.reshape(b * t, c, h, w))  # the same convs on every frame
        seq = per_frame.reshape(b, t, *per_frame.shape[1:])  # (B, T, 8, 5, 11), oldest first
        return self.head(torch.flatten(self.memory(seq), 1))
