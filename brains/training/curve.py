"""The training curve as a PNG, drawn with OpenCV (matplotlib is not a dependency of training)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import cv2
import numpy as np

_COLOURS = {
    "train_loss": (200, 120, 0),
    "train_eval_loss": (0, 160, 0),
    "val_loss": (0, 0, 220),
    "val_mae_speed_mps": (160, 0, 160),
    "val_mae_yaw_rate_radps": (0, 140, 220),
}


def plot_curve(curve: list[dict[str, Any]], path: Path) -> bool:
    """PNG of the curve drawn with OpenCV (matplotlib is not a dependency): losses on a log scale (left) and
    validation MAE (right), one point per epoch."""
    image = np.full((420, 960, 3), 255, np.uint8)
    _panel(image, (0, 0, 480, 420), curve, ("train_loss", "train_eval_loss", "val_loss"), "loss (log10)", log=True)
    _panel(
        image,
        (480, 0, 480, 420),
        curve,
        ("val_mae_speed_mps", "val_mae_yaw_rate_radps"),
        "val MAE (log10; v m/s, w rad/s)",
        log=True,
        empty="no validation split",
    )
    return bool(cv2.imwrite(str(path), image))  # False: it could not be written


def _panel(
    image: np.ndarray,
    box: tuple[int, int, int, int],
    curve: list[dict[str, Any]],
    keys: tuple[str, ...],
    title: str,
    *,
    log: bool,
    empty: str = "no data",
) -> None:
    x0, y0, width, height = box
    left, top, right, bottom = x0 + 60, y0 + 30, x0 + width - 15, y0 + height - 45
    cv2.rectangle(image, (left, top), (right, bottom), (0, 0, 0), 1)
    cv2.putText(image, title, (left, top - 10), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    series = {
        k: [(e["epoch"], e[k]) for e in curve if e.get(k) is not None and e[k] > (0 if log else -math.inf)]
        for k in keys
    }
    values = [math.log10(v) if log else v for points in series.values() for _, v in points]
    if not values:
        cv2.putText(
            image, empty, (left + 20, (top + bottom) // 2), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (90, 90, 90), 1, cv2.LINE_AA
        )
        return
    low, high = min(values), max(values)
    high = high if high > low else low + 1.0
    epochs = [e["epoch"] for e in curve]
    first, last = min(epochs), max(max(epochs), min(epochs) + 1)

    def to_px(epoch: float, v: float) -> tuple[int, int]:
        return (
            int(left + (epoch - first) / (last - first) * (right - left)),
            int(bottom - ((math.log10(v) if log else v) - low) / (high - low) * (bottom - top)),
        )

    for row, key in enumerate(k for k in keys if series[k]):
        points = np.array([to_px(e, v) for e, v in series[key]], np.int32)
        cv2.polylines(image, [points], False, _COLOURS[key], 2, cv2.LINE_AA)
        for point in points if len(points) < 12 else ():  # a lone epoch is a point, not a line
            cv2.circle(image, tuple(int(v) for v in point), 3, _COLOURS[key], -1, cv2.LINE_AA)
        cv2.putText(
            image, key, (left + 8, top + 18 + 16 * row), cv2.FONT_HERSHEY_SIMPLEX, 0.42, _COLOURS[key], 1, cv2.LINE_AA
        )
    label = (lambda v: f"{10**v:.3g}") if log else (lambda v: f"{v:.3g}")
    for text, y in ((label(high), top + 5), (label(low), bottom)):
        cv2.putText(image, text, (x0 + 4, y), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    for text, x in ((str(first), left), (str(last), right - 20)):
        cv2.putText(image, text, (x, bottom + 18), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(
        image,
        "epoch",
        ((left + right) // 2 - 20, bottom + 36),
        cv2.FONT_HERSHEY_SIMPLEX,
        0.45,
        (0, 0, 0),
        1,
        cv2.LINE_AA,
    )
