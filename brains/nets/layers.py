"""Building blocks that reproduce Keras (TF 2.9) semantics in PyTorch.

* ``KerasSameConv2d`` / ``KerasSameConv3d``: Keras ``padding="same"``, which with stride 2 puts the odd extra
  row/column at the bottom/right. PyTorch's ``padding="same"`` refuses stride > 1 and symmetric integer padding
  gives other sizes (or shifts the sampling grid), so we pad explicitly with ``F.pad`` (stride 1 with an odd
  kernel is symmetric and left to the conv).
* ``ConvLSTM2d``: Keras ``ConvLSTM2D``.
* ``KerasLSTM``: Keras ``LSTM`` with its single bias vector (``nn.LSTM`` has two, +4·units parameters per layer).
* ``keras_param_count``: parameters as Keras counts them (BatchNorm moving mean/variance included).
* ``keras_init_``: Keras default initialisers (Glorot-uniform kernels, zero biases).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import nn

BN_EPS = 1e-3  # Keras BatchNormalization default
BN_MOMENTUM = 0.01  # Keras momentum 0.99 (weight of the old value) = PyTorch 0.01 (weight of the new value)


def keras_same_padding(size: int, kernel: int, stride: int) -> tuple[int, int]:
    """(before, after) padding of one spatial dim under Keras/TF "same": output size is ceil(size / stride)."""
    out = math.ceil(size / stride)
    total = max((out - 1) * stride + kernel - size, 0)
    return total // 2, total - total // 2


def keras_same_pad(x: torch.Tensor, kernel: Sequence[int], stride: Sequence[int]) -> torch.Tensor:
    """Zero-pad the trailing ``len(kernel)`` dims of ``x`` the way Keras "same" would before a convolution."""
    pads: list[int] = []
    # F.pad takes pairs starting from the last dim.
    for size, k, s in zip(reversed(x.shape[-len(kernel) :]), reversed(kernel), reversed(stride)):
        pads.extend(keras_same_padding(int(size), k, s))
    return F.pad(x, pads) if any(pads) else x


def _conv_padding(kernel_size: int, stride: int) -> int | None:
    """The padding a Keras "same" conv leaves to the conv itself, or None when ``forward`` pads first. Stride 1 with
    an odd kernel pads k // 2 on both sides: the conv does it (no extra F.pad op)."""
    return kernel_size // 2 if stride == 1 and kernel_size % 2 == 1 else None


class _KerasSameForward(nn.Module):
    """Keras "same" padding in ``forward`` for the ``nn.ConvNd`` that comes after this class in a subclass's bases
    (each subclass's ``__init__`` builds its conv: ``super().__init__`` in a mixin would be object's to mypy)."""

    kernel_size: tuple[int, ...]
    stride: tuple[int, ...]
    _symmetric: bool  # the conv pads itself (see _conv_padding)

    def forward(self, input: torch.Tensor) -> torch.Tensor:
        return super().forward(input if self._symmetric else keras_same_pad(input, self.kernel_size, self.stride))


class KerasSameConv2d(_KerasSameForward, nn.Conv2d):
    """``nn.Conv2d`` with Keras "same" padding; input (B, C, H, W) -> (B, F, ceil(H/s), ceil(W/s))."""

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int, stride: int = 1, bias: bool = True):
        padding = _conv_padding(kernel_size, stride)
        super().__init__(in_channels, out_channels, kernel_size, stride=stride, padding=padding or 0, bias=bias)
        self._symmetric = padding is not None


class KerasSameConv3d(_KerasSameForward, nn.Conv3d):
    """``nn.Conv3d`` with Keras "same" padding; input (B, C, T, H, W) -> (B, F, ceil(T/s), ceil(H/s), ceil(W/s))."""

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int, stride: int = 1, bias: bool = True):
        padding = _conv_padding(kernel_size, stride)
        super().__init__(in_channels, out_channels, kernel_size, stride=stride, padding=padding or 0, bias=bias)
        self._symmetric = padding is not None


