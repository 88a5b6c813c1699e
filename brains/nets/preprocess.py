"""Input and label conventions of the paper's networks (numpy + OpenCV only; no torch).

Images: RGB, cropped (DeepestLSTMTinyPilotNet only: lower half), resized with INTER_AREA, scaled to [0, 1],
then ImageNet-normalised, channels first. Labels: v and w mapped to [0, 1] with DLS's fixed ranges.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import cv2
import numpy as np

if TYPE_CHECKING:
    from brains.nets import ModelInfo

IMAGENET_MEAN = np.array([0.485, 0.456, 0.406], dtype=np.float32)
IMAGENET_STD = np.array([0.229, 0.224, 0.225], dtype=np.float32)
MAX_PIXEL = 255.0

# v_n = (v - V_OFFSET) / V_SCALE, w_n = (w - W_OFFSET) / W_SCALE (DLS constants, in m/s and rad/s).
V_OFFSET, V_SCALE = 6.5, 17.5  # v in [6.5, 24] m/s maps to [0, 1]
W_OFFSET, W_SCALE = -7.1, 14.2  # w in [-7.1, 7.1] rad/s maps to [0, 1]


def normalise_labels(v, w) -> np.ndarray:
    """(v m/s, w rad/s), scalars or arrays of shape (N,) -> float32 (..., 2) of (v_n, w_n), clipped to [0, 1]."""
    v_n = (np.asarray(v, dtype=np.float32) - V_OFFSET) / V_SCALE
    w_n = (np.asarray(w, dtype=np.float32) - W_OFFSET) / W_SCALE
    return np.clip(np.stack([v_n, w_n], axis=-1), 0.0, 1.0).astype(np.float32)


def denormalise(out) -> tuple[np.ndarray, np.ndarray]:
    """Network output (..., 2) of (v_n, w_n) -> (v m/s, w rad/s); not clipped (the output layer is linear)."""
    out = np.asarray(out, dtype=np.float32)
    return V_OFFSET + V_SCALE * out[..., 0], W_OFFSET + W_SCALE * out[..., 1]


def _normalise_pixels(rgb_uint8: np.ndarray) -> np.ndarray:
    """(..., H, W, 3) uint8 -> (..., 3, H, W) float32 ImageNet-normalised."""
    x = (rgb_uint8.astype(np.float32) / MAX_PIXEL - IMAGENET_MEAN) / IMAGENET_STD
    return np.ascontiguousarray(np.moveaxis(x, -1, -3))


def crop_and_resize(rgb_uint8: np.ndarray, info: ModelInfo) -> np.ndarray:
    """Camera frame (H, W, 3) uint8 RGB -> (input_height_px, input_width_px, 3) uint8: top crop, INTER_AREA."""
    if rgb_uint8.ndim != 3 or rgb_uint8.shape[2] != 3:
        raise ValueError(f"expected an (H, W, 3) RGB frame, got shape {rgb_uint8.shape}")
    top = int(round(rgb_uint8.shape[0] * info.crop_top_fraction))
    cropped = rgb_uint8[top:]
    size = (info.input_width_px, info.input_height_px)  # cv2 wants (W, H)
    if cropped.shape[1::-1] == size:
        return np.ascontiguousarray(cropped)
    return cv2.resize(cropped, size, interpolation=cv2.INTER_AREA)


def prepare_frame(rgb_uint8: np.ndarray, info: ModelInfo) -> np.ndarray:
    """Camera frame (H, W, 3) uint8 RGB -> float32 (3, input_height_px, input_width_px), ready for the network.

    For 480-row frames and crop_top_fraction 0.5 the crop keeps rows 240:480, as DLS did.
    """
    return _normalise_pixels(crop_and_resize(rgb_uint8, info))


def prepare_batch(frames_uint8: np.ndarray, info: ModelInfo | None = None) -> np.ndarray:
    """Already cropped and resized frames (N, H, W, 3) uint8 RGB -> float32 (N, 3, H, W), ImageNet-normalised.

    Works for any leading dims, e.g. sequences (N, T, H, W, 3) -> (N, T, 3, H, W). With ``info`` the size is checked.
    """
    frames_uint8 = np.asarray(frames_uint8)
    if frames_uint8.dtype != np.uint8 or frames_uint8.ndim < 4 or frames_uint8.shape[-1] != 3:
        raise ValueError(f"expected uint8 (N, H, W, 3), got {frames_uint8.dtype} {frames_uint8.shape}")
    if info is not None and frames_uint8.shape[-3:-1] != (info.input_height_px, info.input_width_px):
        raise ValueError(
            f"{info.name} wants {info.input_height_px}x{info.input_width_px} frames, "
            f"got {frames_uint8.shape[-3]}x{frames_uint8.shape[-2]}"
        )
    return _normalise_pixels(frames_uint8)
