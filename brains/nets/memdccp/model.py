"""memDCCP (DeepestConvLSTMConv3DPilotnet, a.k.a. "frankenstein") from DeepLearningStudio: 910,694 parameters."""

from __future__ import annotations

import torch
from torch import nn

from brains.nets.layers import BN_EPS, BN_MOMENTUM, ConvLSTM2d, KerasSameConv3d, dense_head, keras_init_, pilotnet_convs


class MemDCCP(nn.Module):
    """Three frames (t-9, t-5, t) of 50x100 -> normalised (v_n, w_n).

    BN on the input; five ReLU Conv3Ds with Keras "same" padding: 24 5x5x5 s2 (T·H·W 3x50x100 -> 2x25x50),
    36 and 48 5x5x5 s2 (-> 1x13x25 -> 1x7x13), 64 3x3x3 s1 twice. Time is now collapsed to one step, so the
    four 8-filter 5x5 ConvLSTMs that follow run on a sequence of length one (gated convs; their recurrent
    kernels multiply zeros). Flatten and Dense 50/10/2.

    The reshape (faithful default): the reference does Keras ``Reshape((1, 13, 64, 7))`` on the channels-last
    (1, 7, 13, 64) tensor. That is a raw row-major reinterpretation, not a transpose: the ConvLSTMs then see a
    13x64 "image" with 7 "channels", i.e. scrambled spatial/channel axes. It is what was trained and reported
    (910,694 parameters; 13·64·8 = 6,656 features into Dense 50). ``clean=True`` instead runs the ConvLSTMs on
    the real 7x13 map with 64 channels (659,894 parameters).
    """

    def __init__(self, clean: bool = False):
        super().__init__()
        self.clean = clean
        self.input_norm = nn.BatchNorm3d(3, eps=BN_EPS, momentum=BN_MOMENTUM)
        self.features = pilotnet_convs(KerasSameConv3d)
        channels, map_hw = (64, (7, 13)) if clean else (7, (13, 64))
        self.memory = nn.Sequential(
            ConvLSTM2d(channels, 8, 5, return_sequences=True),
            ConvLSTM2d(8, 8, 5, return_sequences=True),
            ConvLSTM2d(8, 8, 5, return_sequences=True),
            ConvLSTM2d(8, 8, 5, return_sequences=False),
        )
        self.head = dense_head(8 * map_hw[0] * map_hw[1], [50, 10, 2])
        keras_init_(self)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x: (B, T=3, 3, 50, 100) float32, ImageNet-normalised RGB, oldest first -> (B, 2) = (v_n, w_n), linear."""
        feats = self.features(self.input_norm(x.transpose(1, 2)))  # Conv3d wants (B, C, T, H, W) -> (B, 64, 1, 7, 13)
        if self.clean:
            seq = feats.transpose(1, 2)  # (B, T=1, 64, 7, 13)
        else:
            seq = keras_raw_reshape(feats)  # (B, T=1, 7, 13, 64)
        return self.head(torch.flatten(self.memory(seq), 1))


def keras_raw_reshape(feats: torch.Tensor) -> torch.Tensor:
    """The reference's Keras ``Reshape((1, 13, 64, 7))``, on our channels-first (B, 64, 1, 7, 13) Conv3d output.

    Keras holds the tensor channels-last as (B, 1, 7, 13, 64) and reinterprets its row-major memory as
    (B, 1, 13, 64, 7): a 13x64 "image" with 7 "channels". We rebuild that layout, reshape it the same way, and move
    the 7 channels to where ``ConvLSTM2d`` wants them: (B, T=1, 7, 13, 64).
    """
    b, c, t, h, w = feats.shape
    keras_layout = feats.permute(0, 2, 3, 4, 1)  # (B, T, H, W, C); reshape copies it in this order
    return keras_layout.reshape(b, t, w, c, h).permute(0, 1, 4, 2, 3)  # (B, 1, 13, 64, 7) -> (B, 1, 7, 13, 64)
