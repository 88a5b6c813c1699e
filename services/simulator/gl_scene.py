"""The ``gl`` renderer: the scene description drawn by OpenGL (moderngl on a headless EGL context).

On a machine without a GPU, EGL gives Mesa's llvmpipe (a CPU rasteriser, ~10x faster than PyBullet's TinyRenderer
here, see ``reference/renderers.md``); with a GPU the same code runs there. It draws the same
:class:`~services.simulator.world.SceneDescription` as the PyBullet scene (:mod:`services.simulator.scene`), with
the same camera matrices and the same lighting model, so that a frame agrees with TinyRenderer's but for edge pixels:

* TinyRenderer lights our meshes (created without normals) as if every vertex's normal were the direction from the
  world origin to the vertex: a surface's brightness depends on where it lies, not how it faces. Measured on
  PyBullet 3.2.7 (road and walls at one place get the same factor; the factor follows the position), and reproduced
  here so that shading matches: ``colour = floor(min(255, c8 * (ambient + diffuse * max(0, n . l))))`` with ``c8``
  the 8-bit material colour and ``n`` the interpolated, renormalised vertex direction.
* TinyRenderer samples each pixel at its corner, GL at its centre: the projection is moved by half a pixel so
  that edges fall on the same pixels.
* No anti-aliasing and no texture (flat colours), as TinyRenderer; back faces culled (walls carry both windings);
  pixels nothing covers keep the sky colour.
* Chunks beyond the far plane (plus a margin) are skipped as in the PyBullet scene (same pixels, less vertex work).

llvmpipe starts one rendering thread per core unless ``LP_NUM_THREADS`` is set; several rendering processes on a
small machine then oversubscribe it, so this module sets it to 1 before the first context unless it is set. A
stack's simulator gets its share of the cores instead (:func:`orchestrator.stack.launcher.render_threads_for`): all of
them for ``drivebench run``, whose other processes wait for the frame in lock-step. The pixels do not depend on it.
The context is one per process, shared by every :class:`GLScene` in it. Set ``GLCONTEXT_LINUX_LIBEGL`` to choose
the EGL library (glcontext's own variable; a path that does not load makes context creation fail, which is how the
tests simulate a machine without EGL).
"""

from __future__ import annotations

import os
import threading
from typing import TYPE_CHECKING, Any

import numpy as np

from circuits import Circuit
from protocol.episode_spec import CameraSpec, WorldVariation
from services.simulator.car import CarState

if TYPE_CHECKING:
    from services.simulator.gl_gazebo import GazeboPasses
from services.simulator.world import (
    SceneDescription,
    camera_eye_and_axes,
    chunk_runs,
    describe_world,
    projection_matrix,
    view_matrix,
)

_VERTEX_SHADER = """
#version 330
uniform mat4 clip_from_world;
in vec3 in_position;
in vec3 in_colour;
out vec3 v_direction;
out vec3 v_colour;
void main() {
    gl_Position = clip_from_world * vec4(in_position, 1.0);
    // TinyRenderer's normal for a mesh given without normals: the vertex's direction from the origin.
    v_direction = normalize(in_position);
    v_colour = in_colour;
}
"""

_FRAGMENT_SHADER = """
#version 330
uniform vec3 light_towards;
uniform float ambient;
uniform float diffuse;
in vec3 v_direction;
in vec3 v_colour;
out vec4 out_colour;
void main() {
    float shade = ambient + diffuse * max(0.0, dot(normalize(v_direction), light_towards));
    // v_colour holds the 8-bit material colour; TinyRenderer truncates the lit value to an integer.
    vec3 lit = floor(min(vec3(255.0), v_colour * shade));
    out_colour = vec4(lit / 255.0, 1.0);
}
"""

_context_lock = threading.Lock()
_context = None  # the process's one moderngl context, made on first use


class GLUnavailable(RuntimeError):
    """No OpenGL context could be made here (moderngl missing, no EGL library, no usable device)."""


