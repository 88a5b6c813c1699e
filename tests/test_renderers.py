"""Both renderers of one scene: every variation drawn by content, bitwise determinism per backend, parity between
them, ``auto`` falling back where EGL is missing, and the choice recorded in the score and the recording.

The gl tests need moderngl and an EGL context (Mesa's llvmpipe on CPU): they skip on a developer's machine without
them and fail in CI, which installs the gl extra (scripts/setup.sh).
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import subprocess
import sys
import textwrap

import needs
import numpy as np
import pybullet
import pytest
from mcap.reader import make_reader
from support.processes import environment_of

from circuits import load_circuit
from orchestrator.matrix.load import MatrixError, parse_matrix, with_renderer
from orchestrator.matrix.runner import MatrixRunner, RunOptions
from orchestrator.stack.launcher import render_threads_for
from protocol.episode_spec import CameraSpec, EpisodeSpec, WorldVariation
from services.simulator.car import CarState
from services.simulator.episode import EpisodeSim, SceneCache
from services.simulator.parity import differing_fraction, mean_absolute_difference, parity_poses, ssim
from services.simulator.renderers import RendererUnavailable, make_scene, resolve_renderer, resolve_spec
from services.simulator.world import (
    GRASS_COLOUR,
    LIGHTING,
    LINE_COLOURS,
    ROAD_COLOURS,
    SKY_RGB_BY_LIGHTING,
    WALL_COLOUR,
    projection_matrix,
    vertical_fov_rad,
    view_matrix,
)

CIRCUIT = load_circuit("simple")
CAMERA = CameraSpec(width_px=320, height_px=240)
NO_EGL = {"GLCONTEXT_LINUX_LIBEGL": "/nonexistent/libEGL.so.1"}  # glcontext's own variable: the library won't load


require_gl = needs.require_gl


@pytest.fixture(params=["pybullet", "gl"])
def renderer(request) -> str:
    if request.param == "gl":
        require_gl()
    return request.param


def lit_range(rgba: tuple[float, ...], lighting: str) -> tuple[np.ndarray, np.ndarray]:
    """The lowest and highest 8-bit RGB a surface of colour ``rgba`` can take under ``lighting``."""
    colour8 = np.floor(np.asarray(rgba[:3]) * 255)
    ambient, diffuse = LIGHTING[lighting]["lightAmbientCoeff"], LIGHTING[lighting]["lightDiffuseCoeff"]
    return np.floor(colour8 * ambient), np.minimum(255, np.floor(colour8 * (ambient + diffuse)))


def is_lit(pixels: np.ndarray, rgba: tuple[float, ...], lighting: str) -> bool:
    low, high = lit_range(rgba, lighting)
    pixels = pixels.reshape(-1, 3)
    return bool(((pixels >= low) & (pixels <= high)).all())


WORLDS = [
    WorldVariation(),
    WorldVariation(line="white"),
    WorldVariation(line="none"),
    WorldVariation(road="white"),
    WorldVariation(walls=False),
    WorldVariation(lighting="no_sun"),
    WorldVariation(line="white", road="white", walls=False, lighting="no_sun"),
]


@pytest.mark.parametrize(
    "world", WORLDS, ids=lambda w: f"{w.line}-{w.road}-{'walls' if w.walls else 'open'}-{w.lighting}"
)
def test_every_variation_is_drawn_by_both_renderers(renderer, world):
    scene = make_scene(CIRCUIT, world, renderer=renderer)
    try:
        image = scene.render(CarState(*CIRCUIT.start_pose()), CAMERA)
    finally:
        scene.close()
    assert image.shape == (240, 320, 3) and image.dtype == np.uint8 and image.flags.c_contiguous
    # The road on either side of the line, right in front of the car.
    assert is_lit(image[-20:, :40], ROAD_COLOURS[world.road], world.lighting)
    assert is_lit(image[-20:, -40:], ROAD_COLOURS[world.road], world.lighting)
    # The centre line (or the road where there is none) at the bottom centre.
    line_rgba = LINE_COLOURS.get(world.line, ROAD_COLOURS[world.road])
    assert is_lit(image[-10:, 155:165], line_rgba, world.lighting)
    # The sky on top.
    assert (image[:20] == SKY_RGB_BY_LIGHTING[world.lighting]).all()
    # Walls rise above the horizon on both sides; without them, sky there and grass beyond the road below it.
    beside_horizon = np.concatenate([image[100:116, :10], image[100:116, -10:]])
    low, high = lit_range(GRASS_COLOUR, world.lighting)
    grass_pixels = int(((image.reshape(-1, 3) >= low) & (image.reshape(-1, 3) <= high)).all(axis=1).sum())
    if world.walls:
        assert is_lit(beside_horizon, WALL_COLOUR, world.lighting)
        assert grass_pixels == 0
    else:
        assert (beside_horizon == SKY_RGB_BY_LIGHTING[world.lighting]).all()
        assert grass_pixels > 50


def test_the_camera_matrices_are_pybullets():
    car = CarState(3.0, -2.0, 0.7)
    camera = CameraSpec(width_px=200, height_px=66, pitch_down_rad=0.1, yaw_rad=0.05, lateral_offset_m=0.02)
    from services.simulator.world import camera_eye_and_axes

    eye, forward, up = camera_eye_and_axes(car, camera)
    theirs = np.array(pybullet.computeViewMatrix(eye.tolist(), (eye + forward).tolist(), up.tolist())).reshape(4, 4).T
    np.testing.assert_allclose(view_matrix(car, camera), theirs, atol=1e-5)
    theirs = (
        np.array(
            pybullet.computeProjectionMatrixFOV(
                math.degrees(vertical_fov_rad(camera)), 200 / 66, camera.near_m, camera.far_m
            )
        )
        .reshape(4, 4)
        .T
    )
    np.testing.assert_allclose(projection_matrix(camera), theirs, rtol=1e-5, atol=1e-6)


def _digest(image: np.ndarray) -> str:
    return hashlib.sha256(image.tobytes()).hexdigest()


def test_each_renderer_is_bitwise_deterministic(renderer):
    poses = parity_poses(CIRCUIT, count=4, seed=3)
    first = make_scene(CIRCUIT, WorldVariation(), renderer=renderer)
    second = make_scene(CIRCUIT, WorldVariation(), renderer=renderer)
    try:
        digests = [_digest(first.render(pose, CAMERA)) for pose in poses]
        assert [_digest(first.render(pose, CAMERA)) for pose in poses] == digests
        assert [_digest(second.render(pose, CAMERA)) for pose in poses] == digests
    finally:
        first.close()
        second.close()
    # And in another process (a fresh context / PyBullet client).
    code = textwrap.dedent(f"""
        import hashlib
        from circuits import load_circuit
        from protocol.episode_spec import CameraSpec, WorldVariation
        from services.simulator.parity import parity_poses
        from services.simulator.renderers import make_scene
        circuit = load_circuit("simple")
        scene = make_scene(circuit, WorldVariation(), renderer={renderer!r})
        for pose in parity_poses(circuit, count=4, seed=3):
            print(hashlib.sha256(scene.render(pose, CameraSpec(width_px=320, height_px=240)).tobytes()).hexdigest())
    """)
    child = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True)
    assert child.stdout.split() == digests


def test_a_scene_cache_draws_each_direction_of_a_circuit_from_its_own_scene(renderer):
    """A warm simulator's scene cache: a circuit driven forward after it was driven in reverse (and the other way
    round) is drawn, pixel for pixel, as a fresh simulator draws it. Both directions are the same road, but built
    from the centreline in opposite orders their triangles round differently at the edges: a few pixels a frame,
    enough to change a network's commands (two episodes of `drivebench paper` on warm stacks, issue 29)."""
    forward, reverse = load_circuit("simple"), load_circuit("simple", direction="reverse")
    warm = SceneCache()
    try:
        for name, circuit, after in (("forward", forward, reverse), ("reverse", reverse, forward)):
            poses = parity_poses(circuit, count=8, seed=5)
            fresh = make_scene(circuit, WorldVariation(), renderer=renderer)
            try:
                expected = [_digest(fresh.render(pose, CAMERA)) for pose in poses]
            finally:
                fresh.close()
            warm.get(after, renderer=renderer)  # the other direction's scene, as the previous episode left it
            scene = warm.get(circuit, renderer=renderer)
            assert [_digest(scene.render(pose, CAMERA)) for pose in poses] == expected, name
        # Each direction's scene is cached: an episode in either direction builds nothing.
        assert warm.get(forward, renderer=renderer) is warm.get(forward, renderer=renderer)
        assert warm.get(reverse, renderer=renderer) is not warm.get(forward, renderer=renderer)
    finally:
        warm.close()


