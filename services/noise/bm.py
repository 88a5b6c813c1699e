"""Behavior Metrics' random perturbations (rain, shadow, snow, fog, sunflare) drawn as BM draws them.

BM pins albumentations 1.0.3; albumentations 2.x changed what these five draw (2.x rain: 20 px drops, 2 x height of
them, a greyed sky; 2.x fog stronger; 2.x snow desaturates; 2.x sun flare weaker). These are drivebench's own
implementations of what 1.0.3 was observed to do with BM's parameters (``benchmarks/bm_perturbations.py`` measures
both side by side; docs/behavior-metrics.md has the numbers). The random draws are seeded NumPy draws, so a frame is
never bit-identical to BM's: the distributions of the drawn quantities are the same.

Lightness changes go through OpenCV's HLS, as 1.0.3's do: scaling L keeps the hue and HLS saturation, so a pale
sky darkened by rain keeps (even deepens) its colour instead of turning grey.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

# Rain as BM asks for it: rain_type "torrential" overrides drop_length=20 with 1.0.3's torrential length.
RAIN_DROP_PX = 60
RAIN_AREA_PX_PER_DROP = 500  # drops = H * W // 500: 614 at 640x480
# 1.0.3 draws a slant in [-10, 10] (truncated to an int) but only uses it for where drops may start: the slant it
# draws with is always its default, +10 px across 60 px down (every streak leans the same way, on every frame).
RAIN_SLANT_PX = 10
RAIN_COLOUR_RGB = (200, 200, 200)
RAIN_BLUR_PX = 7
RAIN_LIGHTNESS = 0.7
SHADOW_LIGHTNESS = 0.5
SNOW_LIGHTNESS_GAIN = 2.5
FOG_ALPHA = 0.08
FLARE_SOURCE_RADIUS_PX = 400


def scale_lightness(image_rgb: np.ndarray, factor: float, *, where: np.ndarray | None = None) -> np.ndarray:
    """HLS lightness times ``factor`` (truncated, as a uint8 cast), everywhere or where ``where`` is true."""
    hls = cv2.cvtColor(image_rgb, cv2.COLOR_RGB2HLS)
    lightness = hls[..., 1].astype(np.float32) * factor
    if where is None:
        hls[..., 1] = np.clip(lightness, 0, 255).astype(np.uint8)
    else:
        hls[..., 1][where] = np.clip(lightness[where], 0, 255).astype(np.uint8)
    return cv2.cvtColor(hls, cv2.COLOR_HLS2RGB)


def rain(image_rgb: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """H*W//500 straight grey streaks 60 px tall leaning 10 px right, a 7x7 box blur, lightness x 0.7."""
    height, width = image_rgb.shape[:2]
    drawn_slant = int(rng.uniform(-RAIN_SLANT_PX, RAIN_SLANT_PX))  # int() truncates towards zero, as 1.0.3's does
    drops = height * width // RAIN_AREA_PX_PER_DROP
    x_low, x_high = (drawn_slant, width) if drawn_slant < 0 else (0, width - drawn_slant)
    xs = rng.integers(x_low, x_high, size=drops, endpoint=True)
    ys = rng.integers(0, max(0, height - RAIN_DROP_PX), size=drops, endpoint=True)
    out = image_rgb.copy()
    for x, y in zip(xs.tolist(), ys.tolist(), strict=True):
        cv2.line(out, (x, y), (x + RAIN_SLANT_PX, y + RAIN_DROP_PX), RAIN_COLOUR_RGB, 1)
    out = cv2.blur(out, (RAIN_BLUR_PX, RAIN_BLUR_PX))
    return scale_lightness(out, RAIN_LIGHTNESS)


