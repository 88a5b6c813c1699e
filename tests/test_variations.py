"""World variations and camera presets: parsing, and rendered images that look right (real PyBullet)."""

from __future__ import annotations

import numpy as np
import pytest

from circuits import load_circuit
from protocol.episode_spec import Drop, EpisodeSpec, Jpeg, Occlusion, SaltPepper, WorldVariation
from protocol.variations import CAMERA_PRESETS, VariationError, apply_variation, noise_stage
from services.simulator.car import CarState
from services.simulator.scene import Scene

CIRCUIT = load_circuit("simple")


def render(world: str = "", *, s_m: float = 20.0) -> np.ndarray:
    """A 320x240 frame on the top straight of simple (a straight: the line runs up the middle)."""
    spec = apply_variation(EpisodeSpec(), world) if world else EpisodeSpec()
    x, y, yaw = CIRCUIT.centreline.pose_at(s_m)
    with Scene.for_world(CIRCUIT, spec.world) as scene:
        return scene.render(CarState(x_m=x, y_m=y, yaw_rad=yaw), spec.camera).astype(int)


def bottom_centre(image: np.ndarray) -> np.ndarray:
    h, w = image.shape[:2]
    return image[int(0.9 * h) :, int(0.45 * w) : int(0.55 * w)].reshape(-1, 3)


def beside_road(image: np.ndarray) -> np.ndarray:
    """Just above the horizon at the image sides: walls when they are on, sky (and grass) when off."""
    h, w = image.shape[:2]
    return np.concatenate(
        [
            image[int(0.42 * h) : int(0.49 * h), : int(0.1 * w)].reshape(-1, 3),
            image[int(0.42 * h) : int(0.49 * h), int(0.9 * w) :].reshape(-1, 3),
        ]
    )


def test_line_colours():
    red, white, none = (bottom_centre(render(f"line={c}")).mean(axis=0) for c in ("red", "white", "none"))
    assert red[0] > 200 and red[1] < 40 and red[2] < 40
    assert white.min() > 200
    assert abs(none[0] - none[1]) < 5 and none.max() < 120  # grey asphalt where the line was


def test_road_colours():
    h, w = 240, 320
    grey = render("road=grey")[int(0.9 * h) :, : int(0.15 * w)].reshape(-1, 3).mean(axis=0)
    white = render("road=white")[int(0.9 * h) :, : int(0.15 * w)].reshape(-1, 3).mean(axis=0)
    assert grey.max() < 120 and white.min() > 170
    assert np.ptp(grey) < 5 and np.ptp(white) < 5  # unsaturated


def test_walls_hide_what_lies_beyond_the_road():
    with_walls = beside_road(render("walls=on"))
    assert np.all(np.abs(with_walls[:, 0] - with_walls[:, 2]) < 5)  # grey wall everywhere there
    assert 120 < with_walls[:, 0].mean() < 170  # darker than the sky in red (the explicit brain's speed rule)
    h = 240
    without = render("walls=off")
    horizon_band = without[int(0.45 * h) : int(0.52 * h)].reshape(-1, 3)
    grass = (horizon_band[:, 1] > horizon_band[:, 0] + 10) & (horizon_band[:, 1] > horizon_band[:, 2] + 10)
    assert grass.mean() > 0.05  # grass seen beyond the road edge
    with_band = render("walls=on")[int(0.45 * h) : int(0.52 * h)].reshape(-1, 3)
    assert ((with_band[:, 1] > with_band[:, 0] + 10) & (with_band[:, 1] > with_band[:, 2] + 10)).mean() == 0


def test_no_sun_is_darker():
    assert render("lighting=no_sun").mean() < 0.7 * render().mean()


def test_camera_offsets_move_the_line_the_right_way():
    def line_x(image: np.ndarray) -> float:
        rows = image[int(0.8 * image.shape[0]) :]
        red = (rows[..., 0] > 180) & (rows[..., 1] < 60)
        return float(np.nonzero(red)[1].mean())

    centre = line_x(render())
    assert line_x(render("camera=left")) > centre + 20  # camera moved left: the line is to its right
    assert line_x(render("camera=right")) < centre - 20
    assert line_x(render("camera_yaw_rad=0.2")) > centre + 20  # camera turned left: the line moves right


def test_pitch_moves_the_horizon():
    def horizon_row(image: np.ndarray) -> int:
        road = (np.abs(image[..., 0] - 80) < 25) & (np.ptp(image, axis=2) < 8)
        return int(np.argmax(road[:, image.shape[1] // 4]))

    level = horizon_row(render())
    assert horizon_row(render("camera_pitch_rad=0.2")) < level - 10  # looking down: the horizon rises
    assert horizon_row(render("camera_pitch_rad=-0.2")) > level + 10


def test_presets_match_behavior_metrics_offsets():
    spec = EpisodeSpec()
    assert apply_variation(spec, "camera=left").camera.lateral_offset_m == pytest.approx(0.20)
    assert apply_variation(spec, "camera=right").camera.lateral_offset_m == pytest.approx(-0.20)
    down = apply_variation(spec, "camera=rotate_down").camera
    assert (down.lateral_offset_m, down.pitch_down_rad) == pytest.approx((-0.20, 0.2))
    assert set(CAMERA_PRESETS) >= {"left", "right", "rotate_down", "rotate_up"}


def test_variation_parsing():
    spec = apply_variation(EpisodeSpec(), "line=white,road=white,walls=off,lighting=no_sun")
    assert spec.world == WorldVariation(line="white", road="white", walls=False, lighting="no_sun")
    assert apply_variation(EpisodeSpec(), {"walls": False, "line": "none"}).world.walls is False
    reverse = apply_variation(EpisodeSpec(), "direction=reverse,line=white")
    assert reverse.direction == "reverse" and reverse.world.line == "white"
    assert apply_variation(reverse, "start_m=120.5").start_m == 120.5
    assert apply_variation(reverse, {"start_m": 7}).start_m == 7.0
    with pytest.raises(ValueError, match="direction must be one of forward, reverse"):
        EpisodeSpec(direction="sideways")
    for bad, message in [
        ("line=blue", "line must be one of red, white, none"),
        ("walls=maybe", "walls must be on"),
        ("camera=top", "unknown camera preset 'top'"),
        ("fog=1", "unknown variation 'fog'"),
        ("line", "must look like key=value"),
        ("camera_hfov_rad=9", "hfov_rad must be within"),
        ("direction=backwards", "direction must be one of forward, reverse"),
        ("start_m=-1", "start_m must be a number of metres >= 0, got '-1'"),
        ("start_m=far", "start_m must be a number, got 'far'"),
    ]:
        with pytest.raises(VariationError, match=message):
            apply_variation(EpisodeSpec(), bad)


def test_noise_shorthands():
    assert noise_stage("salt_pepper=0.4") == SaltPepper(probability=0.4)
    assert noise_stage({"jpeg": 30}) == Jpeg(quality=30)
    assert noise_stage("occlusion:patches=3,size_fraction=0.1") == Occlusion(patches=3, size_fraction=0.1)
    assert noise_stage({"drop": {"probability": 0.5}}) == Drop(probability=0.5)
    for bad, message in [
        ("hail=1", "unknown noise model 'hail'"),
        ("jpeg=0", "quality must be within 1..100"),
        ("salt_pepper=lots", "Expected `float`"),
        ({"a": 1, "b": 2}, "one model"),
    ]:
        with pytest.raises(VariationError, match=message):
            noise_stage(bad)