def gl_context():
    """The process's shared headless moderngl context (EGL), created on first call; GLUnavailable says why not."""
    global _context
    with _context_lock:
        if _context is None:
            os.environ.setdefault("LP_NUM_THREADS", "1")  # before Mesa starts: one llvmpipe thread per process
            try:
                import moderngl
            except ImportError as error:
                raise GLUnavailable(f"moderngl is not installed ({error}); pip install 'drivebench[gl]'") from None
            try:
                context = moderngl.create_context(standalone=True, backend="egl", require=330)
            except Exception as error:  # glcontext raises bare Exceptions: "libEGL.so.1 not loaded", "eglInitialize"
                raise GLUnavailable(f"no EGL OpenGL 3.3 context: {error}") from None
            _context = context
        return _context


def egl_unavailable_reason() -> str | None:
    """None when an EGL context can be made in this process, else why not (one line)."""
    try:
        gl_context()
    except GLUnavailable as error:
        return str(error)
    return None


class GLScene:
    """The scene of one circuit drawn with OpenGL; same interface as :class:`services.simulator.scene.Scene`.

    description: the world to draw (:func:`services.simulator.world.describe_world`).
    cull_margin_m: chunks farther than ``camera.far_m + cull_margin_m`` from the camera are skipped; ``None`` draws
        every chunk (same pixels).
    """

    def __init__(self, description: SceneDescription, *, cull_margin_m: float | None = 5.0):
        if cull_margin_m is not None and cull_margin_m < 0:
            raise ValueError(f"cull_margin_m must be >= 0 or None, got {cull_margin_m}")
        self.description = description
        self.circuit = description.circuit
        self.cull_margin_m = cull_margin_m
        self._ctx = gl_context()
        self._gazebo: GazeboPasses | None = None
        self._program: Any = None
        self._vbo: Any = None
        self._vao: Any = None
        if description.look == "gazebo":
            from services.simulator.gl_gazebo import GazeboPasses

            self._gazebo = GazeboPasses(self._ctx, description)
            self._first, self._count = self._gazebo.first, self._gazebo.count
        else:
            self._program = self._ctx.program(vertex_shader=_VERTEX_SHADER, fragment_shader=_FRAGMENT_SHADER)
            self._program["light_towards"].value = description.light_towards
            self._program["ambient"].value = description.ambient
            self._program["diffuse"].value = description.diffuse
            vertices, self._first, self._count = _triangle_soup(description)
            self._vbo = self._ctx.buffer(vertices.tobytes())
            self._vao = self._ctx.vertex_array(self._program, [(self._vbo, "3f 3f", "in_position", "in_colour")])
        self._centres = np.stack([mesh.centre_m for mesh in description.meshes])
        self._radii = np.array([mesh.radius_m for mesh in description.meshes])
        self._framebuffers: dict[tuple[int, int], object] = {}
        self._sky = tuple(channel / 255.0 for channel in description.sky_rgb)
        self.visible_chunk_count = len(description.meshes)

    @classmethod
    def for_world(cls, circuit: Circuit, world: WorldVariation) -> GLScene:
        """The scene of ``circuit`` with a world variation (line, road, walls, lighting, look)."""
        return cls(describe_world(circuit, world))

    @property
    def triangle_count(self) -> int:
        return self.description.triangle_count

    @property
    def chunk_count(self) -> int:
        return len(self.description.meshes)

    def _framebuffer(self, width_px: int, height_px: int):
        framebuffer = self._framebuffers.get((width_px, height_px))
        if framebuffer is None:
            framebuffer = self._ctx.framebuffer(
                color_attachments=[self._ctx.renderbuffer((width_px, height_px), components=4)],
                depth_attachment=self._ctx.depth_renderbuffer((width_px, height_px)),
            )
            self._framebuffers[(width_px, height_px)] = framebuffer
        return framebuffer

    def _visible(self, eye: np.ndarray, far_m: float) -> np.ndarray:
        """Which chunks to draw (bool per chunk).

        Unlike the PyBullet scene, the grass is not hidden when the walls occlude it: here the depth test rejects
        its pixels for less than the centre-line projection that decides it costs (measured: 0.13 ms a frame).
        """
        if self.cull_margin_m is None:
            draw = np.ones(len(self._radii), dtype=bool)
        else:
            offsets = self._centres - eye
            gaps = np.sqrt(np.einsum("ij,ij->i", offsets, offsets)) - self._radii
            draw = gaps <= far_m + self.cull_margin_m
        self.visible_chunk_count = int(draw.sum())
        return draw

    def _visible_runs(self, eye: np.ndarray, far_m: float) -> list[tuple[int, int]]:
        """(first vertex, vertex count) of each run of consecutive chunks to draw."""
        return chunk_runs(self._visible(eye, far_m), first=self._first, count=self._count)

    def render(self, car: CarState, camera: CameraSpec) -> np.ndarray:
        """The camera image for the car at ``car``: height_px x width_px x 3 uint8 RGB, row 0 at the top."""
        eye, forward, up = camera_eye_and_axes(car, camera)
        projection = _tinyrenderer_sampling(camera)
        clip_from_world = projection @ view_matrix(car, camera)
        width, height = camera.width_px, camera.height_px
        framebuffer = self._framebuffer(width, height)
        if self._gazebo is not None:
            self._gazebo.draw(
                framebuffer=framebuffer,
                clip_from_world=clip_from_world,
                eye=eye,
                camera_axes=(forward, up),
                camera=camera,
                projection=projection,
                visible=self._visible(eye, camera.far_m),
            )
        else:
            self._program["clip_from_world"].write(clip_from_world.T.astype("f4").tobytes())  # GL: column-major
            framebuffer.use()
            self._ctx.enable(self._ctx.DEPTH_TEST | self._ctx.CULL_FACE)
            framebuffer.clear(*self._sky, 1.0, depth=1.0)
            for first, count in self._visible_runs(eye, camera.far_m):
                self._vao.render(first=first, vertices=count)
        data = framebuffer.read(components=3, alignment=1)
        # GL's rows run bottom-up; flipped into a fresh, writeable, C-contiguous array.
        return np.ascontiguousarray(np.frombuffer(data, dtype=np.uint8).reshape(height, width, 3)[::-1])

    def close(self) -> None:
        """Release this scene's GL objects (the shared context stays); idempotent."""
        for framebuffer in getattr(self, "_framebuffers", {}).values():
            for attachment in (*framebuffer.color_attachments, framebuffer.depth_attachment):
                attachment.release()
            framebuffer.release()
        self._framebuffers = {}
        gazebo = getattr(self, "_gazebo", None)
        if gazebo is not None:
            gazebo.release()
            self._gazebo = None
        for name in ("_vao", "_vbo", "_program"):
            resource = getattr(self, name, None)
            if resource is not None:
                resource.release()
                setattr(self, name, None)

    def __enter__(self) -> GLScene:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()


