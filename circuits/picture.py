"""A top-down picture of a circuit: grass, the road band at its true width, the centre line, the start and the
driving direction, and the circuit's name and length.

World x to the right, world y up (so a clockwise circuit looks clockwise). Images are RGB uint8;
:func:`save_circuit_picture` writes a PNG with OpenCV.
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np

from circuits.library import Circuit

GRASS_RGB = (96, 140, 84)
ROAD_RGB = (90, 90, 90)
EDGE_RGB = (200, 200, 200)
LINE_RGB = (230, 30, 30)
START_RGB = (255, 255, 255)
TEXT_RGB = (255, 255, 255)
MARGIN_PX = 20
TEXT_BAND_PX = 34
MAX_ASPECT = 1.5  # height / width at most (plus the text band)
_SHIFT = 4  # OpenCV sub-pixel bits for smooth polylines
_FONT = cv2.FONT_HERSHEY_SIMPLEX


def circuit_picture(circuit: Circuit, *, width_px: int = 800) -> np.ndarray:
    """The circuit seen from above, ``width_px`` wide (the height follows the circuit's aspect, up to 1.5 times the
    width plus a text band), RGB uint8.

    The road is drawn at its true width but at least 2 px; its edges are thin light lines (the walls), the centre
    line is red (left out where the road is under 3 px wide), a white disc marks the start and a white arrow from it
    shows the driving direction.
    """
    if width_px < 2 * MARGIN_PX + 40:
        raise ValueError(f"width_px must be at least {2 * MARGIN_PX + 40}, got {width_px}")
    points = circuit.centreline.points_m
    low, high = points.min(axis=0), points.max(axis=0)
    pad = circuit.road_half_width_m
    low, high = low - pad, high + pad
    extent = np.maximum(high - low, 1e-6)
    # px per metre: the full width, unless the circuit is so tall that the picture would exceed MAX_ASPECT.
    scale = min((width_px - 2 * MARGIN_PX) / extent[0], (MAX_ASPECT * width_px - 2 * MARGIN_PX) / extent[1])
    left_px = MARGIN_PX + ((width_px - 2 * MARGIN_PX) - extent[0] * scale) / 2  # centred when narrower
    height_px = int(math.ceil(extent[1] * scale)) + 2 * MARGIN_PX + TEXT_BAND_PX
    image = np.empty((height_px, width_px, 3), dtype=np.uint8)
    image[:] = GRASS_RGB

    def to_px(xy: np.ndarray) -> np.ndarray:
        xy = np.atleast_2d(xy)
        u = left_px + (xy[:, 0] - low[0]) * scale
        v = TEXT_BAND_PX + MARGIN_PX + (high[1] - xy[:, 1]) * scale
        return np.round(np.column_stack([u, v]) * (1 << _SHIFT)).astype(np.int32)

    road_px = max(2, int(round(2 * circuit.road_half_width_m * scale)))
    centre = to_px(points)
    if road_px > 2:  # a 1 px light border on each side: the walls
        cv2.polylines(image, [centre], True, EDGE_RGB, road_px + 2, cv2.LINE_AA, _SHIFT)
    cv2.polylines(image, [centre], True, ROAD_RGB, road_px, cv2.LINE_AA, _SHIFT)
    if road_px >= 3:  # on a thinner road the line would hide it
        line_px = max(1, int(round(circuit.line_width_m * scale)))
        cv2.polylines(image, [centre], True, LINE_RGB, line_px, cv2.LINE_AA, _SHIFT)

    # Start: a disc on the centre line, and an arrow along the driving direction.
    x, y, yaw = circuit.start_pose()
    arrow_m = max(30.0 / scale, min(0.06 * float(extent.max()), 80.0))  # at least 30 px long
    start = to_px(np.array([x, y]))[0]
    tip = to_px(np.array([x + arrow_m * math.cos(yaw), y + arrow_m * math.sin(yaw)]))[0]
    radius = max(3, road_px // 2 + 2)
    cv2.circle(image, tuple(int(c) for c in start), radius << _SHIFT, START_RGB, -1, cv2.LINE_AA, _SHIFT)
    cv2.arrowedLine(
        image, tuple(int(c) for c in start), tuple(int(c) for c in tip), START_RGB, 2, cv2.LINE_AA, _SHIFT, 0.35
    )

    width_m = 2 * circuit.road_half_width_m
    text = (
        f"{circuit.name}  {circuit.length_m:.1f} m  ({extent[0] - 2 * pad:.0f} x {extent[1] - 2 * pad:.0f} m, "
        f"road {width_m:g} m)"
    )
    text = text.encode("ascii", "replace").decode("ascii")
    font_scale = 0.6
    (text_w, _), _ = cv2.getTextSize(text, _FONT, font_scale, 1)
    if text_w > width_px - 2 * MARGIN_PX:
        font_scale *= (width_px - 2 * MARGIN_PX) / text_w
    cv2.putText(image, text, (MARGIN_PX, TEXT_BAND_PX - 10), _FONT, font_scale, TEXT_RGB, 1, cv2.LINE_AA)
    return image


def save_circuit_picture(circuit: Circuit, path: str | Path, *, width_px: int = 800) -> Path:
    """Write :func:`circuit_picture` to ``path`` as a PNG; returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    image = circuit_picture(circuit, width_px=width_px)
    if not cv2.imwrite(str(path), cv2.cvtColor(image, cv2.COLOR_RGB2BGR)):
        raise OSError(f"could not write a PNG to {path}")
    return path
