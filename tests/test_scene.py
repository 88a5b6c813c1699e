"""The rendered scene: image format, what the camera sees, culling that changes no pixel, determinism."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from circuits import load_circuit
from protocol.episode_spec import CameraSpec
from services.simulator.car import CarState
from services.simulator.scene import MAX_TRIANGLES_PER_CHUNK, SKY_RGB, Scene, vertical_fov_rad

CIRCUIT = load_circuit("simple")
CAMERA = CameraSpec(width_px=320, height_px=240)


@pytest.fixture(scope="module")
def scene():
    with Scene(CIRCUIT) as scene:
        yield scene


def pose_on_track(s_m: float, lateral_m: float = 0.0, heading_offset_rad: float = 0.0) -> CarState:
    """The car at arc length s_m, lateral_m to the left of the centre line, heading along the track (+ offset)."""
    x, y, heading = CIRCUIT.centreline.pose_at(s_m)
    return CarState(x - lateral_m * math.sin(heading), y + lateral_m * math.cos(heading), heading + heading_offset_rad)


def red_mask(image: np.ndarray) -> np.ndarray:
    red, green, blue = (image[:, :, i].astype(int) for i in range(3))
    return (red > 180) & (green < 60) & (blue < 60)


@pytest.mark.parametrize("size", [(320, 240), (640, 480), (200, 66), (100, 50)])
def test_render_gives_an_rgb_uint8_image_of_the_camera_size(scene, size):
    width, height = size
    image = scene.render(pose_on_track(0.0), CameraSpec(width_px=width, height_px=height))
    assert image.shape == (height, width, 3)
    assert image.dtype == np.uint8
    assert image.flags.c_contiguous and image.flags.writeable


def test_at_the_start_the_red_line_is_ahead_at_the_bottom_centre_and_the_sky_on_top(scene):
    image = scene.render(CarState(*CIRCUIT.start_pose()), CAMERA)
    red = red_mask(image)
    # The bottom-centre is the line right in front of the camera.
    assert red[-20:, 150:170].all()
    assert not red[-20:, :40].any() and not red[-20:, -40:].any()  # road on either side
    # The line is a single band that narrows towards the horizon (row 120 at pitch 0).
    widths = red.sum(axis=1)
    assert widths[-1] > widths[180] > widths[140] > 0
    assert widths[:118].sum() == 0
    # Above the horizon: sky at the top, nothing rendered there.
    assert (image[:100] == SKY_RGB).all(axis=2).mean() > 0.9
    assert (image[0] == SKY_RGB).all()


def test_the_vertical_field_of_view_follows_from_the_aspect_ratio(scene):
    # Behavior Metrics' camera: HFOV 1.57 rad at 640 x 480 is a 73.7 deg vertical field of view.
    assert math.degrees(vertical_fov_rad(CameraSpec(width_px=640, height_px=480))) == pytest.approx(73.7, abs=0.05)
    # The bottom row looks down at vfov/2: from 0.095 m above the line, the 0.10 m line covers
    # 0.10 / (2 * 0.095 / tan(vfov/2)) ~ 39 % of it (the "large red triangle" of the original camera).
    camera = CameraSpec(width_px=640, height_px=480)
    image = scene.render(CarState(*CIRCUIT.start_pose()), camera)
    expected = 0.10 / (2 * 0.095 / math.tan(vertical_fov_rad(camera) / 2))
    assert red_mask(image)[-1].mean() == pytest.approx(expected, abs=0.02)


def test_camera_offsets_and_pitch_move_the_view(scene):
    car = CarState(*CIRCUIT.start_pose())
    centre = red_mask(scene.render(car, CAMERA))[-1]
    shifted_left = red_mask(scene.render(car, CameraSpec(lateral_offset_m=0.04)))[-1]
    columns = np.arange(CAMERA.width_px)
    # A camera moved left sees the line further right.
    assert columns[shifted_left].mean() > columns[centre].mean() + 10
    sky_level = (scene.render(car, CAMERA) == SKY_RGB).all(axis=2).mean()
    sky_down = (scene.render(car, CameraSpec(pitch_down_rad=0.2)) == SKY_RGB).all(axis=2).mean()
    assert sky_down < sky_level - 0.1


def test_only_the_red_line_passes_the_explicit_brains_saturation_mask():
    # HSV S >= 110 and V >= 15 (OpenCV units) must pick the red line and nothing else: road, walls, grass, sky.
    with Scene(CIRCUIT, walls=False) as open_scene, Scene(CIRCUIT, road_colour="white") as white_road:
        for scene in (open_scene, white_road):
            for s in (0.0, 80.0, 130.0, 300.0):
                image = scene.render(pose_on_track(s, lateral_m=0.5, heading_offset_rad=0.3), CAMERA)
                saturated = cv2.inRange(cv2.cvtColor(image, cv2.COLOR_RGB2HSV), (0, 110, 15), (179, 255, 255)) > 0
                assert saturated.any()
                assert np.array_equal(saturated, red_mask(image))


def test_line_variants():
    car = CarState(*CIRCUIT.start_pose())
    for colour in ("white", "none"):
        with Scene(CIRCUIT, line_colour=colour) as scene:
            image = scene.render(car, CAMERA)
            assert not red_mask(image).any()
            hsv = cv2.cvtColor(image, cv2.COLOR_RGB2HSV)
            assert (hsv[:, :, 1] < 110).all()
            bottom_centre = image[-10:, 155:165].reshape(-1, 3)
            if colour == "white":
                assert (bottom_centre > 220).all()
            else:
                assert (bottom_centre < 110).all()  # grey road
    with pytest.raises(ValueError, match="line_colour"):
        Scene(CIRCUIT, line_colour="blue")  # type: ignore[arg-type]


def test_meshes_are_chunked_and_far_chunks_are_culled(scene):
    assert scene.triangle_count / scene.chunk_count <= MAX_TRIANGLES_PER_CHUNK
    scene.render(pose_on_track(0.0), CAMERA)
    visible = scene.visible_chunk_count
    assert 0 < visible < scene.chunk_count / 4
    with Scene(CIRCUIT, cull_margin_m=None) as unculled:
        unculled.render(pose_on_track(0.0), CAMERA)
        assert unculled.visible_chunk_count == unculled.chunk_count


@pytest.mark.parametrize("walls", [True, False])
def test_culling_changes_no_pixel(walls):
    rng = np.random.default_rng(7)
    with Scene(CIRCUIT, walls=walls) as culled, Scene(CIRCUIT, walls=walls, cull_margin_m=None) as unculled:
        for _ in range(12):
            s_m, lateral_m = rng.uniform(0, CIRCUIT.length_m), rng.uniform(-1.4, 1.4)
            heading_offset_rad = rng.uniform(-1, 1)
            car = pose_on_track(s_m, lateral_m, heading_offset_rad)
            for camera in (CameraSpec(width_px=160, height_px=120), CameraSpec(width_px=200, height_px=66)):
                assert np.array_equal(culled.render(car, camera), unculled.render(car, camera))


def test_rendering_is_deterministic_across_calls_and_scenes(scene):
    cars = [pose_on_track(s, lateral_m=0.3) for s in (0.0, 100.0, 250.0, 0.0)]
    first = [scene.render(car, CAMERA) for car in cars]
    assert np.array_equal(first[0], first[3])  # the same pose after going elsewhere
    with Scene(CIRCUIT) as other:  # a second scene in the same process, with its own PyBullet client
        second = [other.render(car, CAMERA) for car in cars]
    for a, b in zip(first, second, strict=True):
        assert np.array_equal(a, b)
    assert not np.array_equal(first[0], first[1])


def test_close_is_idempotent():
    scene = Scene(CIRCUIT)
    scene.close()
    scene.close()
