"""The paper's four networks ("Memory based neural networks for end-to-end autonomous driving"), one folder each.

This module is torch-free: ``MODELS`` describes every network (input size, frames, crop, reference parameter
count) so that recorders and brains can prepare inputs without loading torch. ``make_model`` imports the model
module, and with it torch, only when called.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class ModelInfo:
    """What a network expects at its input, and its Keras parameter count (trainable + BN moving statistics)."""

    name: str
    input_height_px: int
    input_width_px: int
    frames: int  # 1: input (B, 3, H, W); 3: input (B, 3, 3, H, W), frames t-9, t-5, t (oldest first)
    crop_top_fraction: float  # fraction of rows dropped at the top of the camera frame before resizing
    module: str  # "package.module:ClassName"
    reference_params: int


MODELS: dict[str, ModelInfo] = {
    info.name: info
    for info in (
        ModelInfo("pilotnet", 66, 200, 1, 0.0, "brains.nets.pilotnet.model:PilotNet", 17_016_206),
        # The only one trained on the lower half of the 480-row frame (rows 240:480).
        ModelInfo("deepest_lstm_tiny_pilotnet", 50, 100, 1, 0.5,
                  "brains.nets.deepest_lstm_tiny_pilotnet.model:DeepestLSTMTinyPilotNet", 62_470),
        ModelInfo("pilotnet_x3", 50, 100, 3, 0.0, "brains.nets.pilotnet_x3.model:PilotNetX3", 352_958),
        ModelInfo("memdccp", 50, 100, 3, 0.0, "brains.nets.memdccp.model:MemDCCP", 910_694),
        # Ours, not the paper's: the tiny network's layers with ConvLSTMs that recur over the three frames.
        ModelInfo("recurrent_tiny_pilotnet", 50, 100, 3, 0.0,
                  "brains.nets.recurrent_tiny_pilotnet.model:RecurrentTinyPilotNet", 62_470),
    )
}


def make_model(name: str, **hyper: Any):
    """A freshly initialised ``torch.nn.Module`` for network ``name``; ``hyper`` goes to its constructor."""
    try:
        info = MODELS[name]
    except KeyError:
        raise ValueError(f"unknown network {name!r} (known: {', '.join(sorted(MODELS))})") from None
    module_name, class_name = info.module.split(":")
    return getattr(importlib.import_module(module_name), class_name)(**hyper)


__all__ = ["MODELS", "ModelInfo", "make_model"]
