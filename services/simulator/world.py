"""The scene description both renderers draw: meshes, colours, lighting, sky and the camera model.

Pure (NumPy only): built from a circuit and a :class:`WorldVariation`, it holds every triangle of the road, centre
line, walls and grass with its colour, in the chunks the PyBullet backend culls by, plus the lighting coefficients
and sky colour. :class:`services.simulator.scene.Scene` (PyBullet TinyRenderer, the reference) and
:class:`services.simulator.gl_scene.GLScene` (moderngl on EGL) both consume it, so a variation means the same on
both; neither keeps its own copy of the world.

The camera model (mount, field of view, clip planes) is :class:`protocol.episode_spec.CameraSpec`;
:func:`camera_eye_and_axes`, :func:`view_matrix` and :func:`projection_matrix` turn it into OpenGL-convention
matrices (the same ones ``pybullet.computeViewMatrix`` / ``computeProjectionMatrixFOV`` give: a test holds them to it).

Frames: world x/y on the ground, z up; the road surface is z = 0.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from circuits import Circuit
from protocol.episode_spec import CameraSpec, WorldVariation
from services.simulator.car import CarState
from services.simulator.looks import ASPHALT_TILE_M, EDGE_LINE_GREY, WALL_GREY, GazeboLighting, gazebo_lighting

MAX_TRIANGLES_PER_CHUNK = 200
LINE_HEIGHT_M = 0.005  # the centre line floats above the road so that it wins the depth test
GRASS_HEIGHT_M = -0.02  # the grass lies below the road for the same reason
GRASS_MARGIN_M = 60.0  # the grass extends this far beyond the track's bounding box
GRASS_TILE_M = 25.0  # grass tile side: one culling chunk (2 triangles) each
MAX_GRASS_TILES_PER_SIDE = 24

# RGBA in 0..1. Rendered values are about 0.89-1.0 times these (ambient 0.9 + a little diffuse).
RGBA = tuple[float, float, float, float]
ROAD_COLOURS: dict[str, RGBA] = {"grey": (0.35, 0.35, 0.35, 1.0), "white": (0.8, 0.8, 0.8, 1.0)}
LINE_COLOURS: dict[str, RGBA] = {"red": (1.0, 0.0, 0.0, 1.0), "white": (1.0, 1.0, 1.0, 1.0)}
WALL_COLOUR: RGBA = (0.6, 0.6, 0.6, 1.0)  # light grey: unsaturated, R < 170 once rendered
GRASS_COLOUR: RGBA = (0.42, 0.55, 0.38, 1.0)  # muted green: HSV S ~ 79 < 110, so the explicit brain ignores it
SKY_RGB = (180, 192, 210)  # pale blue-grey: HSV S ~ 37, R >= 170 (the "sun" sky)

# Lighting presets: "sun" is flat and bright (Gazebo-like); "no_sun" is Behavior Metrics' darker *_no_sun worlds.
LIGHTING = {
    "sun": {"lightAmbientCoeff": 0.9, "lightDiffuseCoeff": 0.2, "lightSpecularCoeff": 0.0},
    "no_sun": {"lightAmbientCoeff": 0.5, "lightDiffuseCoeff": 0.1, "lightSpecularCoeff": 0.0},
}
SKY_RGB_BY_LIGHTING = {"sun": (180, 192, 210), "no_sun": (96, 104, 118)}
# PyBullet's TinyRenderer lights a z-up world from this direction (towards the light) unless told otherwise; the
# GL backend uses the same one so that shading matches.
DEFAULT_LIGHT_TOWARDS = (-50.0, 30.0, 100.0)

LineColour = Literal["red", "white", "none"]
RoadColour = Literal["grey", "white"]
MeshKind = Literal["line", "edge", "wall", "road", "grass"]
# How the gazebo look shades a mesh: flat colour, a texture (asphalt, grass), or flat with a specular term (wall).
Material = Literal["flat", "asphalt", "grass", "wall"]


@dataclass(frozen=True)
class Mesh:
    """One chunk of the world: at most :data:`MAX_TRIANGLES_PER_CHUNK` triangles of one colour.

    vertices_m: (N, 3) world coordinates; indices: (3T,) int32, anticlockwise seen from the side that faces the
    camera (walls carry both windings). centre_m, radius_m: a bounding sphere, for culling.
    material: how the gazebo look shades it (the flat look draws every mesh in its flat colour).
    texcoords_m: (N, 2) texture coordinates in metres, or None: (arc length, lateral offset) on the road, world
        (x, y) on the grass. normals: (N, 3) smooth unit normals of one side, or None (the triangles' own normals);
        a renderer turns them to the side each triangle faces.
    """

    kind: MeshKind
    vertices_m: np.ndarray
    indices: np.ndarray
    rgba: tuple[float, float, float, float]
    centre_m: np.ndarray
    radius_m: float
    material: Material = "flat"
    texcoords_m: np.ndarray | None = None
    normals: np.ndarray | None = None

    @property
    def triangles(self) -> int:
        return len(self.indices) // 3


@dataclass(frozen=True)
class SceneDescription:
    """Everything a renderer draws for one circuit and world variation.

    meshes: in drawing order (near occluders first: line, walls, road, grass).
    ambient, diffuse: lighting coefficients (TinyRenderer's ``lightAmbientCoeff`` / ``lightDiffuseCoeff``);
        a surface's colour is ``rgb * (ambient + diffuse * max(0, n . l))`` with ``l`` towards the light.
    light_towards: unit vector towards the light, world frame.
    sky_rgb: uint8 colour of every pixel nothing covers (the flat look).
    walls: whether there are walls; wall_height_m, road_half_width_m: for grass occlusion.
    look: "flat" or "gazebo"; gazebo: the gazebo look's light (None in the flat look).
    """

    circuit: Circuit
    meshes: tuple[Mesh, ...]
    lighting: str
    ambient: float
    diffuse: float
    light_towards: tuple[float, float, float]
    sky_rgb: tuple[int, int, int]
    walls: bool
    look: str = "flat"
    gazebo: GazeboLighting | None = None

    @property
    def triangle_count(self) -> int:
        return sum(mesh.triangles for mesh in self.meshes)


def describe_world(circuit: Circuit, world: WorldVariation = WorldVariation()) -> SceneDescription:
    """The scene of ``circuit`` with a world variation (line colour, road colour, walls, lighting, look)."""
    if world.look == "gazebo":
        return describe_gazebo(circuit, world)
    return describe(circuit, line_colour=world.line, road_colour=world.road, walls=world.walls, lighting=world.lighting)


def describe_gazebo(circuit: Circuit, world: WorldVariation) -> SceneDescription:
    """The gazebo look of ``circuit``: the flat look's meshes with materials, texture coordinates along the road and
    smooth wall normals, plus light-grey edge lines, lit as Behavior Metrics' Gazebo world of that circuit
    (:mod:`services.simulator.looks`)."""
    flat = describe(circuit, line_colour=world.line, road_colour=world.road, walls=world.walls, lighting=world.lighting)
    centreline = circuit.centreline
    points, normals = centreline.points_m, centreline.left_normals()
    half, width = circuit.road_half_width_m, circuit.line_width_m
    # An integer number of asphalt tiles round the loop, so that the texture meets itself at the start line.
    tiles = max(1, round(centreline.length_m / ASPHALT_TILE_M))
    s_m = np.append(centreline.s_m, centreline.length_m) * (tiles * ASPHALT_TILE_M / centreline.length_m)
    grey: RGBA = (WALL_GREY, WALL_GREY, WALL_GREY, 1.0)
    edge: RGBA = (EDGE_LINE_GREY, EDGE_LINE_GREY, EDGE_LINE_GREY, 1.0)
    meshes: list[Mesh] = []
    if world.line != "none":
        meshes += _strip(points, normals, width / 2, LINE_HEIGHT_M, LINE_COLOURS[world.line], "line")
    for side in (1.0, -1.0):  # edge lines just inside the road edge, clear of the wall's foot
        edge_centre = points + side * (half - 1.5 * width) * normals
        meshes += _strip(edge_centre, normals, width / 2, LINE_HEIGHT_M, edge, "edge")
    if world.walls:
        for side in (1.0, -1.0):
            meshes += _wall(points + side * half * normals, circuit.wall_height_m, rgba=grey, normals=normals)
    if world.road == "grey":
        meshes += _strip(points, normals, half, 0.0, ROAD_COLOURS["grey"], "road", arc_m=s_m)
    else:
        meshes += _strip(points, normals, half, 0.0, ROAD_COLOURS[world.road], "road")
    meshes += [dataclasses.replace(m, material="grass", texcoords_m=m.vertices_m[:, :2].copy()) for m in _grass(points)]
    light = gazebo_lighting(circuit.name, world.lighting)
    return dataclasses.replace(
        flat,
        meshes=tuple(meshes),
        ambient=light.ambient,
        diffuse=light.diffuse,
        light_towards=light.light_towards,
        look="gazebo",
        gazebo=light,
    )


def describe(
    circuit: Circuit, *, line_colour: str = "red", road_colour: str = "grey", walls: bool = True, lighting: str = "sun"
) -> SceneDescription:
    """The scene description; ValueError names a bad option."""
    if lighting not in LIGHTING:
        raise ValueError(f"lighting must be 'sun' or 'no_sun', got {lighting!r}")
    if line_colour not in ("red", "white", "none"):
        raise ValueError(f"line_colour must be 'red', 'white' or 'none', got {line_colour!r}")
    if road_colour not in ROAD_COLOURS:
        raise ValueError(f"road_colour must be 'grey' or 'white', got {road_colour!r}")
    centreline = circuit.centreline
    points = centreline.points_m
    normals = centreline.left_normals()
    half_width = circuit.road_half_width_m
    meshes: list[Mesh] = []
    # Drawing order matters to TinyRenderer's cost (a pixel that fails the depth test skips shading): near
    # occluders first, the grass last.
    if line_colour != "none":
        meshes += _strip(points, normals, circuit.line_width_m / 2, LINE_HEIGHT_M, LINE_COLOURS[line_colour], "line")
    if walls:
        for side in (1.0, -1.0):
            meshes += _wall(points + side * half_width * normals, circuit.wall_height_m)
    meshes += _strip(points, normals, half_width, 0.0, ROAD_COLOURS[road_colour], "road")
    meshes += _grass(points)
    light = np.array(DEFAULT_LIGHT_TOWARDS) / np.linalg.norm(DEFAULT_LIGHT_TOWARDS)
    coefficients = LIGHTING[lighting]
    return SceneDescription(
        circuit=circuit,
        meshes=tuple(meshes),
        lighting=lighting,
        ambient=coefficients["lightAmbientCoeff"],
        diffuse=coefficients["lightDiffuseCoeff"],
        light_towards=(float(light[0]), float(light[1]), float(light[2])),
        sky_rgb=SKY_RGB_BY_LIGHTING[lighting],
        walls=walls,
    )


def _mesh(kind: MeshKind, vertices: np.ndarray, indices: list[int], rgba: RGBA) -> Mesh:
    assert len(indices) // 3 <= MAX_TRIANGLES_PER_CHUNK, len(indices)
    centre = vertices.mean(axis=0)
    radius = float(np.max(np.linalg.norm(vertices - centre, axis=1)))
    return Mesh(
        kind=kind,
        vertices_m=vertices,
        indices=np.asarray(indices, dtype=np.int32),
        rgba=rgba,
        centre_m=centre,
        radius_m=radius,
    )


def _grass(points: np.ndarray) -> list[Mesh]:
    low = points.min(axis=0) - GRASS_MARGIN_M
    high = points.max(axis=0) + GRASS_MARGIN_M
    # Fixed-size tiles on a small circuit; bigger ones on a real-scale track, so that the number of chunks (a
    # per-frame cost in PyBullet even when hidden) stays bounded.
    tile = max(GRASS_TILE_M, float(np.max(high - low)) / MAX_GRASS_TILES_PER_SIDE)
    meshes = []
    for x0 in np.arange(low[0], high[0], tile):
        for y0 in np.arange(low[1], high[1], tile):
            x1, y1 = x0 + tile, y0 + tile
            vertices = np.array(
                [[x0, y0, GRASS_HEIGHT_M], [x1, y0, GRASS_HEIGHT_M], [x1, y1, GRASS_HEIGHT_M], [x0, y1, GRASS_HEIGHT_M]]
            )
            meshes.append(_mesh("grass", vertices, [0, 1, 2, 0, 2, 3], GRASS_COLOUR))
    return meshes


def _strip(
    points: np.ndarray,
    normals: np.ndarray,
    half_width_m: float,
    z_m: float,
    rgba: RGBA,
    kind: MeshKind,
    *,
    arc_m: np.ndarray | None = None,
) -> list[Mesh]:
    """A closed ribbon of width 2*half_width_m along the points, facing up, split into chunks. With ``arc_m`` (the
    arc length of each point, plus the loop's length at the end) it is asphalt, textured along its length."""
    left = points + half_width_m * normals
    right = points - half_width_m * normals
    segments_per_chunk = MAX_TRIANGLES_PER_CHUNK // 2
    count = len(points)
    meshes = []
    for start in range(0, count, segments_per_chunk):
        ids = np.arange(start, min(start + segments_per_chunk, count) + 1) % count  # closes the loop at the end
        n = len(ids)
        vertices = np.zeros((2 * n, 3))
        vertices[:n, :2] = left[ids]
        vertices[n:, :2] = right[ids]
        vertices[:, 2] = z_m
        indices = []
        for k in range(n - 1):
            l0, l1, r0, r1 = k, k + 1, n + k, n + k + 1
            # Anticlockwise seen from above (normal up) whichever way the track turns: TinyRenderer culls back
            # faces. Driving direction d and left normal make (r0, r1, l1) anticlockwise.
            indices += [r0, r1, l1, r0, l1, l0]
        mesh = _mesh(kind, vertices, indices, rgba)
        if arc_m is not None:
            texcoords = np.empty((2 * n, 2))
            texcoords[:, 0] = np.tile(arc_m[np.arange(start, start + n)], 2)  # the closing vertex: the loop's length
            texcoords[:n, 1], texcoords[n:, 1] = half_width_m, -half_width_m
            mesh = dataclasses.replace(mesh, material="asphalt", texcoords_m=texcoords)
        meshes.append(mesh)
    return meshes


def _wall(
    base: np.ndarray, height_m: float, *, rgba: RGBA = WALL_COLOUR, normals: np.ndarray | None = None
) -> list[Mesh]:
    """A closed vertical wall along the points, both windings (visible from either side), split into chunks. With
    ``normals`` (left normals at the points) it is the gazebo look's wall, smoothly shaded."""
    segments_per_chunk = MAX_TRIANGLES_PER_CHUNK // 4
    count = len(base)
    meshes = []
    for start in range(0, count, segments_per_chunk):
        ids = np.arange(start, min(start + segments_per_chunk, count) + 1) % count
        n = len(ids)
        vertices = np.zeros((2 * n, 3))
        vertices[:n, :2] = base[ids]
        vertices[n:, :2] = base[ids]
        vertices[n:, 2] = height_m
        indices = []
        for k in range(n - 1):
            b0, b1, t0, t1 = k, k + 1, n + k, n + k + 1
            indices += [b0, b1, t1, b0, t1, t0]  # one side
            indices += [b0, t1, b1, b0, t0, t1]  # the other
        mesh = _mesh("wall", vertices, indices, rgba)
        if normals is not None:
            smooth = np.zeros((2 * n, 3))
            smooth[:, :2] = np.tile(normals[ids], (2, 1))
            mesh = dataclasses.replace(mesh, material="wall", normals=smooth)
        meshes.append(mesh)
    return meshes


# -- the camera model ------------------------------------------------------------------------------------------------


def vertical_fov_rad(camera: CameraSpec) -> float:
    """The vertical field of view that goes with ``camera.hfov_rad`` at the camera's aspect ratio (square pixels)."""
    return 2.0 * math.atan(camera.height_px / camera.width_px * math.tan(camera.hfov_rad / 2.0))


def camera_eye_and_axes(car: CarState, camera: CameraSpec) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World position of the camera and its forward and up unit vectors, for a car pose.

    The mount (forward_m, lateral_offset_m, height_m) is in the car frame; the camera looks along the car's heading
    turned by ``camera.yaw_rad`` (anticlockwise) and tilted down by ``camera.pitch_down_rad``.
    """
    cos_yaw, sin_yaw = math.cos(car.yaw_rad), math.sin(car.yaw_rad)
    eye = np.array(
        [
            car.x_m + cos_yaw * camera.forward_m - sin_yaw * camera.lateral_offset_m,
            car.y_m + sin_yaw * camera.forward_m + cos_yaw * camera.lateral_offset_m,
            camera.height_m,
        ]
    )
    cos_pitch, sin_pitch = math.cos(camera.pitch_down_rad), math.sin(camera.pitch_down_rad)
    cos_yaw, sin_yaw = math.cos(car.yaw_rad + camera.yaw_rad), math.sin(car.yaw_rad + camera.yaw_rad)
    forward = np.array([cos_pitch * cos_yaw, cos_pitch * sin_yaw, -sin_pitch])
    up = np.array([sin_pitch * cos_yaw, sin_pitch * sin_yaw, cos_pitch])
    return eye, forward, up


def view_matrix(car: CarState, camera: CameraSpec) -> np.ndarray:
    """camera_from_world, 4x4 (OpenGL convention: the camera looks along -z, y up), as gluLookAt builds it."""
    eye, forward, up = camera_eye_and_axes(car, camera)
    # forward and up are orthonormal by construction, so side = forward x up is a unit vector and up is already
    # gluLookAt's recomputed up; written out, since np.cross costs more than the rest of a small frame's set-up.
    side = np.array(
        [
            forward[1] * up[2] - forward[2] * up[1],
            forward[2] * up[0] - forward[0] * up[2],
            forward[0] * up[1] - forward[1] * up[0],
        ]
    )
    view = np.eye(4)
    view[0, :3], view[1, :3], view[2, :3] = side, up, -forward
    view[:3, 3] = -view[:3, :3] @ eye
    return view


def projection_matrix(camera: CameraSpec) -> np.ndarray:
    """clip_from_camera, 4x4, as gluPerspective builds it from the vertical field of view and the clip planes."""
    f = 1.0 / math.tan(vertical_fov_rad(camera) / 2.0)
    aspect = camera.width_px / camera.height_px
    near, far = camera.near_m, camera.far_m
    projection = np.zeros((4, 4))
    projection[0, 0] = f / aspect
    projection[1, 1] = f
    projection[2, 2] = (far + near) / (near - far)
    projection[2, 3] = 2.0 * far * near / (near - far)
    projection[3, 2] = -1.0
    return projection


def chunk_runs(draw: np.ndarray, *, first: np.ndarray, count: np.ndarray) -> list[tuple[int, int]]:
    """(first vertex, vertex count) of each run of consecutive chunks where ``draw`` is set: one draw call each.

    first, count: each chunk's first vertex and vertex count in the vertex buffer (chunks stored consecutively)."""
    if not draw.any():
        return []
    edges = np.diff(np.concatenate([[False], draw, [False]]).astype(np.int8))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    firsts = first[starts]
    lasts = first[ends - 1] + count[ends - 1]
    return list(zip(firsts.tolist(), (lasts - firsts).tolist()))
