"""Behavior Metrics' perturbations look as BM's albumentations 1.0.3 draws them, measured on real rendered frames.

The reference figures are albumentations 1.0.3's, measured by ``benchmarks/bm_perturbations.py`` (60 draws, the
simple circuit at 640x480): rain keeps the sky's colour (HSV saturation 36 -> 84), draws streaks 60 px tall (median
connected streak height 59.5 px on a black frame) all leaning right; sunflare brightens 46 % of the pixels.
albumentations 2.x: sky 36 -> 33, 19 px streaks, sunflare 33 %.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from protocol.episode_spec import Rain, Sunflare
from services.noise.models import make_model

SKY_ROWS = slice(0, 150)


@pytest.fixture(scope="module")
def frame() -> np.ndarray:
    """The simple circuit seen from its centreline at 48 m, through BM's 640x480 camera (real PyBullet)."""
    from circuits import load_circuit
    from protocol.episode_spec import CameraSpec, WorldVariation
    from services.simulator.car import CarState
    from services.simulator.scene import Scene

    track = load_circuit("simple")
    with Scene.for_world(track, WorldVariation()) as scene:
        return scene.render(CarState(*track.centreline.pose_at(48.0)), CameraSpec(width_px=640, height_px=480))


def sky_saturation(image: np.ndarray) -> float:
    return float(cv2.cvtColor(np.ascontiguousarray(image[SKY_ROWS]), cv2.COLOR_RGB2HSV)[..., 1].mean())


def perturbed(stage, image: np.ndarray, seeds: range) -> list[np.ndarray]:
    model = make_model(stage)
    outputs = []
    for seed in seeds:
        model.reset(seed=seed)
        outputs.append(model.apply(image))
    return outputs


def test_rain_keeps_the_sky_s_colour_and_darkens_it(frame):
    before = sky_saturation(frame)
    assert 25 < before < 50, "the rendered sky is pale blue"
    for rainy in perturbed(Rain(), frame, range(3)):
        assert sky_saturation(rainy) > 1.8 * before  # 1.0.3: 36 -> 84; 2.x greys it: 36 -> 33
        assert rainy[SKY_ROWS].mean() < 0.85 * frame[SKY_ROWS].mean()  # lightness x 0.7


def streak_heights(rainy_black: np.ndarray) -> list[int]:
    grey = cv2.cvtColor(rainy_black, cv2.COLOR_RGB2GRAY)
    count, _, stats, _ = cv2.connectedComponentsWithStats((grey > 20).astype(np.uint8), connectivity=8)
    return [int(stats[i, cv2.CC_STAT_HEIGHT]) for i in range(1, count)]


def test_rain_draws_614_streaks_60_px_tall_all_leaning_right(frame):
    black = np.zeros_like(frame)
    rainy = perturbed(Rain(), black, range(8))
    heights = [height for image in rainy for height in streak_heights(image)]
    assert 50 <= np.median(heights) <= 70  # 1.0.3: 59.5 px; 2.x's 20 px drops: 19 px
    # ink: 614 streaks x 61 px x grey 200 x lightness 0.7, less overlaps and the edges: 4.80e6 in 1.0.3
    ink = np.mean([cv2.cvtColor(image, cv2.COLOR_RGB2GRAY).sum() for image in rainy])
    assert 4.5e6 < ink < 5.1e6
    # every streak leans the same way: the rain layer matches itself 60 rows down and 10 columns right
    layer = cv2.cvtColor(rainy[0], cv2.COLOR_RGB2GRAY).astype(float)
    right = np.corrcoef(layer[:-30, :-5].ravel(), layer[30:, 5:].ravel())[0, 1]
    left = np.corrcoef(layer[:-30, 5:].ravel(), layer[30:, :-5].ravel())[0, 1]
    assert right > left + 0.2


def test_sunflare_brightens_about_half_the_frame(frame):
    brightened = [
        float(((image.astype(int).sum(axis=2) - frame.astype(int).sum(axis=2)) > 30).mean())
        for image in perturbed(Sunflare(), frame, range(40))
    ]
    assert np.mean(brightened) > 0.40  # 1.0.3: 0.46 over 60 draws; 2.x: 0.33
