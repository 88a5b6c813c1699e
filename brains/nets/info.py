"""What a network expects at its input (torch-free), declared by each network's own folder as ``INFO``."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True, kw_only=True)
class ModelInfo:
    """What a network expects at its input, and its Keras parameter count (trainable + BN moving statistics)."""

    name: str
    input_height_px: int
    input_width_px: int
    frames: int  # 1: input (B, 3, H, W); 3: input (B, 3, 3, H, W), frames t-9, t-5, t (oldest first)
    crop_top_fraction: float  # fraction of rows dropped at the top of the camera frame before resizing
    module: str  # "package.module:ClassName"
    reference_params: int