@pytest.mark.parametrize("direction", ["forward", "reverse"])
def test_an_episode_started_along_the_circuit_moves_the_car_not_the_scene(renderer, direction):
    """start_m moves only the car's first pose: the episode draws from the scene a start at the line uses (the
    cache's entry, not a circuit rebuilt to begin elsewhere), so its first frame is that scene's frame there."""
    scenes = SceneCache()
    try:
        at_line = EpisodeSim(EpisodeSpec(renderer=renderer, direction=direction), scenes=scenes)
        along = EpisodeSim(EpisodeSpec(renderer=renderer, direction=direction, start_m=300.0), scenes=scenes)
        assert (along.car.x_m, along.car.y_m, along.car.yaw_rad) == along.circuit.centreline.pose_at(300.0)
        assert along.circuit.centreline.points_m.tobytes() == at_line.circuit.centreline.points_m.tobytes()
        assert along._scene is at_line._scene
        assert _digest(along.render()) == _digest(at_line._scene.render(along.car, EpisodeSpec().camera))
        assert along.progress_m == 0.0 and along.laps_completed == 0
        # One step straight ahead from 300 m: progress counts from there, not from the start line.
        step = along.step(speed_mps=5.0, yaw_rate_radps=0.0)
        assert along.progress_m == pytest.approx(0.25, abs=0.01) and step.lap == 0 and step.end is None
    finally:
        scenes.close()


