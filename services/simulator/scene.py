"""The rendered world of one circuit: road, centre line, walls, grass and sky, seen by the car's front camera.

PyBullet in ``DIRECT`` mode with the CPU ``ER_TINY_RENDERER`` (no GL, deterministic pixels): the reference renderer.
The world itself (meshes, colours, lighting, sky) is :mod:`services.simulator.world`'s scene description, which the
``gl`` backend (:mod:`services.simulator.gl_scene`) draws too. See ``reference/simulator.md`` for the measurements
behind the choices here:

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
from typing import cast

import numpy as np
import pybullet

from circuits import Circuit
from protocol.episode_spec import CameraSpec, WorldVariation
from services.simulator.car import CarState
from services.simulator.world import (  # noqa: F401 - the scene's constants, importable from here as before
    GRASS_COLOUR,
    LIGHTING,
    LINE_COLOURS,
    MAX_TRIANGLES_PER_CHUNK,
    ROAD_COLOURS,
    SKY_RGB,
    SKY_RGB_BY_LIGHTING,
    WALL_COLOUR,
    LineColour,
    Mesh,
    RoadColour,
    SceneDescription,
    camera_eye_and_axes,
    describe,
    vertical_fov_rad,
)

_OCCLUSION_MARGIN_M = 0.02  # the eye must be this far inside the walls for them to hide the grass
SKY_DEPTH = 0.9999  # depth-buffer values at or above this are background (nothing rendered): paint sky there


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


def grass_occluded(description: SceneDescription, eye: np.ndarray) -> bool:
    """True when the walls hide all the grass: the eye is between the walls and below their top.

    A sight line from there to any grass point outside the road crosses the wall curtain below its top, and the
    grass under the road lies below the road surface.
    """
    circuit = description.circuit
    if not description.walls or eye[2] >= circuit.wall_height_m - _OCCLUSION_MARGIN_M:
        return False
    lateral = circuit.centreline.project(float(eye[0]), float(eye[1])).lateral_m
    return abs(lateral) < circuit.road_half_width_m - _OCCLUSION_MARGIN_M


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
        if cull_margin_m is not None and cull_margin_m < 0:
            raise ValueError(f"cull_margin_m must be >= 0 or None, got {cull_margin_m}")
        description = describe(
            circuit, line_colour=line_colour, road_colour=road_colour, walls=walls, lighting=lighting
        )
        self.description = description
        self._lighting = LIGHTING[lighting]
        self._sky_rgb = description.sky_rgb
        self.circuit = circuit
        self.cull_margin_m = cull_margin_m
        self._client: int | None = pybullet.connect(pybullet.DIRECT)
        if self._client < 0:
            raise RuntimeError("could not start a PyBullet DIRECT client")
        self._chunks: list[_Chunk] = []
        try:
            for mesh in description.meshes:
                self._add_chunk(mesh)
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
        # WorldVariation checks its values against these names; its fields are plain str on the wire.
        line = cast(LineColour, world.line)
        road = cast(RoadColour, world.road)
        return cls(circuit, line_colour=line, road_colour=road, walls=world.walls, lighting=world.lighting)

    # -- building ---------------------------------------------------------------------------------------------------

    def _add_chunk(self, mesh: Mesh) -> None:
        """One PyBullet body per mesh chunk, created in the description's order (TinyRenderer draws in it)."""
        shape = pybullet.createVisualShape(
            pybullet.GEOM_MESH,
            vertices=mesh.vertices_m.tolist(),
            indices=mesh.indices.tolist(),
            rgbaColor=list(mesh.rgba),
            specularColor=[0.0, 0.0, 0.0],
            physicsClientId=self._client,
        )
        body = pybullet.createMultiBody(baseMass=0, baseVisualShapeIndex=shape, physicsClientId=self._client)
        self._chunks.append(_Chunk(body, mesh.rgba, mesh.centre_m, mesh.radius_m, mesh.triangles, mesh.kind == "grass"))

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

    def _cull(self, eye: np.ndarray, far_m: float) -> None:
        if self.cull_margin_m is None:
            return
        gap = np.linalg.norm(self._centres - eye, axis=1) - self._radii
        hide = gap > far_m + self.cull_margin_m
        if grass_occluded(self.description, eye):
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
        client = getattr(self, "_client", None)
        if client is not None and client >= 0:
            try:
                pybullet.disconnect(physicsClientId=client)
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