def shadow(image_rgb: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """One or two random pentagons in the lower half, their HLS lightness halved."""
    height, width = image_rgb.shape[:2]
    mask = np.zeros((height, width), np.uint8)
    for _ in range(int(rng.integers(1, 2, endpoint=True))):
        xs = rng.integers(0, width, size=5, endpoint=True)
        ys = rng.integers(height // 2, height, size=5, endpoint=True)
        cv2.fillPoly(mask, [np.stack([xs, ys], axis=1).astype(np.int32)], 255)
    return scale_lightness(image_rgb, SHADOW_LIGHTNESS, where=mask == 255)


def snow(image_rgb: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Pixels whose HLS lightness is under a threshold (85 + 127.5 x U(0.1, 0.3)) get it x 2.5, clipped at 255."""
    threshold = 85 + 127.5 * rng.uniform(0.1, 0.3)
    hls = cv2.cvtColor(image_rgb, cv2.COLOR_RGB2HLS)
    lightness = hls[..., 1].astype(np.float32)
    dim = lightness < threshold
    hls[..., 1][dim] = np.clip(lightness[dim] * SNOW_LIGHTNESS_GAIN, 0, 255).astype(np.uint8)
    return cv2.cvtColor(hls, cv2.COLOR_HLS2RGB)


def _fog_centres(height: int, width: int, coef: float, rng: np.random.Generator) -> list[tuple[int, int]]:
    """Haze blobs' top-left corners: rings of growing boxes around the centre, more blobs in each outer ring."""
    hw = max(1, int(width // 3 * coef))
    mid_x, mid_y = width // 2 - 2 * hw, height // 2 - hw
    corners: list[tuple[int, int]] = []
    ring = 1
    while mid_x > -hw or mid_y > -hw:
        count = hw // 10 * ring
        xs = rng.integers(mid_x, max(mid_x, width - mid_x - hw), size=count, endpoint=True)
        ys = rng.integers(mid_y, max(mid_y, height - mid_y - hw), size=count, endpoint=True)
        corners += zip(xs.tolist(), ys.tolist(), strict=True)
        mid_x -= 3 * hw * width // (height + width)
        mid_y -= 3 * hw * height // (height + width)
        ring += 1
    return corners


def fog(image_rgb: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Fog coefficient c ~ U(0.3, 1): many white discs of diameter W/3 x c, each blended at alpha 0.08 c over the
    frame so far, then a box blur of a tenth of the disc size."""
    height, width = image_rgb.shape[:2]
    coef = rng.uniform(0.3, 1.0)
    corners = _fog_centres(height, width, coef, rng)
    hw = max(int(width // 3 * coef), 10)
    radius, alpha = hw // 2, FOG_ALPHA * coef
    # one disc's footprint, blended into its box only (a full-frame blend per disc is what makes it slow)
    disc = np.zeros((2 * radius + 1, 2 * radius + 1), np.uint8)
    cv2.circle(disc, (radius, radius), radius, 1, -1)
    out = image_rgb.astype(np.float32)
    for x, y in corners:
        cx, cy = x + hw // 2, y + hw // 2
        top, left = max(0, cy - radius), max(0, cx - radius)
        bottom, right = min(height, cy + radius + 1), min(width, cx + radius + 1)
        if top >= bottom or left >= right:
            continue
        inside = disc[top - cy + radius : bottom - cy + radius, left - cx + radius : right - cx + radius] == 1
        box = out[top:bottom, left:right]
        box[inside] = np.rint(alpha * 255 + (1 - alpha) * box[inside])
    kernel = max(1, hw // 10)
    return cv2.blur(out.astype(np.uint8), (kernel, kernel))


def sunflare(image_rgb: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A white sun in the upper half (radius 400 px, fading outwards) and 6-10 faint discs along a line through it."""
    height, width = image_rgb.shape[:2]
    angle = 2 * math.pi * rng.uniform(0, 1)
    sun_x, sun_y = int(width * rng.uniform(0, 1)), int(height * rng.uniform(0, 0.5))
    out = image_rgb.astype(np.float32)
    xs = np.arange(0, width, 10)
    ys = 2 * sun_y - (math.tan(angle) * (xs - sun_x) + sun_y)
    for _ in range(int(rng.integers(6, 10, endpoint=True))):
        alpha = rng.uniform(0.05, 0.2)
        index = int(rng.integers(0, len(xs)))
        radius = int(rng.integers(1, max(height // 100 - 2, 2), endpoint=True)) ** 3
        colour = rng.integers(205, 255, size=3, endpoint=True).astype(np.float32)
        mask = np.zeros((height, width), np.uint8)
        cv2.circle(mask, (int(xs[index]), int(np.clip(ys[index], -1e6, 1e6))), radius, 1, -1)
        inside = mask == 1
        out[inside] = np.rint(alpha * colour + (1 - alpha) * out[inside])
    return _sun(out, sun_x=sun_x, sun_y=sun_y).astype(np.uint8)


def _sun(out: np.ndarray, *, sun_x: int, sun_y: int) -> np.ndarray:
    """40 white discs of growing radius, blended from the largest (alpha 0) to the smallest (alpha 1), alpha
    falling as the cube: a white core fading to nothing at 400 px. Computed as each pixel's white weight."""
    height, width = out.shape[:2]
    steps = FLARE_SOURCE_RADIUS_PX // 10
    alphas = np.linspace(0.0, 1.0, steps)
    radii = np.linspace(1, FLARE_SOURCE_RADIUS_PX, steps).astype(int)
    rows, cols = np.ogrid[:height, :width]
    distance_sq = (cols - sun_x) ** 2 + (rows - sun_y) ** 2
    white = np.zeros((height, width), np.float32)
    for step in range(steps):
        alpha = alphas[steps - step - 1] ** 3
        inside = distance_sq <= radii[step] ** 2
        white[inside] = alpha + (1 - alpha) * white[inside]
    return np.rint(white[..., None] * 255 + (1 - white[..., None]) * out)


DRAWS = {"rain": rain, "shadow": shadow, "snow": snow, "fog": fog, "sunflare": sunflare}