# Measured by benchmarks/renderer_parity.py over every built-in circuit, world variation and camera preset
# (docs/guides/renderers.md):
# MAD <= 0.3 grey levels, SSIM >= 0.997, at most 0.05 % of pixels off by more than 8 levels (edge pixels where the two
# rasterisers round differently, and far line ends where the 5 mm gap to the road is below depth precision). The
# thresholds are 3-10x looser, so another Mesa or LLVM version may round differently without failing, while a real
# change (a colour, a lighting term, a pixel of camera offset: ~0.6 % of pixels, SSIM ~0.98) fails.
PARITY_MAD = 1.0
PARITY_SSIM = 0.99
PARITY_DIFFERING = 0.003


@pytest.mark.parametrize(
    "circuit_name, world",
    [
        ("simple", WorldVariation()),
        ("montreal", WorldVariation(line="white", walls=False)),
        ("many_curves", WorldVariation(road="white", lighting="no_sun")),
    ],
)
def test_gl_frames_match_pybullets(circuit_name, world):
    require_gl()
    circuit = load_circuit(circuit_name)
    reference = make_scene(circuit, world, renderer="pybullet")
    fast = make_scene(circuit, world, renderer="gl")
    try:
        for pose in parity_poses(circuit, count=3):
            a, b = reference.render(pose, CAMERA), fast.render(pose, CAMERA)
            assert mean_absolute_difference(a, b) < PARITY_MAD
            assert ssim(a, b) > PARITY_SSIM
            assert differing_fraction(a, b) < PARITY_DIFFERING
    finally:
        reference.close()
        fast.close()