def keras_hard_sigmoid(x: torch.Tensor) -> torch.Tensor:
    """Keras 2.x (TF 2.9) ``hard_sigmoid``: clip(0.2·x + 0.5, 0, 1).

    Not ``F.hardsigmoid`` (relu6(x + 3)/6, slope 1/6), which is what Keras 3 switched to; the paper used TF 2.9.
    """
    return torch.clamp(0.2 * x + 0.5, 0.0, 1.0)


class ConvLSTM2d(nn.Module):
    """Keras ``ConvLSTM2D`` (stride 1, "same" padding, tanh activation, hard_sigmoid recurrent activation).

    Input (B, T, C_in, H, W); output (B, T, F, H, W) if ``return_sequences`` else the last step (B, F, H, W).
    Gate order along the 4·F channels is i, f, c, o as in Keras, so Keras kernels can be copied slice for slice.
    The input kernel has the bias, the recurrent kernel has none: 4·(k²·(C_in + F)·F + F) parameters.
    State starts at zero for every call (nothing is stateful in the reference models).
    """

    def __init__(self, in_channels: int, filters: int, kernel_size: int, return_sequences: bool = False):
        super().__init__()
        self.filters = filters
        self.return_sequences = return_sequences
        self.input_conv = KerasSameConv2d(in_channels, 4 * filters, kernel_size, bias=True)
        # In the paper's models T == 1 and the state is zero, so this kernel only ever multiplies zeros (forward
        # skips it on the first step; exact). It stays a real parameter so counts match Keras and T > 1 works.
        self.recurrent_conv = KerasSameConv2d(filters, 4 * filters, kernel_size, bias=False)
        self.reset_parameters()

    def reset_parameters(self) -> None:
        """Keras defaults: Glorot-uniform kernel, orthogonal recurrent kernel, zero bias with forget gate at 1."""
        nn.init.xavier_uniform_(self.input_conv.weight)
        nn.init.orthogonal_(self.recurrent_conv.weight)
        bias = self.input_conv.bias
        assert bias is not None  # built with bias=True
        with torch.no_grad():
            bias.zero_()
            bias[self.filters : 2 * self.filters] = 1.0  # unit_forget_bias=True

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, t, c, h, w = x.shape
        z_in = self.input_conv(x.reshape(b * t, c, h, w)).reshape(b, t, 4 * self.filters, h, w)
        hidden = cell = None
        outputs = []
        for step in range(t):
            z = z_in[:, step]
            if hidden is not None:  # with zero state the recurrent term is exactly zero: skip it
                z = z + self.recurrent_conv(hidden)
            i, f, g, o = z.chunk(4, dim=1)
            cell_in = keras_hard_sigmoid(i) * torch.tanh(g)
            cell = cell_in if cell is None else keras_hard_sigmoid(f) * cell + cell_in
            hidden = keras_hard_sigmoid(o) * torch.tanh(cell)
            outputs.append(hidden)
        if hidden is None:
            raise ValueError(f"ConvLSTM2d needs at least one time step, got input of shape {tuple(x.shape)}")
        return torch.stack(outputs, dim=1) if self.return_sequences else hidden


