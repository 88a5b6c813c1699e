"""The ``look`` world variation: the gazebo look as the gl renderer draws it (statistics of road and grass patches,
shadows where Behavior Metrics' worlds have them, determinism), and the look as a variation everywhere (bad looks and
renderers that cannot draw a look refused in one line before anything starts, the randomised recipe).

The gl tests need moderngl and an EGL context (Mesa's llvmpipe on CPU): they skip on a developer's machine without
them and fail in CI, which installs the gl extra (scripts/setup.sh).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest
from test_renderers import require_gl

from circuits import load_circuit
from orchestrator.collect import randomised
from protocol.episode_spec import CameraSpec, EpisodeSpec, WorldVariation
from protocol.variations import VariationError, apply_variation, check_look
from services.simulator.car import CarState
from services.simulator.looks import (
    ASPHALT_MEAN_RGB,
    ASPHALT_SPREAD,
    ASPHALT_TEXEL_GAIN,
    GRASS_MEAN_RGB,
    GRASS_SPREAD,
    asphalt_texture,
    gazebo_lighting,
    grass_texture,
)
from services.simulator.renderers import RendererUnavailable, make_scene
from services.simulator.world import describe_world

SIMPLE = load_circuit("simple")
GAZEBO = WorldVariation(look="gazebo")


def spread(pixels: np.ndarray) -> float:
    """The mean over channels of the per-channel standard deviation (the statistic gazebo-look.md gives)."""
    return float(pixels.reshape(-1, 3).astype(float).std(axis=0).mean())


def within(value: float, target: float, fraction: float = 0.10) -> bool:
    return abs(value - target) <= fraction * target


def test_textures_have_the_measured_statistics_and_are_seeded():
    for texels, mean_rgb, target in (
        (asphalt_texture(), ASPHALT_MEAN_RGB, ASPHALT_SPREAD * ASPHALT_TEXEL_GAIN),
        (grass_texture(), GRASS_MEAN_RGB, GRASS_SPREAD),
    ):
        assert texels.dtype == np.uint8 and texels.shape == (256, 256, 3)
        assert np.allclose(texels.reshape(-1, 3).mean(axis=0), mean_rgb, atol=1.0)
        assert within(spread(texels), target, 0.03)
    assert np.array_equal(asphalt_texture(), asphalt_texture())  # seeded: the same texels every time


def test_bm_worlds_with_shadows_and_flat_light():
    assert gazebo_lighting("montreal", "sun").shadows and gazebo_lighting("montmelo", "sun").shadows
    assert gazebo_lighting("nurburgring", "sun").shadows
    assert not gazebo_lighting("simple", "sun").shadows and not gazebo_lighting("many_curves", "sun").shadows
    assert gazebo_lighting("simple", "sun").ambient == 1.0 and gazebo_lighting("montreal", "sun").ambient == 0.4
    assert not gazebo_lighting("montreal", "no_sun").shadows and gazebo_lighting("montreal", "no_sun").diffuse == 0


def _patches(scene, *, camera: CameraSpec, offset_m: float, road: bool) -> np.ndarray:
    """The bottom 30 % of frames at 8 poses round simple, offset_m to the left of the centre line (pooled)."""
    pixels = []
    for index in range(8):
        x, y, heading = SIMPLE.centreline.pose_at(10.0 + index * SIMPLE.length_m / 8)
        car = CarState(x - offset_m * math.sin(heading), y + offset_m * math.cos(heading), heading)
        bottom = scene.render(car, camera)[int(0.7 * camera.height_px) :]
        if not road:
            pixels.append(bottom.reshape(-1, 3))
        else:  # both sides of the centre line, clear of it in the bends
            width = camera.width_px
            pixels += [bottom[:, : int(0.2 * width)].reshape(-1, 3), bottom[:, int(0.8 * width) :].reshape(-1, 3)]
    return np.concatenate(pixels)


@pytest.mark.parametrize("size", [(320, 240), (640, 480)], ids=["320x240", "640x480"])
def test_rendered_road_and_grass_patches_match_gazebo_within_10_percent(size):
    require_gl()
    camera = CameraSpec(width_px=size[0], height_px=size[1])
    with make_scene(SIMPLE, GAZEBO, renderer="gl") as road_scene:
        road = _patches(road_scene, camera=camera, offset_m=0.0, road=True)
    # No walls, the car 8 m off the road: the bottom of the frame is grass.
    with make_scene(SIMPLE, WorldVariation(look="gazebo", walls=False), renderer="gl") as grass_scene:
        grass = _patches(grass_scene, camera=camera, offset_m=8.0, road=False)
    for pixels, mean_rgb, target in ((road, ASPHALT_MEAN_RGB, ASPHALT_SPREAD), (grass, GRASS_MEAN_RGB, GRASS_SPREAD)):
        means = pixels.astype(float).mean(axis=0)
        assert all(within(float(m), t) for m, t in zip(means, mean_rgb)), (means, mean_rgb)
        assert within(spread(pixels), target), (spread(pixels), target)


def _darkened_fraction(circuit_name: str, *, s_m: float, force_shadows: bool | None = None) -> float:
    """The fraction of pixels the sun's shadows darken: the frame against the same frame drawn without shadows."""
    from services.simulator.gl_scene import GLScene

    circuit = load_circuit(circuit_name)
    description = describe_world(circuit, GAZEBO)
    light = description.gazebo
    assert light is not None
    if force_shadows is not None:
        description = dataclasses.replace(description, gazebo=dataclasses.replace(light, shadows=force_shadows))
    unshadowed = dataclasses.replace(description, gazebo=dataclasses.replace(light, shadows=False))
    car = CarState(*circuit.centreline.pose_at(s_m))
    camera = CameraSpec(width_px=320, height_px=240)
    with GLScene(description) as scene, GLScene(unshadowed) as plain:
        darker = plain.render(car, camera).astype(int) - scene.render(car, camera).astype(int)
    return float((darker.max(axis=2) > 20).mean())