def test_the_parity_measures_tell_a_shifted_frame_from_the_same_one():
    with make_scene(CIRCUIT, WorldVariation(), renderer="pybullet") as scene:
        pose = CarState(*CIRCUIT.start_pose())
        image = scene.render(pose, CAMERA)
        moved = scene.render(pose, CameraSpec(width_px=320, height_px=240, lateral_offset_m=0.01))
    assert mean_absolute_difference(image, image) == 0 and ssim(image, image) == pytest.approx(1.0)
    assert ssim(image, moved) < PARITY_SSIM or differing_fraction(image, moved) > PARITY_DIFFERING
    with pytest.raises(ValueError, match="one size"):
        ssim(image, image[:-1])


def _child(code: str, env: dict[str, str]) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)],
        capture_output=True,
        text=True,
        timeout=60,
        env={**os.environ, **env},
    )


def test_auto_falls_back_to_pybullet_with_the_reason_where_egl_is_missing():
    child = _child(
        """
        import json
        from circuits import load_circuit
        from protocol.episode_spec import EpisodeSpec
        from services.simulator.episode import EpisodeSim, SceneCache
        from services.simulator.renderers import RendererUnavailable, resolve_renderer, resolve_spec
        auto = resolve_renderer("auto")
        try:
            resolve_renderer("gl")
            gl = "accepted"
        except RendererUnavailable as error:
            gl = str(error)
        sim = EpisodeSim(EpisodeSpec(renderer="auto"), scenes=SceneCache())
        print(json.dumps({"auto": auto.name, "notice": auto.notice, "gl": gl,
                          "scene": type(sim._scene).__name__, "frame": list(sim.render().shape),
                          "spec": resolve_spec(EpisodeSpec(renderer="auto")).renderer}))
    """,
        NO_EGL,
    )
    assert child.returncode == 0, child.stderr
    result = json.loads(child.stdout)
    assert result["auto"] == "pybullet" and result["scene"] == "Scene" and result["frame"] == [240, 320, 3]
    assert result["spec"] == "pybullet"
    assert "renderer auto: using pybullet" in result["notice"] and "not loaded" in result["notice"]
    assert result["gl"].startswith("renderer gl: ") and "\n" not in result["gl"]
    assert "renderer auto: using pybullet" in child.stderr  # resolve_spec logged it


def test_auto_takes_gl_where_egl_works_and_a_bad_name_is_refused():
    require_gl()
    assert resolve_renderer("auto").name == "gl" and resolve_renderer("auto").notice is None
    assert resolve_spec(EpisodeSpec(renderer="auto")).renderer == "gl"
    assert resolve_renderer("pybullet").name == "pybullet"
    sim = EpisodeSim(EpisodeSpec(renderer="auto"), scenes=SceneCache())
    assert type(sim._scene).__name__ == "GLScene"
    with pytest.raises(ValueError, match="renderer must be one of"):
        resolve_renderer("vulkan")
    with pytest.raises(ValueError, match="renderer must be one of pybullet, gl, auto"):
        EpisodeSpec(renderer="vulkan")
    assert issubclass(RendererUnavailable, ValueError)


def test_llvmpipe_gets_one_thread_unless_the_user_chose():
    require_gl()
    code = """
        import os
        from services.simulator.gl_scene import gl_context
        gl_context()
        print(os.environ["LP_NUM_THREADS"])
    """
    env = {key: value for key, value in os.environ.items() if key != "LP_NUM_THREADS"}
    child = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True, timeout=60, env=env
    )
    assert child.stdout.strip() == "1", child.stderr
    assert _child(code, {"LP_NUM_THREADS": "2"}).stdout.strip() == "2"


