"""The gazebo look drawn by OpenGL: textures, Lambert + ambient shading, specular walls, sun shadows, a cloudy sky.

Used by :class:`services.simulator.gl_scene.GLScene` for a description whose ``look`` is "gazebo"
(:func:`services.simulator.world.describe_gazebo`); the materials, light and textures are
:mod:`services.simulator.looks`'. One frame is three passes:

1. where the world has shadows, a depth pass of the walls (the only shadow casters: road, lines and grass are flat)
   from the sun into a shadow map over an orthographic box around the camera's view (the 15 m far plane bounds
   it), its centre snapped to whole shadow texels so that shadow edges do not crawl as the car moves;
2. the world: asphalt and grass textures (repeat wrapping, mipmaps, trilinear filtering, so that a 0.30 m asphalt
   tile does not sparkle at 320x240), lit by ``ambient + diffuse * max(0, n . l) * lit``, with a Blinn-Phong
   highlight on the walls, and ``lit`` from the shadow map (3x3 comparison samples, a depth bias and a normal
   offset against shadow acne). Each material has its own program (only its path of the shader), and the chunks
   are drawn in description order, as a single program would draw them: the same pixels, at two thirds of the
   cost on llvmpipe;
3. the sky, last, so that it is shaded only where nothing else is: a full-screen triangle at the far plane, a
   gradient from the horizon to the zenith with static clouds (a seeded texture on a plane above the world, so
   that they stay put in the world as the car turns).

Deterministic: the same pose gives the same pixels on one machine (no time, no random state at draw time).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from protocol.episode_spec import CameraSpec
from services.simulator.looks import (
    ASPHALT_TILE_M,
    CLOUD_RGB,
    GRASS_TILE_M,
    SKY_HORIZON_RGB,
    SKY_ZENITH_RGB,
    SUN_SPECULAR,
    WALL_SHININESS,
    WALL_SPECULAR,
    asphalt_texture,
    cloud_texture,
    grass_texture,
)
from services.simulator.world import SceneDescription, chunk_runs

SHADOW_MAP_PX = 1024
SHADOW_BOX_HALF_M = 17.0  # the view frustum to 15 m (90 deg wide) fits in a sphere of 16.8 m around its middle
SHADOW_DEPTH_M = 50.0
MATERIAL_IDS = {"flat": 0, "asphalt": 1, "grass": 2, "wall": 3}
WALL = MATERIAL_IDS["wall"]
# Anisotropic filtering costs about 5x a frame on llvmpipe (measured at 640x480: 526 ms against 97 ms, with
# explicit gradients): trilinear only, so the distant road blurs along its length instead of sparkling.
ANISOTROPY = 1.0
NO_SUN_SKY_GAIN = 0.55  # the no_sun worlds' sky, darker as the flat look's (96 / 104 / 118 against 180 / 192 / 210)

_WORLD_VERTEX = """
#version 330
uniform mat4 clip_from_world;
in vec3 in_position;
in vec3 in_normal;
in vec2 in_uv;
in vec3 in_colour;
out vec3 v_world;
out vec3 v_normal;
out vec2 v_uv;
out vec3 v_colour;
void main() {
    gl_Position = clip_from_world * vec4(in_position, 1.0);
    v_world = in_position;
    v_normal = in_normal;
    v_uv = in_uv;
    v_colour = in_colour;
}
"""

# One program per material and per shadowing (preprocessor switches): llvmpipe runs both sides of a branch and
# both arms of a select, so one program with every material's code paid each pixel for two texture lookups, the
# specular term and, even where the world has no shadows, the four shadow-map taps. The arithmetic of each path is
# the same as in the one program, so the pixels are too (tested bit for bit).
_WORLD_FRAGMENT = """
uniform sampler2D asphalt;
uniform sampler2D grass;
uniform sampler2DShadow shadow_map;
uniform mat4 shadow_from_world;
uniform float shadow_texel;
uniform float shadow_bias;
uniform vec3 light_towards;
uniform vec3 eye;
uniform float ambient;
uniform float diffuse;
uniform float exposure;
uniform float specular;
uniform float shininess;
in vec3 v_world;
in vec3 v_normal;
in vec2 v_uv;
in vec3 v_colour;
out vec4 out_colour;

#if SHADOWS
float sunlit(vec3 n) {
    vec4 p = shadow_from_world * vec4(v_world + 0.02 * n, 1.0);
    vec3 q = p.xyz * 0.5 + 0.5;
    if (q.x <= 0.0 || q.y <= 0.0 || q.x >= 1.0 || q.y >= 1.0) return 1.0;
    // Four bilinear comparison taps (the sampler filters linearly): a soft 3x3-texel edge.
    float lit = 0.0;
    for (int i = 0; i < 4; i++) {
        vec2 offset = vec2(float(i & 1) - 0.5, float(i >> 1) - 0.5) * shadow_texel;
        lit += texture(shadow_map, vec3(q.xy + offset, q.z - shadow_bias));
    }
    return 0.25 * lit;
}
#endif

