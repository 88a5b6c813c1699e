"""The rendered world of one circuit: road, centre line, walls, grass and sky, seen by the car's front camera.

PyBullet in ``DIRECT`` mode with the CPU ``ER_TINY_RENDERER`` (no GL, deterministic pixels); see
``reference/simulator.md`` for the measurements behind the choices here:

* Every mesh is split into chunks of at most :data:`MAX_TRIANGLES_PER_CHUNK` triangles (about 25 m of track). Before
  each frame, chunks whose bounding sphere lies entirely beyond the camera's far plane plus a margin get alpha 0,
  which TinyRenderer skips, so the frame cost does not grow with the track length. Such chunks could not have
  produced a pixel anyway (everything beyond the far plane is clipped), so culling never changes the image.
* The grass is most of a frame's fill cost (big triangles under the road). While the eye is between the walls and
  below their top, nothing of it can be seen (sight lines to it cross a wall or the road), so it is hidden too.
  Bodies are created near occluders first (line, walls, road, grass), since TinyRenderer draws them in that order
  and a pixel that fails the depth test skips shading.
* Flat, Gazebo-like lighting (ambient 0.9, diffuse 0.2, no specular); the sky is painted with NumPy over the pixels
  the renderer left empty (depth buffer ~1).
* Colours are chosen for the explicit brain's saturation mask (HSV S >= 110, V >= 15): only the red centre line
  passes; road, walls, grass and sky are (nearly) unsaturated. The walls are darker than the sky in the red channel
  (R < 170 against R >= 170), as in Behavior Metrics' Gazebo worlds whose speed rule tells wall from sky that way.

Frames: world x/y on the ground, z up; the road surface is z = 0.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
import pybullet

from circuits import Circuit
from protocol.messages import CameraSpec, WorldVariation
from services.simulator.car import CarState

MAX_TRIANGLES_PER_CHUNK = 200
LINE_HEIGHT_M = 0.005  # the centre line floats above the road so that it wins the depth test
GRASS_HEIGHT_M = -0.02  # the grass lies below the road for the same reason
GRASS_MARGIN_M = 60.0  # the grass extends this far beyond the track's bounding box
GRASS_TILE_M = 25.0  # grass tile side: one culling chunk (2 triangles) each
MAX_GRASS_TILES_PER_SIDE = 24
_OCCLUSION_MARGIN_M = 0.02  # the eye must be this far inside the walls for them to hide the grass
SKY_DEPTH = 0.9999  # depth-buffer values at or above this are background (nothing rendered): paint sky there

# RGBA in 0..1. Rendered values are about 0.89-1.0 times these (ambient 0.9 + a little diffuse).
ROAD_COLOURS = {"grey": (0.35, 0.35, 0.35, 1.0), "white": (0.8, 0.8, 0.8, 1.0)}
LINE_COLOURS = {"red": (1.0, 0.0, 0.0, 1.0), "white": (1.0, 1.0, 1.0, 1.0)}
WALL_COLOUR = (0.6, 0.6, 0.6, 1.0)  # light grey: unsaturated, R < 170 once rendered
GRASS_COLOUR = (0.42, 0.55, 0.38, 1.0)  # muted green: HSV S ~ 79 < 110, so the explicit brain ignores it
SKY_RGB = (180, 192, 210)  # pale blue-grey: HSV S ~ 37, R >= 170 (the "sun" sky)

# Lighting presets: "sun" is flat and bright (Gazebo-like); "no_sun" is Behavior Metrics' darker *_no_sun worlds.
LIGHTING = {
    "sun": {"lightAmbientCoeff": 0.9, "lightDiffuseCoeff": 0.2, "lightSpecularCoeff": 0.0},
    "no_sun": {"lightAmbientCoeff": 0.5, "lightDiffuseCoeff": 0.1, "lightSpecularCoeff": 0.0},
}
SKY_RGB_BY_LIGHTING = {"sun": (180, 192, 210), "no_sun": (96, 104, 118)}

LineColour = Literal["red", "white", "none"]
RoadColour = Literal["grey", "white"]


@dataclass
class _Chunk:
    """One PyBullet body holding a piece of a mesh, with our own bounding sphere (getAABB is empty for visual-only
    bodies)."""

    body_id: int
    rgba: tuple[float, float, float, float]
    centre_m: np.ndarray  # (3,)
    radius_m: float
    triangles: int
    is_grass: bool = False
    hidden: bool = False


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


class Scene:
    """A PyBullet ``DIRECT`` world holding one circuit, rendered from the car's camera.

    circuit: the circuit to build (road of the circuit's width, centre line, walls on the road edges).
    line_colour: ``"red"`` (Behavior Metrics' default), ``"white"`` (the white-line variant) or ``"none"``.
    road_colour: ``"grey"`` or ``"white"`` (Behavior Metrics' white-road variant, 0.8 grey).
    walls: ``wall_height_m`` walls on both road edges (False: the no-wall variants).
    lighting: ``"sun"`` or ``"no_sun"`` (darker, as Behavior Metrics' *_no_sun worlds).
    cull_margin_m: chunks farther than ``camera.far_m + cull_margin_m`` from the camera are hidden before each frame;
        ``None`` disables culling (same pixels, slower).

    Several scenes may live in one process: each owns its own PyBullet client. Close it (or use ``with``).
    """

    def __init__(
        self,
        circuit: Circuit,
        *,
        line_colour: LineColour = "red",
        road_colour: RoadColour = "grey",
        walls: bool = True,
        lighting: str = "sun",
        cull_margin_m: float | None = 5.0,
    ):
        if lighting not in LIGHTING:
            raise ValueError(f"lighting must be 'sun' or 'no_sun', got {lighting!r}")
        self._lighting = LIGHTING[lighting]
        self._sky_rgb = SKY_RGB_BY_LIGHTING[lighting]
        if line_colour not in ("red", "white", "none"):
            raise ValueError(f"line_colour must be 'red', 'white' or 'none', got {line_colour!r}")
        if road_colour not in ROAD_COLOURS:
            raise ValueError(f"road_colour must be 'grey' or 'white', got {road_colour!r}")
        if cull_margin_m is not None and cull_margin_m < 0:
            raise ValueError(f"cull_margin_m must be >= 0 or None, got {cull_margin_m}")
        self.circuit = circuit
        self.cull_margin_m = cull_margin_m
        self._client: int | None = pybullet.connect(pybullet.DIRECT)
        if self._client < 0:
            raise RuntimeError("could not start a PyBullet DIRECT client")
        self._chunks: list[_Chunk] = []
        try:
            self._build(line_colour=line_colour, road_colour=road_colour, walls=walls)
        except BaseException:
            self.close()
            raise
        self._centres = np.stack([chunk.centre_m for chunk in self._chunks])
        self._radii = np.array([chunk.radius_m for chunk in self._chunks])
        self._is_grass = np.array([chunk.is_grass for chunk in self._chunks])
        self._hidden = np.zeros(len(self._chunks), dtype=bool)
        self._walls = walls

    @classmethod
    def for_world(cls, circuit: Circuit, world: WorldVariation) -> Scene:
        """The scene of ``circuit`` with a world variation (line, road, walls, lighting)."""
        return cls(circuit, line_colour=world.line, road_colour=world.road, walls=world.walls,
                   lighting=world.lighting)

    # -- building ---------------------------------------------------------------------------------------------------

    def _build(self, *, line_colour: str, road_colour: str, walls: bool) -> None:
        centreline = self.circuit.centreline
        points = centreline.points_m
        normals = centreline.left_normals()
        half_width = self.circuit.road_half_width_m
        # TinyRenderer draws bodies in creation order with a per-pixel depth test: near occluders first (line,
        # walls, road), the grass last, so that hidden pixels fail the depth test early and skip shading.
        if line_colour != "none":
            line_half_width = self.circuit.line_width_m / 2
            self._add_strip(points, normals, line_half_width, LINE_HEIGHT_M, LINE_COLOURS[line_colour])
        if walls:
            for side in (1.0, -1.0):
                self._add_wall(points + side * half_width * normals, self.circuit.wall_height_m)
        self._add_strip(points, normals, half_width, 0.0, ROAD_COLOURS[road_colour])
        self._add_grass(points)

    def _add_grass(self, points: np.ndarray) -> None:
        low = points.min(axis=0) - GRASS_MARGIN_M
        high = points.max(axis=0) + GRASS_MARGIN_M
        # Fixed-size tiles on a small circuit; bigger ones on a real-scale track, so that the number of bodies (a
        # per-frame cost even when hidden) stays bounded.
        tile = max(GRASS_TILE_M, float(np.max(high - low)) / MAX_GRASS_TILES_PER_SIDE)
        xs = np.arange(low[0], high[0], tile)
        ys = np.arange(low[1], high[1], tile)
        for x0 in xs:
            for y0 in ys:
                x1, y1 = x0 + tile, y0 + tile
                vertices = np.array([[x0, y0, 0.0], [x1, y0, 0.0], [x1, y1, 0.0], [x0, y1, 0.0]])
                vertices[:, 2] = GRASS_HEIGHT_M
                self._add_chunk(vertices, [0, 1, 2, 0, 2, 3], GRASS_COLOUR, is_grass=True)

    def _add_strip(
        self, points: np.ndarray, normals: np.ndarray, half_width_m: float, z_m: float, rgba: tuple[float, ...]
    ) -> None:
        """A closed ribbon of width 2*half_width_m along the points, facing up, split into chunks."""
        left = points + half_width_m * normals
        right = points - half_width_m * normals
        segments_per_chunk = MAX_TRIANGLES_PER_CHUNK // 2
        count = len(points)
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
                # Anticlockwise seen from above (normal up) whichever way the track turns: TinyRenderer culls
                # back faces. Driving direction d and left normal make (r0, r1, l1) anticlockwise.
                indices += [r0, r1, l1, r0, l1, l0]
            self._add_chunk(vertices, indices, rgba)

    def _add_wall(self, base: np.ndarray, height_m: float) -> None:
        """A closed vertical wall along the points, both windings (visible from either side), split into chunks."""
        segments_per_chunk = MAX_TRIANGLES_PER_CHUNK // 4
        count = len(base)
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
            self._add_chunk(vertices, indices, WALL_COLOUR)

    def _add_chunk(
        self, vertices: np.ndarray, indices: list[int], rgba: tuple[float, ...], *, is_grass: bool = False
    ) -> None:
        triangles = len(indices) // 3
        assert triangles <= MAX_TRIANGLES_PER_CHUNK, triangles
        shape = pybullet.createVisualShape(
            pybullet.GEOM_MESH,
            vertices=vertices.tolist(),
            indices=indices,
            rgbaColor=list(rgba),
            specularColor=[0.0, 0.0, 0.0],
            physicsClientId=self._client,
        )
        body = pybullet.createMultiBody(baseMass=0, baseVisualShapeIndex=shape, physicsClientId=self._client)
        centre = vertices.mean(axis=0)
        radius = float(np.max(np.linalg.norm(vertices - centre, axis=1)))
        self._chunks.append(_Chunk(body, tuple(rgba), centre, radius, triangles, is_grass))

    # -- rendering --------------------------------------------------------------------------------------------------

    @property
    def triangle_count(self) -> int:
        """Triangles in the whole scene (all chunks)."""
        return sum(chunk.triangles for chunk in self._chunks)

    @property
    def chunk_count(self) -> int:
        return len(self._chunks)

    @property
    def visible_chunk_count(self) -> int:
        """Chunks drawn in the last frame (all of them when culling is off)."""
        return sum(not chunk.hidden for chunk in self._chunks)

    def _grass_occluded(self, eye: np.ndarray) -> bool:
        """True when the walls hide all the grass: the eye is between the walls and below their top.

        A sight line from there to any grass point outside the road crosses the wall curtain below its top, and the
        grass under the road lies below the road surface.
        """
        if not self._walls or eye[2] >= self.circuit.wall_height_m - _OCCLUSION_MARGIN_M:
            return False
        lateral = self.circuit.centreline.project(float(eye[0]), float(eye[1])).lateral_m
        return abs(lateral) < self.circuit.road_half_width_m - _OCCLUSION_MARGIN_M

    def _cull(self, eye: np.ndarray, far_m: float) -> None:
        if self.cull_margin_m is None:
            return
        gap = np.linalg.norm(self._centres - eye, axis=1) - self._radii
        hide = gap > far_m + self.cull_margin_m
        if self._grass_occluded(eye):
            # The grass is most of the fill cost of a frame (big triangles under the road); skip it when unseen.
            hide |= self._is_grass
        # Touch only the chunks whose visibility changed: a long track has thousands, and most stay as they were.
        for index in np.flatnonzero(hide != self._hidden).tolist():
            chunk = self._chunks[index]
            hidden = bool(hide[index])
            # changeVisualShape replaces the colour: restore the stored one when showing the chunk again.
            rgba = (*chunk.rgba[:3], 0.0) if hidden else chunk.rgba
            pybullet.changeVisualShape(chunk.body_id, -1, rgbaColor=list(rgba), physicsClientId=self._client)
            chunk.hidden = hidden
        self._hidden = hide

    def render(self, car: CarState, camera: CameraSpec) -> np.ndarray:
        """The camera image for the car at ``car``: height_px x width_px x 3 uint8 RGB, row 0 at the top."""
        eye, forward, up = camera_eye_and_axes(car, camera)
        self._cull(eye, camera.far_m)
        view = pybullet.computeViewMatrix(eye.tolist(), (eye + forward).tolist(), up.tolist())
        projection = pybullet.computeProjectionMatrixFOV(
            math.degrees(vertical_fov_rad(camera)), camera.width_px / camera.height_px, camera.near_m, camera.far_m
        )
        width, height = camera.width_px, camera.height_px
        _, _, rgba, depth, _ = pybullet.getCameraImage(
            width,
            height,
            viewMatrix=view,
            projectionMatrix=projection,
            renderer=pybullet.ER_TINY_RENDERER,
            shadow=0,
            flags=pybullet.ER_NO_SEGMENTATION_MASK,
            physicsClientId=self._client,
            **self._lighting,
        )
        image = np.array(np.reshape(rgba, (height, width, 4))[:, :, :3], dtype=np.uint8)
        sky = np.reshape(depth, (height, width)) >= SKY_DEPTH
        image[sky] = self._sky_rgb
        return image

    # -- life cycle -------------------------------------------------------------------------------------------------

    def close(self) -> None:
        """Disconnect the PyBullet client; idempotent."""
        if getattr(self, "_client", None) is not None and self._client >= 0:
            try:
                pybullet.disconnect(physicsClientId=self._client)
            except pybullet.error:
                pass
        self._client = None

    def __enter__(self) -> Scene:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:
            pass
