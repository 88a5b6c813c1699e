"""PilotNet x3 from DeepLearningStudio: per-frame PilotNet convs over 3 frames, then stacked LSTMs."""

from __future__ import annotations

import torch
from torch import nn

from brains.nets.layers import (
    BN_EPS,
    BN_MOMENTUM,
    KerasLSTM,
    KerasSameConv2d,
    dense_head,
    keras_init_,
    pilotnet_convs,
    pilotnet_feature_map,
)


class PilotNetX3(nn.Module):
    """Three frames (t-9, t-5, t) of 50x100 -> normalised (v_n, w_n); 352,958 Keras parameters with 4 LSTM units.

    BN on the input; PilotNet's five convs applied to each frame (TimeDistributed; 50x100 -> 7x13x64 = 5,824
    features per frame); four LSTMs of ``lstm_units`` (the first three return sequences, the last only its final
    step); Dense 1164/100/50/10/2.

    The LSTMs have Keras' single bias (``nn.LSTM`` has two and would count 353,022). The first LSTM alone is
    93,264 parameters and squeezes 5,824 features into 4 numbers, a tight bottleneck; it trains slowly.

    Parameter mystery: the paper reports 15.9 M parameters for this model, but the only public code (DLS) gives
    352,958, and no obvious variant reproduces 15.9 M (3 frames flattened into Dense 1164: 20.6 M; one 50x100
    frame: 7.0 M; 66x200 inputs: 0.49 M with LSTMs, 50.5 M flattened; the LSTM would need about 420 units).
    We build the code's version and expose the LSTM width as ``lstm_units``.
    """

    def __init__(self, lstm_units: int = 4, lstm_layers: int = 4, input_height_px: int = 50, input_width_px: int = 100):
        super().__init__()
        self.input_norm = nn.BatchNorm2d(3, eps=BN_EPS, momentum=BN_MOMENTUM)
        self.features = pilotnet_convs(KerasSameConv2d)  # applied to each frame (Keras TimeDistributed)
        h, w = pilotnet_feature_map(input_height_px, input_width_px)
        sizes = [64 * h * w] + [lstm_units] * lstm_layers
        self.memory = nn.Sequential(
            *(KerasLSTM(sizes[i], sizes[i + 1], return_sequences=i < lstm_layers - 1) for i in range(lstm_layers))
        )
        self.head = dense_head(lstm_units, [1164, 100, 50, 10, 2])
        keras_init_(self)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x: (B, T, 3, H, W) float32, ImageNet-normalised RGB, oldest frame first -> (B, 2) = (v_n, w_n), linear."""
        b, t = x.shape[:2]
        # BN over (B·T, 3, H, W) = Keras BN on the channels-last 5-D tensor (statistics over B, T, H, W).
        frames = self.features(self.input_norm(x.flatten(0, 1)))
        return self.head(self.memory(frames.reshape(b, t, -1)))