def test_shadows_fall_on_montreal_and_not_on_simple():
    require_gl()
    # Montreal 358 m: heading south-west, the sun behind the left wall, whose shadow covers the left edge line.
    assert _darkened_fraction("montreal", s_m=358.0) > 0.001
    # simple has no shadows (BM turns them off), though its walls would cast them there: the test can fail.
    assert _darkened_fraction("simple", s_m=90.0) == 0.0
    assert _darkened_fraction("simple", s_m=90.0, force_shadows=True) > 0.001


@pytest.mark.parametrize("circuit_name", ["simple", "montreal"])
def test_two_renders_of_a_pose_are_identical(circuit_name):
    require_gl()
    circuit = load_circuit(circuit_name)
    car = CarState(*circuit.centreline.pose_at(358.0 % circuit.length_m))
    camera = CameraSpec(width_px=320, height_px=240)
    with make_scene(circuit, GAZEBO, renderer="gl") as first, make_scene(circuit, GAZEBO, renderer="gl") as second:
        frame = first.render(car, camera)
        first.render(CarState(car.x_m + 3.0, car.y_m, car.yaw_rad + 0.5), camera)  # another pose in between
        assert np.array_equal(frame, first.render(car, camera))
        assert np.array_equal(frame, second.render(car, camera))
    with make_scene(circuit, WorldVariation(), renderer="gl") as flat:
        assert not np.array_equal(frame, flat.render(car, camera))  # the look changes the picture


def test_more_llvmpipe_threads_draw_the_same_pixels(tmp_path):
    """drivebench run's simulator renders with every core (orchestrator.stack.launcher.render_threads_for), a matrix
    worker's with its share: the frames must not depend on it (shadowed Montreal, 640x480: 80 tiles, all threads)."""
    require_gl()
    code = """
        import sys
        import numpy as np
        from circuits import load_circuit
        from protocol.episode_spec import CameraSpec, WorldVariation
        from services.simulator.parity import parity_poses
        from services.simulator.renderers import make_scene
        circuit = load_circuit("montreal")
        with make_scene(circuit, WorldVariation(look="gazebo"), renderer="gl") as scene:
            camera = CameraSpec(width_px=640, height_px=480)
            np.save(sys.argv[1], np.stack([scene.render(car, camera) for car in parity_poses(circuit, count=4)]))
    """
    frames = {}
    for threads in ("1", "2"):
        path = tmp_path / f"threads-{threads}.npy"
        child = subprocess.run(
            [sys.executable, "-c", textwrap.dedent(code), str(path)],
            capture_output=True,
            text=True,
            timeout=120,
            env={**os.environ, "LP_NUM_THREADS": threads},
        )
        assert child.returncode == 0, child.stderr
        frames[threads] = np.load(path)
    assert frames["1"].shape == (4, 480, 640, 3) and frames["1"].std() > 10  # a picture, not a blank
    assert np.array_equal(frames["1"], frames["2"])