def test_stacks_side_by_side_share_the_cores_for_rendering(tmp_path):
    cores = len(os.sched_getaffinity(0))
    assert render_threads_for(stacks=1) == min(8, cores)
    assert render_threads_for(stacks=cores) == 1
    assert render_threads_for(stacks=4 * cores) == 1  # never none
    matrix = parse_matrix("brains: [explicit]\ncircuits: [simple]\n")
    for workers in (1, 2, 3):
        runner = MatrixRunner(matrix, tmp_path, RunOptions(workers=workers))
        stack = runner.executor.make_stack(run_id="threads", run_dir=tmp_path / "threads")  # not started
        assert stack.render_threads == render_threads_for(stacks=workers)


@pytest.mark.integration
def test_a_stack_simulator_renders_with_its_threads_unless_the_user_chose(make_stack, monkeypatch):
    monkeypatch.delenv("LP_NUM_THREADS", raising=False)
    stack = make_stack(render_threads=2)
    assert environment_of(stack.child("simulator", "sim").process.pid)["LP_NUM_THREADS"] == "2"
    brain = next(child for child in stack.children if child.role == "brain")
    assert "LP_NUM_THREADS" not in environment_of(brain.process.pid)  # only the simulator renders
    monkeypatch.setenv("LP_NUM_THREADS", "3")
    chosen = make_stack(render_threads=2)
    assert environment_of(chosen.child("simulator", "sim").process.pid)["LP_NUM_THREADS"] == "3"


def test_a_matrix_file_names_its_renderer_and_the_command_line_overrides_it(monkeypatch):
    monkeypatch.delenv("DRIVEBENCH_RENDERER", raising=False)
    default = parse_matrix("brains: [explicit]\ncircuits: [simple]\n")
    assert {episode.spec.renderer for episode in default.episodes} == {"auto"}  # parity holds: gl where EGL works
    monkeypatch.setenv("DRIVEBENCH_RENDERER", "pybullet")
    assert parse_matrix("brains: [explicit]\ncircuits: [simple]\n").episodes[0].spec.renderer == "pybullet"
    text = "brains: [explicit]\ncircuits: [simple]\nrenderer: gl\n"
    matrix = parse_matrix(text)
    assert {episode.spec.renderer for episode in matrix.episodes} == {"gl"}
    assert {e.spec.renderer for e in with_renderer(matrix, lambda _: "pybullet").episodes} == {"pybullet"}
    with pytest.raises(MatrixError, match=r"^<matrix>:3: renderer must be one of pybullet, gl, auto, got 'vulkan'$"):
        parse_matrix(text.replace("gl", "vulkan"))


def drivebench(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "orchestrator.cli", *args],
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, **(env or {})},
    )


@pytest.mark.integration
def test_run_auto_without_egl_drives_with_pybullet_and_says_why(tmp_path):
    result = drivebench(
        "run", "--renderer", "auto", "--max-sim-seconds", "1", "--json", "--runs-dir", str(tmp_path), env=NO_EGL
    )
    assert result.returncode == 0, result.stderr
    assert json.loads(result.stdout)["spec"]["renderer"] == "pybullet"
    notices = [line for line in result.stderr.splitlines() if "renderer auto" in line]
    assert len(notices) == 1 and "using pybullet" in notices[0] and "not loaded" in notices[0]
    refused = drivebench("run", "--renderer", "gl", "--runs-dir", str(tmp_path), env=NO_EGL)
    assert refused.returncode == 2
    assert refused.stderr.strip().splitlines()[-1].startswith("drivebench: error: renderer gl: ")


@pytest.mark.integration
def test_run_with_gl_records_the_renderer_in_the_score_and_the_recording(tmp_path):
    require_gl()
    recording = tmp_path / "gl.mcap"
    result = drivebench(
        "run",
        "--renderer",
        "auto",
        "--max-sim-seconds",
        "2",
        "--json",
        "--runs-dir",
        str(tmp_path),
        "--record",
        str(recording),
    )
    assert result.returncode == 0, result.stderr
    score = json.loads(result.stdout)
    assert score["spec"]["renderer"] == "gl" and score["metrics"]["steps"] >= 39
    with recording.open("rb") as stream:
        metadata = {record.name: record.metadata for record in make_reader(stream).iter_metadata()}
    assert json.loads(metadata["episode:0"]["spec"])["renderer"] == "gl"