void main() {
#if MATERIAL == 1
    vec3 base = texture(asphalt, v_uv).rgb;
#elif MATERIAL == 2
    vec3 base = texture(grass, v_uv).rgb;
#else
    vec3 base = v_colour;
#endif
    vec3 n = normalize(v_normal);
    float lambert = max(0.0, dot(n, light_towards)) * step(0.0, diffuse - 1e-6);
#if SHADOWS
    float lit = lambert > 0.0 ? sunlit(n) : 1.0;
#else
    float lit = 1.0;
#endif
    vec3 colour = base * (ambient + diffuse * lambert * lit) / exposure;
#if MATERIAL == 3
    if (lambert > 0.0) {
        vec3 h = normalize(light_towards + normalize(eye - v_world));
        colour += vec3(specular * pow(max(0.0, dot(n, h)), shininess) * lit);
    }
#endif
    out_colour = vec4(min(colour, vec3(1.0)), 1.0);
}
"""

_SHADOW_VERTEX = """
#version 330
uniform mat4 shadow_from_world;
in vec3 in_position;
void main() {
    gl_Position = shadow_from_world * vec4(in_position, 1.0);
}
"""

_SHADOW_FRAGMENT = """
#version 330
void main() {
}
"""

_SKY_VERTEX = """
#version 330
in vec2 in_ndc;
out vec2 v_ndc;
void main() {
    gl_Position = vec4(in_ndc, 1.0, 1.0);  // at the far plane: drawn only where the world left the depth at 1
    v_ndc = in_ndc;
}
"""

_SKY_FRAGMENT = """
#version 330
uniform mat3 world_from_camera;
uniform vec2 tan_half;
uniform vec2 ndc_shift;
uniform sampler2D clouds;
uniform vec3 horizon;
uniform vec3 zenith;
uniform vec3 cloud_colour;
uniform float sky_gain;
in vec2 v_ndc;
out vec4 out_colour;
void main() {
    vec3 d = normalize(world_from_camera * vec3((v_ndc - ndc_shift) * tan_half, -1.0));
    float e = d.z;
    vec3 sky = mix(horizon, zenith, smoothstep(0.0, 0.6, e));
    // Clouds on a plane above the world, seen in direction d; they thin out towards the horizon.
    vec2 p = d.xy / max(e, 0.08) * 0.35;
    float cover = texture(clouds, p).r * smoothstep(0.02, 0.25, e);
    out_colour = vec4(sky_gain * mix(sky, cloud_colour, cover), 1.0);
}
"""


class GazeboPasses:
    """The GL objects of the gazebo look for one scene: programs, vertex arrays, textures, the shadow map."""

    def __init__(self, ctx, description: SceneDescription):
        light = description.gazebo
        if light is None:
            raise ValueError("GazeboPasses needs a gazebo-look description (describe_gazebo)")
        self._ctx = ctx
        self.shadows = light.shadows
        vertices, self.first, self.count = gazebo_soup(description)
        self._vbo = ctx.buffer(vertices.tobytes())
        self._chunk_materials = np.array([MATERIAL_IDS[mesh.material] for mesh in description.meshes])
        uniforms = {
            "light_towards": light.light_towards,
            "ambient": light.ambient,
            "diffuse": light.diffuse,
            "exposure": light.exposure,
            "specular": SUN_SPECULAR * WALL_SPECULAR,
            "shininess": WALL_SHININESS,
            "shadow_texel": 1.0 / SHADOW_MAP_PX,
            "shadow_bias": 0.03 / (2.0 * SHADOW_DEPTH_M),
            "asphalt": 0,
            "grass": 1,
            "shadow_map": 2,
        }
        self._programs: dict[int, Any] = {}
        self._vaos: dict[int, Any] = {}
        for material in sorted(set(self._chunk_materials.tolist())):
            defines = f"#version 330\n#define MATERIAL {material}\n#define SHADOWS {int(light.shadows)}\n"
            program = ctx.program(vertex_shader=_WORLD_VERTEX, fragment_shader=defines + _WORLD_FRAGMENT)
            for name, value in uniforms.items():
                if program.get(name, None) is not None:  # each program keeps only the uniforms its paths use
                    program[name].value = value
            self._programs[material] = program
            self._vaos[material] = ctx.vertex_array(
                program,
                [(self._vbo, "3f 3f 2f 3f", "in_position", "in_normal", "in_uv", "in_colour")],
                skip_errors=True,  # attributes a material's program does not read
            )
        self._textures = [
            self._texture(asphalt_texture(), 3),
            self._texture(grass_texture(), 3),
        ]
        self._clouds = self._texture(cloud_texture(), 1)
        self._sky_program = ctx.program(vertex_shader=_SKY_VERTEX, fragment_shader=_SKY_FRAGMENT)
        for name, rgb in (("horizon", SKY_HORIZON_RGB), ("zenith", SKY_ZENITH_RGB), ("cloud_colour", CLOUD_RGB)):
            self._sky_program[name].value = tuple(channel / 255.0 for channel in rgb)
        self._sky_program["clouds"].value = 3
        self._sky_program["sky_gain"].value = 1.0 if light.sun else NO_SUN_SKY_GAIN
        self._sky_vbo = ctx.buffer(np.array([-1, -1, 3, -1, -1, 3], dtype="f4").tobytes())
        self._sky_vao = ctx.vertex_array(self._sky_program, [(self._sky_vbo, "2f", "in_ndc")])
        self._shadow_map: Any = None
        self._shadow_framebuffer: Any = None
        self._shadow_vao: Any = None
        self._shadow_program: Any = None
        if light.shadows:
            import moderngl

            self._shadow_map = ctx.depth_texture((SHADOW_MAP_PX, SHADOW_MAP_PX))
            self._shadow_map.compare_func = "<="
            self._shadow_map.repeat_x = self._shadow_map.repeat_y = False
            self._shadow_map.filter = (moderngl.LINEAR, moderngl.LINEAR)  # bilinear comparison: 2x2 samples a tap
            self._shadow_framebuffer = ctx.framebuffer(depth_attachment=self._shadow_map)
            self._shadow_program = ctx.program(vertex_shader=_SHADOW_VERTEX, fragment_shader=_SHADOW_FRAGMENT)
            self._shadow_vao = ctx.vertex_array(self._shadow_program, [(self._vbo, "3f 32x", "in_position")])
        self._light_towards = np.asarray(light.light_towards)

    def _texture(self, texels: np.ndarray, components: int):
        import moderngl

        height, width = texels.shape[:2]
        texture = self._ctx.texture((width, height), components, np.ascontiguousarray(texels).tobytes(), alignment=1)
        texture.build_mipmaps()
        texture.filter = (moderngl.LINEAR_MIPMAP_LINEAR, moderngl.LINEAR)
        texture.anisotropy = ANISOTROPY
        return texture

    def draw(
        self,
        *,
        framebuffer,
        clip_from_world: np.ndarray,
        eye: np.ndarray,
        camera_axes: tuple[np.ndarray, np.ndarray],
        camera: CameraSpec,
        projection: np.ndarray,
        visible: np.ndarray,
    ) -> None:
        """One frame into ``framebuffer``: shadow map, world, sky; ``visible``: which chunks to draw (bool each)."""
        ctx = self._ctx
        if self.shadows:
            shadow_from_world = self._shadow_matrix(eye, camera_axes[0])
            self._draw_shadow_map(shadow_from_world, self._runs(visible & (self._chunk_materials == WALL)))
            shadow_bytes = shadow_from_world.T.astype("f4").tobytes()
            for program in self._programs.values():
                program["shadow_from_world"].write(shadow_bytes)
            self._shadow_map.use(location=2)
        framebuffer.use()  # also sets the viewport to the camera's size
        framebuffer.clear(0.0, 0.0, 0.0, 1.0, depth=1.0)
        self._textures[0].use(location=0)
        self._textures[1].use(location=1)
        clip_bytes = clip_from_world.T.astype("f4").tobytes()
        for material, program in self._programs.items():
            program["clip_from_world"].write(clip_bytes)
            if material == WALL:
                program["eye"].value = tuple(float(v) for v in eye)
        ctx.enable(ctx.DEPTH_TEST | ctx.CULL_FACE)
        # In description order, as one program drew them: where two surfaces tie in depth the first drawn wins.
        draws = [
            (first, count, material)
            for material in self._programs
            for first, count in self._runs(visible & (self._chunk_materials == material))
        ]
        for first, count, material in sorted(draws):
            self._vaos[material].render(first=first, vertices=count)
        self._draw_sky(camera_axes, projection)  # last: the sky is shaded only where nothing else is

    def _draw_sky(self, camera_axes: tuple[np.ndarray, np.ndarray], projection: np.ndarray) -> None:
        forward, up = camera_axes
        side = np.cross(forward, up)
        world_from_camera = np.column_stack([side, up, -forward])
        self._sky_program["world_from_camera"].write(world_from_camera.T.astype("f4").tobytes())
        self._sky_program["tan_half"].value = (1.0 / projection[0, 0], 1.0 / projection[1, 1])
        self._sky_program["ndc_shift"].value = (-projection[0, 2], -projection[1, 2])
        self._clouds.use(location=3)
        ctx = self._ctx
        ctx.disable(ctx.CULL_FACE)
        ctx.depth_func = "<="
        self._sky_vao.render(vertices=3)
        ctx.depth_func = "<"

    def _runs(self, draw: np.ndarray) -> list[tuple[int, int]]:
        return chunk_runs(draw, first=self.first, count=self.count)

    def _shadow_matrix(self, eye: np.ndarray, forward: np.ndarray) -> np.ndarray:
        """shadow_from_world: the sun's orthographic view of a box around the camera's view, snapped to texels."""
        z_axis = self._light_towards
        x_axis = np.cross([0.0, 0.0, 1.0], z_axis)
        x_axis /= np.linalg.norm(x_axis)
        y_axis = np.cross(z_axis, x_axis)
        rotation = np.stack([x_axis, y_axis, z_axis])
        ahead = np.array([forward[0], forward[1], 0.0])
        ahead /= max(float(np.linalg.norm(ahead)), 1e-9)
        centre = rotation @ (eye + 7.5 * ahead)
        texel_m = 2.0 * SHADOW_BOX_HALF_M / SHADOW_MAP_PX
        centre[:2] = np.round(centre[:2] / texel_m) * texel_m
        light_from_world = np.eye(4)
        light_from_world[:3, :3] = rotation
        light_from_world[:3, 3] = -centre
        scale = np.diag([1.0 / SHADOW_BOX_HALF_M, 1.0 / SHADOW_BOX_HALF_M, -1.0 / SHADOW_DEPTH_M, 1.0])
        return scale @ light_from_world

    def _draw_shadow_map(self, shadow_from_world: np.ndarray, wall_runs: list[tuple[int, int]]) -> None:
        ctx = self._ctx
        self._shadow_framebuffer.use()
        self._shadow_framebuffer.clear(depth=1.0)
        ctx.enable(ctx.DEPTH_TEST)
        ctx.disable(ctx.CULL_FACE)
        self._shadow_program["shadow_from_world"].write(shadow_from_world.T.astype("f4").tobytes())
        for first, count in wall_runs:
            self._shadow_vao.render(first=first, vertices=count)

    def release(self) -> None:
        """Release every GL object of the look; idempotent."""
        for name in (
            "_vbo",
            "_sky_vao",
            "_sky_vbo",
            "_sky_program",
            "_shadow_vao",
            "_shadow_program",
            "_shadow_framebuffer",
            "_shadow_map",
            "_clouds",
        ):
            resource = getattr(self, name, None)
            if resource is not None:
                resource.release()
                setattr(self, name, None)
        for resource in (*getattr(self, "_vaos", {}).values(), *getattr(self, "_programs", {}).values()):
            resource.release()
        self._vaos, self._programs = {}, {}
        for texture in getattr(self, "_textures", []):
            texture.release()
        self._textures = []


def gazebo_soup(description: SceneDescription) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every mesh as consecutive triangles of float32 vertices (position 3, normal 3, texture coordinates in tiles 2,
    colour 0..1 3), in description order, with the first vertex and vertex count of each mesh.

    Normals: a mesh's smooth normals turned to the side each triangle faces (walls carry both windings), or the
    triangles' own normals."""
    parts, firsts, counts = [], [], []
    first = 0
    tiles = {"asphalt": ASPHALT_TILE_M, "grass": GRASS_TILE_M}
    for mesh in description.meshes:
        corners = mesh.vertices_m[mesh.indices]
        triangles = corners.reshape(-1, 3, 3)
        faces = np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])
        faces /= np.linalg.norm(faces, axis=1, keepdims=True)
        if mesh.normals is None:
            normals = np.repeat(faces, 3, axis=0)
        else:
            smooth = mesh.normals[mesh.indices].reshape(-1, 3, 3)
            sides = np.sign(np.einsum("ij,ij->i", faces, smooth[:, 0]))
            normals = (smooth * sides[:, None, None]).reshape(-1, 3)
        part = np.zeros((len(corners), 11), dtype=np.float32)
        part[:, :3] = corners
        part[:, 3:6] = normals
        if mesh.texcoords_m is not None:
            uv = mesh.texcoords_m[mesh.indices] / tiles[mesh.material]
            # Whole tiles off a chunk's coordinates change no texel and keep float32 precise kilometres down a track.
            part[:, 6:8] = uv - np.floor(uv.min(axis=0))
        part[:, 8:11] = mesh.rgba[:3]
        parts.append(part)
        firsts.append(first)
        counts.append(len(corners))
        first += len(corners)
    return np.concatenate(parts), np.array(firsts), np.array(counts)