class KerasLSTM(nn.Module):
    """One Keras ``LSTM`` layer (TF 2 defaults: tanh, sigmoid recurrent activation, one bias, gates i, f, c, o).

    Input (B, T, C); output (B, T, units) if ``return_sequences`` else (B, units).
    Parameters: 4·((C + units)·units + units).
    """

    def __init__(self, input_size: int, units: int, return_sequences: bool = False):
        super().__init__()
        self.units = units
        self.return_sequences = return_sequences
        self.weight_ih = nn.Parameter(torch.empty(4 * units, input_size))
        self.weight_hh = nn.Parameter(torch.empty(4 * units, units))
        self.bias = nn.Parameter(torch.empty(4 * units))
        self.reset_parameters()

    def reset_parameters(self) -> None:
        """Glorot-uniform input kernel, orthogonal recurrent kernel, zero bias with forget gate at 1.

        PyTorch's default U(±1/√units) would be ±0.5 for 4 units on 5,824 inputs and saturate the gates.
        """
        nn.init.xavier_uniform_(self.weight_ih)
        nn.init.orthogonal_(self.weight_hh)
        with torch.no_grad():
            self.bias.zero_()
            self.bias[self.units : 2 * self.units] = 1.0

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        z_in = F.linear(x, self.weight_ih, self.bias)  # (B, T, 4·units), all steps at once
        hidden = cell = None
        outputs = []
        for step in range(x.shape[1]):
            z = z_in[:, step] if hidden is None else z_in[:, step] + F.linear(hidden, self.weight_hh)
            i, f, g, o = z.chunk(4, dim=1)
            cell_in = torch.sigmoid(i) * torch.tanh(g)
            cell = cell_in if cell is None else torch.sigmoid(f) * cell + cell_in
            hidden = torch.sigmoid(o) * torch.tanh(cell)
            outputs.append(hidden)
        if hidden is None:
            raise ValueError(f"KerasLSTM needs at least one time step, got input of shape {tuple(x.shape)}")
        return torch.stack(outputs, dim=1) if self.return_sequences else hidden


def pilotnet_convs(conv: type[nn.Module]) -> nn.Sequential:
    """PilotNet's five convolutions (24/36/48 5x5 stride 2, then 64/64 3x3), each with ReLU, all Keras "same".

    ``conv`` is :class:`KerasSameConv2d` (PilotNet, PilotNet x3 per frame) or :class:`KerasSameConv3d` (memDCCP,
    whose 5x5x5 and 3x3x3 kernels and strides apply along time too).
    """
    layers: list[nn.Module] = []
    for channels_in, channels_out, kernel, stride in (
        (3, 24, 5, 2),
        (24, 36, 5, 2),
        (36, 48, 5, 2),
        (48, 64, 3, 1),
        (64, 64, 3, 1),
    ):
        layers += [conv(channels_in, channels_out, kernel, stride=stride), nn.ReLU()]
    return nn.Sequential(*layers)


def pilotnet_feature_map(height_px: int, width_px: int) -> tuple[int, int]:
    """(height, width) after :func:`pilotnet_convs`: three stride-2 "same" convs, ceil(n / 2) each."""
    for _ in range(3):
        height_px, width_px = -(-height_px // 2), -(-width_px // 2)
    return height_px, width_px


def dense_head(in_features: int, widths: Sequence[int]) -> nn.Sequential:
    """Dense layers of ``widths`` with ReLU between them and a linear last layer (the (v_n, w_n) output)."""
    layers: list[nn.Module] = []
    for i, width in enumerate(widths):
        layers.append(nn.Linear(in_features, width))
        if i < len(widths) - 1:
            layers.append(nn.ReLU())
        in_features = width
    return nn.Sequential(*layers)


def keras_init_(model: nn.Module) -> None:
    """Keras default initialisers: Glorot-uniform weights and zero biases for Conv/Dense layers, then the
    recurrent layers' own Keras defaults (orthogonal recurrent kernels, forget bias 1)."""
    for m in model.modules():
        if isinstance(m, (nn.Conv2d, nn.Conv3d, nn.Linear)):
            nn.init.xavier_uniform_(m.weight)
            if m.bias is not None:
                nn.init.zeros_(m.bias)
    for m in model.modules():
        if isinstance(m, (ConvLSTM2d, KerasLSTM)):
            m.reset_parameters()


def keras_param_count(model: nn.Module) -> int:
    """Parameters as Keras reports them: all ``nn.Parameter``s plus BatchNorm moving mean and variance.

    PyTorch keeps the moving statistics as buffers, so ``sum(p.numel() for p in model.parameters())`` is
    2·C smaller per BatchNorm than the Keras figure.
    """
    n = sum(p.numel() for p in model.parameters())
    for m in model.modules():
        # Without track_running_stats the statistics are None: Keras would have none to count either.
        if isinstance(m, nn.modules.batchnorm._BatchNorm) and m.running_mean is not None and m.running_var is not None:
            n += m.running_mean.numel() + m.running_var.numel()
    return n