@pytest.mark.integration
def test_the_simulator_resolves_auto_itself_for_an_attached_driver(tmp_path):
    """A driver attached to a running stack sends "auto" as asked; the simulator process resolves it and the score
    names what it chose (the stack's processes share this machine's EGL, so gl here)."""
    require_gl()
    from orchestrator.stack.launcher import BrainLaunch, LocalStack

    with LocalStack(run_id="glauto", run_dir=tmp_path, brains=[BrainLaunch("explicit")]) as stack:
        score = stack.run_episode(EpisodeSpec(renderer="auto", max_sim_seconds=1.0))
        reference = stack.run_episode(EpisodeSpec(renderer="pybullet", max_sim_seconds=1.0))  # same simulator
    assert score.spec.renderer == "gl" and score.metrics.steps >= 19
    assert reference.spec.renderer == "pybullet" and reference.metrics.steps == score.metrics.steps


def test_dataset_collect_puts_its_renderer_in_every_spec(monkeypatch):
    import argparse

    from orchestrator.collect import CollectError, collection_specs

    args = argparse.Namespace(
        circuits="simple,montreal",
        direction="forward",
        laps=1,
        max_sim_seconds=100.0,
        camera=(320, 240),
        recovery_noise=0.0,
        brain="explicit",
        variation=[],
        randomise=False,
        renderer="pybullet",
    )
    assert {spec.renderer for spec in collection_specs(args)} == {"pybullet"}
    child = _child(
        """
        import argparse
        from orchestrator.collect import collection_specs
        args = argparse.Namespace(circuits="simple", direction="forward", laps=1, max_sim_seconds=100.0,
                                  camera=(320, 240), recovery_noise=0.0, brain="explicit", variation=[],
                                  randomise=False, renderer="auto")
        print(collection_specs(args)[0].renderer)
    """,
        NO_EGL,
    )
    assert child.stdout.strip() == "pybullet" and "renderer auto: using pybullet" in child.stderr
    monkeypatch.setenv("DRIVEBENCH_RENDERER", "vulkan")
    with pytest.raises(CollectError, match="DRIVEBENCH_RENDERER must be one of"):
        collection_specs(argparse.Namespace(**{**vars(args), "renderer": None}))


@pytest.mark.integration
def test_a_simulator_without_egl_refuses_gl_in_one_line_and_falls_back_for_auto(tmp_path, monkeypatch):
    """The simulator's own check, for a driver that did not resolve the renderer (an attached one): gl is refused
    with the reason, auto runs with pybullet and the score says so."""
    from orchestrator.stack.failures import StackError
    from orchestrator.stack.launcher import BrainLaunch, LocalStack

    monkeypatch.setenv("GLCONTEXT_LINUX_LIBEGL", NO_EGL["GLCONTEXT_LINUX_LIBEGL"])  # the stack's processes inherit it
    with LocalStack(run_id="noegl", run_dir=tmp_path, brains=[BrainLaunch("explicit")]) as stack:
        with pytest.raises(StackError, match=r"renderer gl: no EGL OpenGL 3.3 context: .* not loaded") as refused:
            stack.run_episode(EpisodeSpec(renderer="gl", max_sim_seconds=0.5))
        score = stack.run_episode(EpisodeSpec(renderer="auto", max_sim_seconds=0.5))
    assert "\n" not in str(refused.value)
    assert score.spec.renderer == "pybullet" and score.metrics.steps == 10
    notices = [
        line
        for line in (tmp_path / "logs" / "simulator.log").read_text().splitlines()
        if "renderer auto: using pybullet" in line
    ]
    assert len(notices) == 1 and "not loaded" in notices[0]
