"""The gazebo look: Behavior Metrics' Gazebo worlds re-created from their measured statistics (gazebo-look.md).

Pure NumPy. Holds the look's materials, its lighting per world, and its procedural, seeded textures: tiled asphalt
(mean RGB 66 / 61 / 62, spread 11, a tile every 0.30 m), tiled grass (138 / 158 / 68, spread 26, a tile every
1.18 m) and static clouds. Nothing is downloaded or copied: every texture is noise shaped in the frequency domain
(so that it tiles without a seam) and scaled to the statistics, from fixed seeds (the same texels on every machine).

"Spread" is the mean over the three channels of the per-channel standard deviation of the pixels of a patch. The
texels have the target mean and spread (the asphalt a little more, see ASPHALT_TEXEL_GAIN); most of the spread
lies at scales of a centimetre or more, so that the patches the gl renderer draws close to the camera (mipmapped and
filtered) keep it: ``tests/test_looks.py`` measures them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

ASPHALT_MEAN_RGB = (66.0, 61.0, 62.0)
ASPHALT_SPREAD = 11.0
ASPHALT_TILE_M = 0.30
GRASS_MEAN_RGB = (138.0, 158.0, 68.0)
GRASS_SPREAD = 26.0
GRASS_TILE_M = 1.18
EDGE_LINE_GREY = 0.78  # light grey edge lines on both road sides
WALL_GREY = 0.64
WALL_SPECULAR = 0.5  # the walls' material; Gazebo's sun adds a specular of its own (SUN_SPECULAR)
WALL_SHININESS = 50.0
SUN_SPECULAR = 0.2  # Gazebo's default sun
SUN_DIFFUSE = 0.8
SUN_TOWARDS = (0.5, -0.5, 1.0)  # towards the sun: Gazebo's sun shines along (-0.5, 0.5, -1)
DEFAULT_AMBIENT = 0.4  # Gazebo's default scene ambient
SKY_HORIZON_RGB = (200, 212, 226)
SKY_ZENITH_RGB = (82, 132, 204)
CLOUD_RGB = (236, 238, 242)

# Behavior Metrics' worlds with the sun's shadows on (Gazebo's default); simple_circuit and many_curves turn them
# off, and simple_circuit lights everything with ambient 1.0. drivebench's own circuits follow the BM circuit they
# derive from (extended_simple: simple); generated ones take the cheaper shadowless lighting.
SHADOWED_CIRCUITS = frozenset({"montreal", "montmelo", "nurburgring", "monaco"})
FULL_AMBIENT_CIRCUITS = frozenset({"simple", "extended_simple"})

# The asphalt's texels spread this much more than the target: filtering and mipmaps average neighbouring grains,
# and the rendered road then spreads ~10.5 at 320x240 and ~11.4 at 640x480 (tests/test_looks.py); the grass's
# coarser blotches survive filtering (rendered ~25.5 against 26 in the texels).
ASPHALT_TEXEL_GAIN = 1.1

_TEXTURE_SEEDS = {"asphalt": 30_01, "grass": 30_02, "clouds": 30_03}


@dataclass(frozen=True)
class GazeboLighting:
    """The look's light for one world.

    ambient, diffuse: Gazebo's scene ambient and the sun's diffuse; the rendered colour of a surface is
        ``texel * (ambient + diffuse * max(0, n . l) * lit) / exposure`` plus the walls' specular term, with ``lit``
        0 in the sun's shadow. exposure: the factor of sunlit level ground, so that such ground shows its texture's
        own colour (what the statistics were measured on). sun: whether there is a sun (no_sun: ambient only).
    shadows: whether the sun casts shadows (a shadow map).
    """

    ambient: float
    diffuse: float
    exposure: float
    sun: bool
    shadows: bool
    light_towards: tuple[float, float, float]


def gazebo_lighting(circuit_name: str, lighting: str) -> GazeboLighting:
    """The gazebo look's light for a circuit (by name) and lighting variation ("sun" or "no_sun")."""
    towards = np.asarray(SUN_TOWARDS) / np.linalg.norm(SUN_TOWARDS)
    ambient = 1.0 if circuit_name in FULL_AMBIENT_CIRCUITS else DEFAULT_AMBIENT
    exposure = ambient + SUN_DIFFUSE * float(towards[2])  # sunlit level ground
    sun = lighting == "sun"
    return GazeboLighting(
        ambient=ambient,
        diffuse=SUN_DIFFUSE if sun else 0.0,
        exposure=exposure,
        sun=sun,
        shadows=sun and circuit_name in SHADOWED_CIRCUITS,
        light_towards=(float(towards[0]), float(towards[1]), float(towards[2])),
    )


