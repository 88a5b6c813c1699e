"""The training curve (brains/training/curve.py): a real PNG drawn with matplotlib, read back."""

from __future__ import annotations

import math

import cv2
import numpy as np

from brains.training.curve import plot_curve


def epochs(count: int, *, validation: bool = True) -> list[dict]:
    curve = []
    for epoch in range(1, count + 1):
        entry = {"epoch": epoch, "train_loss": 0.5 * math.exp(-epoch / 5) + 0.01, "val_loss": None}
        if validation:
            entry |= {"val_loss": 0.4 * math.exp(-epoch / 6) + 0.02, "val_mae_speed_mps": 0.6 / epoch}
        curve.append(entry)
    return curve


def test_the_curve_is_a_png_with_both_panels_drawn(tmp_path):
    path = tmp_path / "curve.png"
    assert plot_curve(epochs(30), path)
    image = cv2.imread(str(path))
    assert image is not None and image.shape[1] > 1000 and image.shape[0] > 400
    left, right = image[:, : image.shape[1] // 2], image[:, image.shape[1] // 2 :]
    for half in (left, right):  # each panel holds coloured lines, not only black axes on white
        saturation = cv2.cvtColor(half, cv2.COLOR_BGR2HSV)[..., 1]
        assert np.count_nonzero(saturation > 120) > 500


def test_a_curve_without_validation_says_so_and_one_epoch_is_a_point(tmp_path):
    assert plot_curve(epochs(1, validation=False), tmp_path / "one.png")
    assert cv2.imread(str(tmp_path / "one.png")) is not None


def test_an_unwritable_path_is_false_not_a_traceback(tmp_path):
    assert plot_curve(epochs(3), tmp_path / "missing-folder" / "curve.png") is False
