"""Behavior Metrics' explicit brain (``brain_f1_opencv``): an OpenCV red-line detector with a two-mode PID.

Re-implemented from the description in ``reference/behavior-metrics.md`` section 6 (no code copied). Per frame:

1. Crop the image below ``crop_top_row`` (original: rows 230: of 480).
2. Gaussian blur (original 27 x 27).
3. RGB -> HSV; mask = S >= 110 and V >= 15 at any hue (picks the red line, not the grey road or walls).
4. ``alt`` = the topmost mask row of the crop (0 if the mask is empty). Sample rows alt, 124, 62 and 249 of the
   250-row crop; the line's x in a row is the midpoint of that row's leftmost and rightmost mask pixels (0 if the row
   is empty).
5. Curve detector: ``l = |(y1-y2)(x1-x3) - (y1-y3)(x1-x2)|`` over the points of rows alt, 124 and 62 (twice the
   area of their triangle: 0 when they are collinear, as a straight line on the ground is in the image).
   ``l > 500`` switches to curve mode; back to straight mode only after 25 consecutive frames with ``l <= 500``.
6. ``e = 320 - x_alt``; ``w = kp e + kd (e - e_prev)``.
   Straight mode: kp 0.001, kd 0.004; ``v = 4 v_mult`` where ``v_mult`` (from 2) drops by 0.4 when the red channel
   at the crop's top-centre pixel is < 170 and the previous v > 8, and rises by 0.3 otherwise, capped at 6 (v <= 24).
   Curve mode: kp 0.011, kd 0.011, v = 7.

This is the pre-June-2022 behaviour (the one that generated Behavior Metrics' datasets): the deceleration branch is
live. At HEAD the code overwrites v with a normalised value, which makes the deceleration dead code.

Adaptations (each constant is a keyword-only constructor option, defaults as listed):

* **Any camera size.** The original assumes 640 x 480. All image geometry is expressed in those *reference* units
  and scaled to the actual size: the crop start row and the sample rows scale with the image height
  (``row * H / 480``, and crop rows ``row * crop_height / 250``); the blur kernel scales per axis to the nearest odd
  size (27 x 27 at 640 x 480, 13 x 13 at 320 x 240, 9 x 3 at 200 x 66); the line's x and the sample rows are
  converted back to 640 x 480 pixel units before the curve area and the error are computed, so ``l > 500``,
  ``e = 320 - x`` and the PID gains keep their original meaning (an error of 320 = the line at the image edge).
  Scaling rows proportionally keeps the *image* layout; on a camera with a different aspect ratio (200 x 66 with the
  same 90 deg HFOV) the rows look at different ground distances, which is unavoidable.
* **The speed rule's probe pixel.** In Behavior Metrics' Gazebo worlds the crop's top-centre pixel (row 230,
  1.8 deg above the horizon with the original level camera at 0.10 m) shows the sky (R about 178) down a straight
  and the 0.5 m wall when a bend is less than about 13 m ahead. drivebench's scene reproduces that geometry
  (camera 0.10 m high, 0.5 m walls) and colours (sky R 180, walls R ~137-153, see ``services.simulator.scene``),
  so the rule is kept as is: ``speed_probe_threshold`` 170 on the red channel of the *unblurred* crop, pixel
  ``(0, width / 2)``.
* **What the sample rows see** (measured in drivebench's scene, level camera 0.10 m high, no adaptation needed):
  crop rows 249, 124 and 62 look at the ground only 0.13, 0.28 and 0.6 m ahead of the camera; only ``alt`` looks
  far (up to ~15 m down a straight). A straight line on the ground stays straight in the image, so ``l`` is ~0 on a
  straight whatever the offset, but any bend in view, or an offset beyond ~0.3 m (the near rows lose the line and
  read x = 0), switches to curve mode: about 95 % of a lap of ``simple`` runs in curve mode at 7 m/s, with
  straight-mode bursts to 24 m/s on the straights.
* **Lost line.** As in the original, an empty row counts as x = 0 (the line far left), so losing the line steers
  left in whatever mode the brain is in.

Everything the brain remembers (previous error, curve mode and its 25-frame counter, ``v_mult``, previous v) is
cleared by :meth:`ExplicitBrain.reset`.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from brains.base import Action, Observation

# The original brain's image size; every pixel constant below is in these units.
REFERENCE_WIDTH_PX = 640
REFERENCE_HEIGHT_PX = 480


def _nearest_odd(value: float) -> int:
    return max(1, 2 * round((value - 1.0) / 2.0) + 1)


@dataclass(frozen=True)
class LineObservation:
    """What the detector found in one frame, in 640 x 480 reference pixel units (rows within the crop).

    points: (x, row) for the sample rows alt, 124, 62, 249 (x = 0 where the row has no mask pixel).
    curve_area: l, twice the area of the triangle of the first three points.
    found: whether any mask pixel was found at all.
    """

    points: tuple[tuple[float, float], ...]
    curve_area: float
    found: bool


class ExplicitBrain:
    """Behavior Metrics' explicit red-line follower (see the module docstring for the algorithm and adaptations).

    All constants are in 640 x 480 reference pixels and m/s, rad/s.
    """

    def __init__(
        self,
        *,
        crop_top_row: float = 230.0,
        blur_kernel_px: float = 27.0,
        hsv_low: tuple[int, int, int] = (0, 110, 15),
        hsv_high: tuple[int, int, int] = (179, 255, 255),
        crop_rows: float = 250.0,
        sample_rows: tuple[float, float, float] = (124.0, 62.0, 249.0),
        image_centre_x: float = 320.0,
        curve_area_threshold: float = 500.0,
        straight_frames_to_leave_curve: int = 25,
        straight_kp: float = 0.001,
        straight_kd: float = 0.004,
        curve_kp: float = 0.011,
        curve_kd: float = 0.011,
        curve_speed_mps: float = 7.0,
        speed_per_multiplier_mps: float = 4.0,
        multiplier_start: float = 2.0,
        multiplier_max: float = 6.0,
        multiplier_up: float = 0.3,
        multiplier_down: float = 0.4,
        speed_probe_threshold: int = 170,
        min_speed_to_slow_mps: float = 8.0,
    ):
        self.crop_top_row = crop_top_row
        self.blur_kernel_px = blur_kernel_px
        self.hsv_low = np.array(hsv_low, dtype=np.uint8)
        self.hsv_high = np.array(hsv_high, dtype=np.uint8)
        self.crop_rows = crop_rows
        self.sample_rows = sample_rows
        self.image_centre_x = image_centre_x
        self.curve_area_threshold = curve_area_threshold
        self.straight_frames_to_leave_curve = straight_frames_to_leave_curve
        self.straight_kp, self.straight_kd = straight_kp, straight_kd
        self.curve_kp, self.curve_kd = curve_kp, curve_kd
        self.curve_speed_mps = curve_speed_mps
        self.speed_per_multiplier_mps = speed_per_multiplier_mps
        self.multiplier_start = multiplier_start
        self.multiplier_max = multiplier_max
        self.multiplier_up, self.multiplier_down = multiplier_up, multiplier_down
        self.speed_probe_threshold = speed_probe_threshold
        self.min_speed_to_slow_mps = min_speed_to_slow_mps
        self.reset(seed=0)

    # -- state ------------------------------------------------------------------------------------------------------

    def reset(self, *, seed: int) -> None:
        """Forget the previous episode: PID memory, curve mode and its counter, speed multiplier, last speed."""
        del seed  # deterministic
        self._previous_error = 0.0
        self._in_curve = False
        self._calm_frames = 0
        self._multiplier = self.multiplier_start
        self._previous_speed_mps = 0.0
        self.last_line: LineObservation | None = None

    @property
    def in_curve(self) -> bool:
        return self._in_curve

    # -- perception -------------------------------------------------------------------------------------------------

    def _crop_top(self, height_px: int) -> int:
        return min(height_px - 1, round(self.crop_top_row * height_px / REFERENCE_HEIGHT_PX))

    def detect(self, image_rgb: np.ndarray) -> LineObservation:
        """Find the line in an RGB image of any size; results in 640 x 480 reference units."""
        height, width = image_rgb.shape[:2]
        crop = image_rgb[self._crop_top(height) :]
        crop_height = crop.shape[0]
        kernel = (
            _nearest_odd(self.blur_kernel_px * width / REFERENCE_WIDTH_PX),
            _nearest_odd(self.blur_kernel_px * height / REFERENCE_HEIGHT_PX),
        )
        blurred = cv2.GaussianBlur(crop, kernel, 0)
        mask = cv2.inRange(cv2.cvtColor(blurred, cv2.COLOR_RGB2HSV), self.hsv_low, self.hsv_high) > 0

        rows_with_line = np.flatnonzero(mask.any(axis=1))
        found = rows_with_line.size > 0
        alt = int(rows_with_line[0]) if found else 0
        rows_per_reference = crop_height / self.crop_rows
        rows = [alt] + [min(crop_height - 1, round(row * rows_per_reference)) for row in self.sample_rows]
        x_scale = REFERENCE_WIDTH_PX / width
        points = []
        for row in rows:
            columns = np.flatnonzero(mask[row])
            if columns.size:
                # Pixel centres map onto pixel centres: column c of W covers reference columns around (c+0.5)*640/W.
                x = ((columns[0] + columns[-1]) / 2.0 + 0.5) * x_scale - 0.5
            else:
                x = 0.0
            points.append((x, row / rows_per_reference))
        (x1, y1), (x2, y2), (x3, y3) = points[:3]
        area = abs((y1 - y2) * (x1 - x3) - (y1 - y3) * (x1 - x2))
        return LineObservation(points=tuple(points), curve_area=area, found=found)

    # -- control ----------------------------------------------------------------------------------------------------

    def act(self, observation: Observation) -> Action:
        image = observation.image_rgb
        line = self.detect(image)
        self.last_line = line

        if line.curve_area > self.curve_area_threshold:
            self._in_curve = True
            self._calm_frames = 0
        elif self._in_curve:
            self._calm_frames += 1
            if self._calm_frames >= self.straight_frames_to_leave_curve:
                self._in_curve = False
                self._calm_frames = 0

        error = self.image_centre_x - line.points[0][0]
        derivative = error - self._previous_error
        self._previous_error = error

        if self._in_curve:
            yaw_rate = self.curve_kp * error + self.curve_kd * derivative
            speed = self.curve_speed_mps
        else:
            yaw_rate = self.straight_kp * error + self.straight_kd * derivative
            height, width = image.shape[:2]
            probe_red = int(image[self._crop_top(height), width // 2, 0])
            if probe_red < self.speed_probe_threshold and self._previous_speed_mps > self.min_speed_to_slow_mps:
                self._multiplier -= self.multiplier_down
            else:
                self._multiplier = min(self.multiplier_max, self._multiplier + self.multiplier_up)
            speed = self.speed_per_multiplier_mps * self._multiplier
        self._previous_speed_mps = speed
        return Action(speed_mps=float(speed), yaw_rate_radps=float(yaw_rate))