def _tileable_noise(rng: np.random.Generator, size_px: int, *, slope: float, low_cut: int, high_cut: int) -> np.ndarray:
    """Zero-mean, unit-spread noise that tiles: random Fourier coefficients with amplitude ~ 1 / f**slope between
    ``low_cut`` and ``high_cut`` cycles per tile (the inverse FFT of a periodic spectrum is periodic)."""
    fy = np.fft.fftfreq(size_px)[:, None] * size_px
    fx = np.fft.rfftfreq(size_px)[None, :] * size_px
    f = np.hypot(fx, fy)
    amplitude = np.where((f >= low_cut) & (f <= high_cut), 1.0 / np.maximum(f, 1.0) ** slope, 0.0)
    shape = amplitude.shape
    coefficients = amplitude * (rng.standard_normal(shape) + 1j * rng.standard_normal(shape))
    noise = np.fft.irfft2(coefficients, s=(size_px, size_px))
    return (noise - noise.mean()) / noise.std()


def _textured(mean_rgb: tuple[float, float, float], spread: float, luma: np.ndarray, chroma: np.ndarray) -> np.ndarray:
    """uint8 RGB texels of a mean colour whose per-channel spread averages ``spread``: luma noise scaled by each
    channel's mean (as light and shade scale a colour), plus a little independent noise per channel."""
    mean = np.asarray(mean_rgb)
    weights = mean / mean.mean()
    variation = luma[..., None] * weights + 0.12 * chroma
    variation *= spread / variation.std(axis=(0, 1)).mean()
    texels = mean + variation - variation.mean(axis=(0, 1))
    return np.clip(np.rint(texels), 0, 255).astype(np.uint8)


def asphalt_texture(size_px: int = 256) -> np.ndarray:
    """One 0.30 m asphalt tile, size_px x size_px x 3 uint8: grains a few millimetres across."""
    rng = np.random.default_rng(_TEXTURE_SEEDS["asphalt"])
    luma = _tileable_noise(rng, size_px, slope=0.6, low_cut=2, high_cut=size_px // 12)
    chroma = np.stack([_tileable_noise(rng, size_px, slope=0.5, low_cut=2, high_cut=size_px // 6) for _ in range(3)], 2)
    return _textured(ASPHALT_MEAN_RGB, ASPHALT_SPREAD * ASPHALT_TEXEL_GAIN, luma, chroma)


def grass_texture(size_px: int = 256) -> np.ndarray:
    """One 1.18 m grass tile, size_px x size_px x 3 uint8: blotches and blades a few centimetres across."""
    rng = np.random.default_rng(_TEXTURE_SEEDS["grass"])
    luma = _tileable_noise(rng, size_px, slope=0.8, low_cut=1, high_cut=size_px // 4)
    chroma = np.stack([_tileable_noise(rng, size_px, slope=0.5, low_cut=2, high_cut=size_px // 4) for _ in range(3)], 2)
    return _textured(GRASS_MEAN_RGB, GRASS_SPREAD, luma, chroma)


def cloud_texture(size_px: int = 256) -> np.ndarray:
    """Cloud cover, size_px x size_px uint8 (0 clear .. 255 overcast): soft, static, seeded."""
    rng = np.random.default_rng(_TEXTURE_SEEDS["clouds"])
    noise = _tileable_noise(rng, size_px, slope=1.6, low_cut=1, high_cut=size_px // 4)
    cover = np.clip((noise - 0.4) / 1.4, 0.0, 1.0)  # about a third of the sky clouded
    return np.rint(255 * cover).astype(np.uint8)