def test_unknown_look_and_renderers_that_cannot_draw_it_are_named():
    with pytest.raises(VariationError, match=r"unknown look 'pretty' \(looks: flat, gazebo\)"):
        apply_variation(EpisodeSpec(), "look=pretty")
    spec = apply_variation(EpisodeSpec(renderer="pybullet"), "look=gazebo")
    with pytest.raises(VariationError, match="look=gazebo needs renderer gl or auto, got renderer pybullet"):
        check_look(spec)
    check_look(apply_variation(EpisodeSpec(renderer="gl"), "look=gazebo"))
    check_look(apply_variation(EpisodeSpec(renderer="auto"), "look=gazebo"))
    check_look(EpisodeSpec(renderer="pybullet"))  # flat: both renderers
    with pytest.raises(RendererUnavailable, match="renderer pybullet cannot draw look=gazebo"):
        make_scene(SIMPLE, GAZEBO, renderer="pybullet")


@pytest.mark.integration
@pytest.mark.parametrize(
    "args, message",
    [
        (["--variation", "look=gazebo", "--renderer", "pybullet"], "look=gazebo needs renderer gl or auto"),
        (["--variation", "look=shiny"], "unknown look 'shiny' (looks: flat, gazebo)"),
    ],
)
def test_run_refuses_a_look_in_one_line_before_the_stack_starts(tmp_path, args, message):
    out = tmp_path / "r"
    result = subprocess.run(
        [sys.executable, "-m", "orchestrator.cli", "run", "--out", str(out), *args],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 2 and message in result.stderr, result.stderr
    assert len(result.stderr.strip().splitlines()) == 1 and "Traceback" not in result.stderr
    assert not out.exists()


@pytest.mark.integration
def test_matrix_refuses_a_look_its_renderer_cannot_draw(tmp_path):
    matrix = tmp_path / "m.yaml"
    matrix.write_text(
        "name: looks\nbrains: [explicit]\ncircuits: [simple]\nvariations: {look: [flat, gazebo]}\n"
        "renderer: pybullet\nlimits: {max_sim_seconds: 2}\n"
    )
    result = subprocess.run(
        [sys.executable, "-m", "orchestrator.cli", "matrix", str(matrix), "-o", str(tmp_path / "out")],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 2, result.stderr
    assert "looks: look=gazebo needs renderer gl or auto, got renderer pybullet" in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1 and not (tmp_path / "out").exists()


def test_randomised_recipe_draws_looks_only_when_asked_and_leaves_other_draws_alone():
    specs = [EpisodeSpec(seed=seed, renderer="gl") for seed in range(12)]
    flat = [randomised(spec) for spec in specs]
    mixed = [randomised(spec, looks=("flat", "gazebo")) for spec in specs]
    assert {spec.world.look for spec in flat} == {"flat"}
    assert {spec.world.look for spec in mixed} == {"flat", "gazebo"}
    for a, b in zip(flat, mixed):  # the look has a generator of its own: everything else is drawn as before
        assert a.noise == b.noise and a.camera == b.camera
        assert (a.world.line, a.world.road, a.world.walls, a.world.lighting) == (
            b.world.line,
            b.world.road,
            b.world.walls,
            b.world.lighting,
        )


@pytest.mark.integration
def test_run_draws_the_gazebo_look_with_gl_when_no_renderer_is_named(tmp_path):
    require_gl()
    env = {key: value for key, value in os.environ.items() if key != "DRIVEBENCH_RENDERER"}
    result = subprocess.run(
        [sys.executable, "-m", "orchestrator.cli", "run", "--variation", "look=gazebo", "--max-sim-seconds", "2"]
        + ["--camera", "160x120", "--json", "--out", str(tmp_path / "r")],
        capture_output=True,
        text=True,
        timeout=120,
        env=env,
    )
    assert result.returncode == 0, result.stderr
    score = json.loads(result.stdout)
    assert score["spec"]["renderer"] == "gl" and score["spec"]["world"]["look"] == "gazebo"
    assert score["metrics"]["steps"] == 40


@pytest.mark.integration
def test_run_refuses_the_gazebo_look_where_auto_falls_back_to_pybullet(tmp_path):
    env = {**os.environ, "GLCONTEXT_LINUX_LIBEGL": "/nonexistent/libEGL.so.1"}  # no EGL: auto means pybullet
    env.pop("DRIVEBENCH_RENDERER", None)
    result = subprocess.run(
        [sys.executable, "-m", "orchestrator.cli", "run", "--variation", "look=gazebo", "--out", str(tmp_path / "r")],
        capture_output=True,
        text=True,
        timeout=60,
        env=env,
    )
    assert result.returncode == 2, result.stderr
    assert "look=gazebo needs the gl renderer: renderer auto: using pybullet (" in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1 and not (tmp_path / "r").exists()