def _tinyrenderer_sampling(camera: CameraSpec) -> np.ndarray:
    """The projection, moved half a pixel right and up: GL samples a pixel at its centre, TinyRenderer at its
    corner. Measured: edge pixels that differ by more than 8 levels drop from ~0.6 % to < 0.01 % of a frame."""
    projection = projection_matrix(camera)
    # clip.w = -z_camera, so adding -k to the z column moves x_ndc (y_ndc) by +k: half a pixel is 1/width in NDC.
    projection[0, 2] -= 1.0 / camera.width_px
    projection[1, 2] -= 1.0 / camera.height_px
    return projection


def _triangle_soup(description: SceneDescription) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every mesh as consecutive triangles of (x, y, z, r8, g8, b8) float32 vertices, in description order, with the
    first vertex and vertex count of each mesh. The colour is TinyRenderer's 8-bit material colour (truncated)."""
    parts, firsts, counts = [], [], []
    first = 0
    for mesh in description.meshes:
        corners = mesh.vertices_m[mesh.indices]
        colour8 = np.floor(np.asarray(mesh.rgba[:3]) * 255.0)
        part = np.empty((len(corners), 6), dtype=np.float32)
        part[:, :3] = corners
        part[:, 3:] = colour8
        parts.append(part)
        firsts.append(first)
        counts.append(len(corners))
        first += len(corners)
    return np.concatenate(parts), np.array(firsts), np.array(counts)
