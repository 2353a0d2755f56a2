"""Headless moderngl renderer: lit RGB, metric depth and segmentation for every camera of the rig.

How it is built, and why (each choice measured on Mesa llvmpipe, see ``benchmarks/render.py``):

* All scene geometry is uploaded once into one interleaved vertex buffer and one index buffer in the
  Y-up OpenGL world, and every texture into one mipmapped texture array, so a frame needs two
  programs and no texture switches.
* Triangles are grouped into square ground tiles, opaque before alpha-tested. Each frame draws only
  the tiles that intersect the camera frustum, nearest first, so the rasteriser rejects hidden
  fragments early (llvmpipe shades vertices on one thread, so culling matters as much as fill).
* One geometry pass per camera writes three render targets: lit colour, class id (R8UI) and the
  optical-frame z in metres (R32F) taken from the eye-space position, exact to float precision.
  A full-screen sky pass then fills only the pixels still at the far plane: gradient colour, class
  SKY and depth NaN, so misses need no conversion after readback.
* The projection is mirrored vertically so GL row 0 is the image's top row: readback needs no flip.
* The sun's shadow map is rendered once at start (static scene, static sun) and sampled with PCF; a new
  light (:meth:`Renderer.set_light`) renders it again.
* The light (:class:`~droneulator.render.light.Lighting`: sun direction and colour, hemisphere ambient,
  sky gradient, haze) comes in as uniforms. Haze (Koschmieder fog) is a program variant of its own
  (``FOG``), so the colour path without it and the depth-only path carry nothing for it.
"""

from __future__ import annotations

from collections.abc import Collection
from dataclasses import dataclass

import moderngl
import numpy as np
from PIL import Image

from droneulator import frames
from droneulator.config import CameraConfig, SimConfig
from droneulator.render.light import HAZE_LAYER_M, Lighting, historical_lighting, resolve_lighting
from droneulator.scenes.base import MeshPart, Scene
from droneulator.sensors.camera import Camera, gl_projection
from droneulator.vehicles.mesh import TEXTURE as VEHICLE_TEXTURE
from droneulator.vehicles.mesh import vehicle_mesh, vehicle_texture

#: Target number of ground tiles along the longer side of the scene.
TILES_PER_SIDE = 12
#: Textures are resized to one common square size in the array, at most this many texels a side.
MAX_TEXTURE_SIZE = 2048
#: Horizontal margin (m) around the scene's flyable bounds that the shadow map covers.
SHADOW_MARGIN = 10.0
#: Mirrors clip-space y so that framebuffer row 0 is the top image row (OpenCV convention).
_FLIP_Y = np.diag([1.0, -1.0, 1.0, 1.0])
_QUIET_NAN = 0x7FC00000
#: Interleaved vertex layout: attribute name, moderngl format, padding that skips it when unused.
_ATTRIBUTES = (
    ("in_pos", "3f4", "12x"),
    ("in_normal", "3f4", "12x"),
    ("in_uv", "2f4", "8x"),
    ("in_meta", "2u2", "4x"),
)

_GEOMETRY_VS = """
in vec3 in_pos;
in vec3 in_normal;
in vec2 in_uv;
in uvec2 in_meta;  // semantic class, texture layer
uniform mat4 u_view;
uniform mat4 u_proj;
// Varyings are packed into few vec4 slots: llvmpipe's triangle setup cost grows with the slot count.
flat out uvec2 v_meta;
out vec4 v_depth_shadow;  // shadow map coordinates (xyz, with SHADOWS), optical depth in metres (w)
#ifdef TEXCOORD
out vec4 v_uv_light;  // uv (xy), sky weight of the hemisphere ambient (z), sun diffuse (w)
#endif
#ifdef COLOR
uniform vec3 u_eye;
uniform vec3 u_sun;
#endif
#ifdef FOG
out vec3 v_view;  // eye-space position: the distance the haze acts over
#endif
#ifdef SHADOWS
uniform mat4 u_light;
uniform float u_normal_offset;
#endif

#ifdef MODEL
uniform mat4 u_model;  // a vehicle's body frame -> the GL world
#endif

void main() {
#ifdef MODEL
    vec3 pos = (u_model * vec4(in_pos, 1.0)).xyz;
#else
    vec3 pos = in_pos;
#endif
    vec4 eye = u_view * vec4(pos, 1.0);
    gl_Position = u_proj * eye;
    v_meta = in_meta;
    v_depth_shadow = vec4(0.0, 0.0, 0.0, -eye.z);
#ifdef FOG
    v_view = eye.xyz;
#endif
#ifdef TEXCOORD
    v_uv_light = vec4(in_uv, 0.0, 0.0);
#endif
#ifdef COLOR
#ifdef MODEL
    vec3 n = mat3(u_model) * in_normal;
#else
    vec3 n = in_normal;
#endif
    if (dot(n, u_eye - pos) < 0.0) n = -n;  // two-sided: light the side the camera sees
    v_uv_light.zw = vec2(0.5 + 0.5 * n.y, max(dot(n, u_sun), 0.0));
#ifdef SHADOWS
    v_depth_shadow.xyz = (u_light * vec4(pos + n * u_normal_offset, 1.0)).xyz;
#endif
#endif
}
"""

_GEOMETRY_FS = """
flat in uvec2 v_meta;
in vec4 v_depth_shadow;
#ifdef TEXCOORD
in vec4 v_uv_light;
uniform sampler2DArray u_texture;
#endif
#ifdef ALPHA_TEST
uniform float u_texture_size;
#endif
#ifdef SHADOWS
uniform sampler2DShadow u_shadow_map;
#endif
#ifdef COLOR
uniform vec3 u_sun_color;
uniform vec3 u_ambient_ground;  // hemisphere ambient: surfaces facing down, and up
uniform vec3 u_ambient_sky;
#endif
#ifdef FOG
in vec3 v_view;
uniform float u_fog_beta;
uniform vec3 u_fog_color;
#endif
#ifdef COLOR
layout(location = 0) out vec4 o_color;
layout(location = 1) out uint o_class;
layout(location = 2) out float o_depth;
#else
layout(location = 0) out uint o_class;
layout(location = 1) out float o_depth;
#endif

void main() {
#ifdef TEXCOORD
    vec4 albedo = texture(u_texture, vec3(v_uv_light.xy, float(v_meta.y)));
#endif
#ifdef ALPHA_TEST
    // Raise alpha with the mip level so that distant leaf cards keep their coverage.
    vec2 texels = max(abs(dFdx(v_uv_light.xy)), abs(dFdy(v_uv_light.xy))) * u_texture_size;
    float lod = max(log2(max(texels.x, texels.y)), 0.0);
    if (albedo.a * (1.0 + 0.25 * lod) < 0.5) discard;
#endif
#ifdef COLOR
#ifdef SHADOWS
    // Only surfaces facing the sun need the (2x2 PCF) lookup; the map has no mips, so LOD 0.
    float lit = 0.0;
    if (v_uv_light.w > 0.0) {
        vec2 st = v_depth_shadow.xy;
        bool mapped = all(equal(clamp(st, 0.0, 1.0), st));
        lit = mapped ? textureLod(u_shadow_map, v_depth_shadow.xyz, 0.0) : 1.0;
    }
#else
    float lit = 1.0;
#endif
    vec3 ambient = mix(u_ambient_ground, u_ambient_sky, v_uv_light.z);
    vec3 color = albedo.rgb * (ambient + u_sun_color * (v_uv_light.w * lit));
#ifdef FOG
    // Koschmieder: what the camera sees fades to the haze's colour as exp(-beta * distance)
    color = mix(u_fog_color, min(color, vec3(1.0)), exp(-u_fog_beta * length(v_view)));
#endif
    o_color = vec4(color, 1.0);
#endif
    o_class = v_meta.x;
    o_depth = v_depth_shadow.w;
}
"""

_SHADOW_VS = """
in vec3 in_pos;
in vec2 in_uv;
in uvec2 in_meta;
uniform mat4 u_light_clip;
#ifdef ALPHA_TEST
out vec3 v_uv;
#endif
void main() {
    gl_Position = u_light_clip * vec4(in_pos, 1.0);
#ifdef ALPHA_TEST
    v_uv = vec3(in_uv, float(in_meta.y));
#endif
}
"""

_SHADOW_FS = """
#ifdef ALPHA_TEST
in vec3 v_uv;
uniform sampler2DArray u_texture;
uniform float u_texture_size;
#endif
void main() {
#ifdef ALPHA_TEST
    vec2 texels = max(abs(dFdx(v_uv.xy)), abs(dFdy(v_uv.xy))) * u_texture_size;
    float lod = max(log2(max(texels.x, texels.y)), 0.0);
    if (texture(u_texture, v_uv).a * (1.0 + 0.25 * lod) < 0.5) discard;
#endif
}
"""

_SKY_VS = """
out vec2 v_ndc;
void main() {
    v_ndc = vec2(gl_VertexID == 1 ? 3.0 : -1.0, gl_VertexID == 2 ? 3.0 : -1.0);
    gl_Position = vec4(v_ndc, 1.0, 1.0);  // on the far plane: drawn only where nothing was hit
}
"""

_SKY_FS = """
in vec2 v_ndc;
uniform mat3 u_ray;  // NDC (x, y, 1) -> viewing ray in the GL world
uniform vec3 u_zenith;
uniform vec3 u_horizon;
#ifdef FOG
uniform float u_fog_beta;
uniform vec3 u_fog_color;
uniform float u_fog_layer;  // the haze layer's depth (m): a ray up at elevation e crosses layer / sin(e)
#endif
#ifdef COLOR
layout(location = 0) out vec4 o_color;
layout(location = 1) out uint o_class;
layout(location = 2) out float o_depth;
#else
layout(location = 0) out uint o_class;
layout(location = 1) out float o_depth;
#endif
void main() {
#ifdef COLOR
    float up = normalize(u_ray * vec3(v_ndc, 1.0)).y;
    vec3 sky = up > 0.0 ? mix(u_horizon, u_zenith, sqrt(up)) : u_horizon * (1.0 + 0.3 * up);
#ifdef FOG
    sky = mix(u_fog_color, sky, exp(-u_fog_beta * u_fog_layer / max(up, 1e-4)));
#endif
    o_color = vec4(sky, 1.0);
#endif
    o_class = 0u;
    o_depth = uintBitsToFloat(QUIET_NAN);
}
"""


@dataclass
class CameraFrame:
    """One camera's images at one instant.

    The arrays are the renderer's own readback buffers: the next :meth:`Renderer.render` call
    overwrites them, so copy whatever must outlive it.
    """

    name: str
    rgb: np.ndarray | None  # (H, W, 3) uint8, row 0 at the top; None when rendered without colour
    depth: np.ndarray  # (H, W) float32, optical-frame z in metres, NaN where nothing is hit
    seg: np.ndarray  # (H, W) uint8 SemanticClass ids, SKY where nothing is hit
    K: np.ndarray  # (3, 3) intrinsics
    T_world_optical: np.ndarray  # (4, 4) optical frame in the Z-up world
    #: plumb_bob (k1, k2, p1, p2, k3) of a distorted image (droneulator.sensors.camera_models); None: pinhole
    D: np.ndarray | None = None


def _mat(M: np.ndarray) -> bytes:
    """A matrix as GLSL expects it (column-major float32)."""
    return np.ascontiguousarray(np.asarray(M, dtype=np.float32).T).tobytes()


def _source(body: str, defines: tuple[str, ...]) -> str:
    header = "#version 330\n" + "".join(f"#define {d}\n" for d in defines)
    return header + f"#define QUIET_NAN {_QUIET_NAN}u\n" + body


class _Target:
    """Per-camera framebuffer and readback buffers (``vehicle``: the rig the camera is mounted on)."""

    def __init__(self, ctx: moderngl.Context, cam: CameraConfig, vehicle: str = "") -> None:
        self.vehicle = vehicle
        self.cam = cam
        size = (cam.width, cam.height)
        camera = Camera(cam)
        self.K = camera.K
        self.T_body_link = camera.T_body_link
        self.proj = _FLIP_Y @ gl_projection(cam)
        self.color = ctx.renderbuffer(size, 4)
        self.seg_rb = ctx.renderbuffer(size, 1, dtype="u1")
        self.depth_rb = ctx.renderbuffer(size, 1, dtype="f4")
        self.zbuffer = ctx.depth_renderbuffer(size)
        self.fbo_color = ctx.framebuffer([self.color, self.seg_rb, self.depth_rb], self.zbuffer)
        self.fbo_geometry = ctx.framebuffer([self.seg_rb, self.depth_rb], self.zbuffer)
        self.rgb = np.empty((cam.height, cam.width, 3), dtype=np.uint8)
        self.seg = np.empty((cam.height, cam.width), dtype=np.uint8)
        self.depth = np.empty((cam.height, cam.width), dtype=np.float32)

    def release(self) -> None:
        for obj in (self.fbo_color, self.fbo_geometry, self.color, self.seg_rb, self.depth_rb, self.zbuffer):
            obj.release()


class _Body:
    """A vehicle body's mesh on the GPU (its own small vertex and index buffers, drawn per pose)."""

    def __init__(self, ctx: moderngl.Context, part: MeshPart, layer: int) -> None:
        vertex = np.dtype([("pos", "3f4"), ("normal", "3f4"), ("uv", "2f4"), ("meta", "2u2")])
        v = np.empty(len(part.positions), dtype=vertex)
        v["pos"], v["normal"], v["uv"] = part.positions, part.normals, part.uvs
        v["meta"][:, 0] = part.class_ids
        v["meta"][:, 1] = layer
        self.vbo = ctx.buffer(v.tobytes())
        self.ibo = ctx.buffer(np.asarray(part.indices, dtype=np.uint32).tobytes())
        self.count = part.triangle_count * 3
        self.vaos: dict[tuple[str, ...], moderngl.VertexArray] = {}

    def release(self) -> None:
        for obj in (*self.vaos.values(), self.vbo, self.ibo):
            obj.release()


class Renderer:
    """Renders RGB, depth and segmentation for rigs of body-mounted cameras in a static scene.

    ``rigs`` maps each vehicle to its cameras, ``bodies`` each vehicle to its body mesh (body frame, see
    :func:`~droneulator.vehicles.mesh.vehicle_mesh`; drawn in every other vehicle's cameras; vehicles
    given the same mesh share its buffers); ``cameras`` alone is one rig, :meth:`render`'s. ``light``:
    the sun, sky and haze (:func:`~droneulator.render.light.resolve_lighting`); None: the scene's fixed
    sun in a clear sky, as before the light settings existed."""

    def __init__(
        self,
        scene: Scene,
        cameras: list[CameraConfig] | None = None,
        shadows: bool = True,
        shadow_map_size: int = 2048,
        ctx: moderngl.Context | None = None,
        *,
        rigs: dict[str, list[CameraConfig]] | None = None,
        bodies: dict[str, MeshPart] | None = None,
        light: Lighting | None = None,
    ) -> None:
        """Upload ``scene`` and render its shadow map; ``ctx`` defaults to a new headless EGL context."""
        if (rigs is None) == (cameras is None):
            raise ValueError("give the cameras of one rig, or rigs, not both")
        rigs = {"": list(cameras or [])} if rigs is None else rigs
        for vehicle, cams in rigs.items():
            names = [c.name for c in cams]
            if len(set(names)) != len(names):
                raise ValueError(f"camera names must be unique per vehicle, got {names} for {vehicle!r}")
        self._own_ctx = ctx is None
        self.ctx = moderngl.create_context(standalone=True, backend="egl") if ctx is None else ctx
        self.scene = scene
        self.shadows = shadows
        self._programs: dict[tuple[str, ...], moderngl.Program] = {}
        self._vaos: dict[tuple[str, ...], moderngl.VertexArray] = {}
        self._shadow_map: moderngl.Texture | None = None
        self._shadow_map_size = shadow_map_size
        self._light = np.eye(4)
        self._normal_offset = 0.0
        self._use_light(light or historical_lighting(scene))
        with self.ctx:  # current for this thread even when other renderers made their own contexts
            self._upload_textures(scene, with_bodies=bool(bodies))
            self._upload_geometry(scene)
            if shadows and self._n_triangles:
                self._render_shadow_map(shadow_map_size)
            self._sky_vao = self.ctx.vertex_array(self._program(_SKY_VS, _SKY_FS, ("COLOR",)), [])
            self._sky_geometry_vao = self.ctx.vertex_array(self._program(_SKY_VS, _SKY_FS, ()), [])
            self._sky_fog_vao: moderngl.VertexArray | None = None
            self.targets = [_Target(self.ctx, cam, vehicle) for vehicle, cams in rigs.items() for cam in cams]
            # one set of buffers per mesh, shared by every vehicle given the same one
            meshes: dict[int, _Body] = {}
            self._bodies: dict[str, _Body] = {}
            for vehicle, part in (bodies or {}).items():
                if id(part) not in meshes:
                    meshes[id(part)] = _Body(self.ctx, part, self._layers[VEHICLE_TEXTURE])
                self._bodies[vehicle] = meshes[id(part)]

    # ------------------------------------------------------------------------------------ setup
    def _use_light(self, lighting: Lighting) -> None:
        """Take ``lighting``'s values (the sun as a unit vector in the GL world)."""
        self.lighting = lighting
        self._sun = frames.zup_to_gl(np.asarray(lighting.sun, dtype=float))
        self._sun = self._sun / np.linalg.norm(self._sun)
        self._zenith = tuple(lighting.zenith)
        self._horizon = tuple(lighting.horizon)
        self._fog_defines: tuple[str, ...] = ("FOG",) if lighting.fog else ()
        self._light_uniforms = {
            "u_sun_color": tuple(lighting.sun_color),
            "u_ambient_ground": tuple(lighting.ambient_ground),
            "u_ambient_sky": tuple(lighting.ambient_sky),
            "u_fog_beta": float(lighting.fog_beta),
            "u_fog_color": tuple(lighting.fog_color),
            "u_fog_layer": HAZE_LAYER_M,
        }

    def set_light(self, lighting: Lighting) -> None:
        """Light the scene with ``lighting`` from the next frame on (the shadow map is rendered again for
        the new sun; nothing else is uploaded)."""
        if self.ctx is None:
            raise RuntimeError("renderer is closed")
        self._use_light(lighting)
        if self._shadow_map is not None:
            with self.ctx:
                self._shadow_map.release()
                self._shadow_map = None
                self._render_shadow_map(self._shadow_map_size)

    def _program(self, vs: str, fs: str, defines: tuple[str, ...]) -> moderngl.Program:
        key = (vs, fs, *defines)
        if key not in self._programs:
            self._programs[key] = self.ctx.program(
                vertex_shader=_source(vs, defines), fragment_shader=_source(fs, defines)
            )
        return self._programs[key]

    def _upload_textures(self, scene: Scene, with_bodies: bool = False) -> None:
        """All scene textures (and the vehicles' when they are drawn) as layers of one mipmapped RGBA8
        array (resized to a common square)."""
        textures = dict(scene.textures)
        if with_bodies:
            textures[VEHICLE_TEXTURE] = vehicle_texture()
        self._layers = {name: i for i, name in enumerate(textures)}
        images = list(textures.values()) or [np.full((1, 1, 4), 255, dtype=np.uint8)]
        size = min(MAX_TEXTURE_SIZE, max(max(img.shape[:2]) for img in images))
        data = np.empty((len(images), size, size, 4), dtype=np.uint8)
        for i, img in enumerate(images):
            img = np.ascontiguousarray(img, dtype=np.uint8)
            if img.shape[:2] != (size, size):
                # nearest for the vehicles' two-texel colour table, bilinear for the scene's textures
                smooth = Image.Resampling.NEAREST if img.shape[:2] == (2, 2) else Image.Resampling.BILINEAR
                img = np.asarray(Image.fromarray(img, "RGBA").resize((size, size), smooth))
            data[i] = img
        self._texture_size = float(size)
        self._texture = self.ctx.texture_array((size, size, len(images)), 4, data.tobytes())
        self._texture.build_mipmaps()
        self._texture.filter = (moderngl.LINEAR_MIPMAP_LINEAR, moderngl.LINEAR)

    def _upload_geometry(self, scene: Scene) -> None:
        """One vertex and one index buffer for the whole scene, triangles sorted by (alpha, tile)."""
        vertex = np.dtype([("pos", "3f4"), ("normal", "3f4"), ("uv", "2f4"), ("meta", "2u2")])
        parts = [p for p in scene.parts if p.triangle_count]
        n_vertices = sum(len(p.positions) for p in parts)
        vertices = np.empty(n_vertices, dtype=vertex)
        triangles, alpha, start = [], [], 0
        for p in parts:
            if p.texture not in self._layers:
                raise KeyError(f"mesh part {p.name!r} uses unknown texture {p.texture!r}")
            v = vertices[start : start + len(p.positions)]
            v["pos"] = frames.zup_to_gl(p.positions)
            v["normal"] = frames.zup_to_gl(p.normals)
            v["uv"] = p.uvs
            v["meta"][:, 0] = p.class_ids
            v["meta"][:, 1] = self._layers[p.texture]
            triangles.append(np.asarray(p.indices, dtype=np.int64) + start)
            alpha.append(np.full(p.triangle_count, p.alpha_test))
            start += len(p.positions)
        self._n_triangles = sum(p.triangle_count for p in parts)
        if not self._n_triangles:
            self._bounds = np.zeros((2, 3))
            self._tile_first = self._tile_count = np.zeros(0, dtype=np.int64)
            self._tile_alpha = np.zeros(0, dtype=bool)
            return
        tris = np.concatenate(triangles)
        tri_alpha = np.concatenate(alpha)
        pos = vertices["pos"].astype(np.float64)
        self._bounds = np.stack([pos.min(axis=0), pos.max(axis=0)])

        # Tiles on the ground plane (GL x, z), keyed so that opaque tiles come before alpha-tested ones.
        centroid = pos[tris].mean(axis=1)
        extent = self._bounds[1] - self._bounds[0]
        tile = max(extent[0], extent[2], 1e-6) / TILES_PER_SIDE
        cells = np.floor((centroid[:, [0, 2]] - self._bounds[0, [0, 2]]) / tile).astype(np.int64)
        cells = np.clip(cells, 0, TILES_PER_SIDE - 1)
        key = (tri_alpha.astype(np.int64) * TILES_PER_SIDE + cells[:, 0]) * TILES_PER_SIDE + cells[:, 1]
        order = np.argsort(key, kind="stable")
        tris, key = tris[order], key[order]
        keys, first_tri, counts = np.unique(key, return_index=True, return_counts=True)
        tri_min = pos[tris].min(axis=1)
        tri_max = pos[tris].max(axis=1)
        lo = np.minimum.reduceat(tri_min, first_tri)
        hi = np.maximum.reduceat(tri_max, first_tri)
        corners = np.array([[i & 1, (i >> 1) & 1, (i >> 2) & 1] for i in range(8)], dtype=float)
        self._tile_corners = np.concatenate(
            [lo[:, None] + corners[None] * (hi - lo)[:, None], np.ones((len(keys), 8, 1))], axis=2
        )
        self._tile_centre = 0.5 * (lo + hi)
        self._tile_first = first_tri * 3
        self._tile_count = counts * 3
        self._tile_alpha = keys >= TILES_PER_SIDE * TILES_PER_SIDE

        self._vbo = self.ctx.buffer(vertices.tobytes())
        self._ibo = self.ctx.buffer(tris.astype(np.uint32).tobytes())

    def _vao(self, vs: str, fs: str, defines: tuple[str, ...]) -> moderngl.VertexArray:
        """Vertex array of the scene buffers bound to the program compiled with ``defines``."""
        key = (vs, fs, *defines)
        if key not in self._vaos:
            prog = self._program(vs, fs, defines)
            names = [n for n, _, _ in _ATTRIBUTES if n in prog]
            fmt = " ".join(fmt if n in prog else pad for n, fmt, pad in _ATTRIBUTES)
            self._vaos[key] = self.ctx.vertex_array(prog, [(self._vbo, fmt, *names)], self._ibo, 4)
        return self._vaos[key]

    def _body_vao(self, body: _Body, defines: tuple[str, ...]) -> moderngl.VertexArray:
        """Vertex array of a vehicle body's buffers bound to the program compiled with ``defines``."""
        if defines not in body.vaos:
            prog = self._program(_GEOMETRY_VS, _GEOMETRY_FS, defines)
            names = [n for n, _, _ in _ATTRIBUTES if n in prog]
            fmt = " ".join(fmt if n in prog else pad for n, fmt, pad in _ATTRIBUTES)
            body.vaos[defines] = self.ctx.vertex_array(prog, [(body.vbo, fmt, *names)], body.ibo, 4)
        return body.vaos[defines]

    def _render_shadow_map(self, size: int) -> None:
        """Orthographic depth map of the scene seen from the sun, rendered once (alpha-tested cards cast
        leaf-shaped shadows); slope-scaled polygon offset plus a normal offset at lookup avoid acne."""
        toward_sun = self._sun
        helper = np.array([0.0, 0.0, 1.0]) if abs(toward_sun[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
        right = np.cross(helper, toward_sun)
        right /= np.linalg.norm(right)
        up = np.cross(toward_sun, right)
        rows = np.stack([right, up, toward_sun])  # light space: x, y across the map, z towards the sun

        def light_box(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            box = np.array([[hi[i] if (k >> i) & 1 else lo[i] for i in range(3)] for k in range(8)]) @ rows.T
            return box.min(axis=0) - 0.1, box.max(axis=0) + 0.1

        # The map covers the geometry within the flyable bounds grown by SHADOW_MARGIN, so that a ground
        # plane running to the horizon does not dilute its resolution; fragments outside it are lit.
        lo, hi = self._bounds.copy()
        flyable = frames.zup_to_gl(np.stack([self.scene.bounds_min, self.scene.bounds_max]))
        for axis in (0, 2):  # GL ground axes
            a = max(lo[axis], flyable[:, axis].min() - SHADOW_MARGIN)
            b = min(hi[axis], flyable[:, axis].max() + SHADOW_MARGIN)
            if a < b:
                lo[axis], hi[axis] = a, b
        bmin, bmax = light_box(lo, hi)
        bmax[2] = light_box(*self._bounds)[1][2]  # every occluder on the sun's side still casts
        # World (GL) -> [0, 1]^3 map coordinates; depth 0 is nearest the sun.
        scale = np.diag(
            [1.0 / (bmax[0] - bmin[0]), 1.0 / (bmax[1] - bmin[1]), -1.0 / (bmax[2] - bmin[2]), 1.0]
        )
        offset = frames.make_transform(np.eye(3), [-bmin[0], -bmin[1], -bmax[2]])
        self._light = scale @ offset @ frames.make_transform(rows, np.zeros(3))
        to_clip = np.array([[2.0, 0, 0, -1], [0, 2.0, 0, -1], [0, 0, 2.0, -1], [0, 0, 0, 1]])
        texel = max(bmax[0] - bmin[0], bmax[1] - bmin[1]) / size
        self._normal_offset = 1.5 * texel

        self._shadow_map = self.ctx.depth_texture((size, size))
        self._shadow_map.compare_func = "<="
        self._shadow_map.filter = (moderngl.LINEAR, moderngl.LINEAR)
        self._shadow_map.repeat_x = self._shadow_map.repeat_y = False
        fbo = self.ctx.framebuffer(depth_attachment=self._shadow_map)
        fbo.use()
        fbo.clear(depth=1.0)
        self.ctx.enable_only(moderngl.DEPTH_TEST)
        self.ctx.depth_func = "<"
        self.ctx.polygon_offset = (2.0, 2.0)
        self._texture.use(0)
        for alpha, defines in ((False, ()), (True, ("ALPHA_TEST",))):
            vao = self._vao(_SHADOW_VS, _SHADOW_FS, defines)
            vao.program["u_light_clip"].write(_mat(to_clip @ self._light))
            if alpha:
                vao.program["u_texture"].value = 0
                vao.program["u_texture_size"].value = self._texture_size
            for first, count in zip(
                self._tile_first[self._tile_alpha == alpha],
                self._tile_count[self._tile_alpha == alpha],
                strict=True,
            ):
                vao.render(moderngl.TRIANGLES, vertices=int(count), first=int(first))
        self.ctx.polygon_offset = (0.0, 0.0)
        self.ctx.finish()
        fbo.release()

    # ------------------------------------------------------------------------------------ frames
    def _visible_tiles(self, view_proj: np.ndarray, eye: np.ndarray) -> np.ndarray:
        """Indices of the tiles intersecting the frustum, opaque first, each group nearest first."""
        clip = self._tile_corners @ view_proj.T
        w = clip[..., 3]
        outside = np.zeros(len(clip), dtype=bool)
        for axis in range(3):
            outside |= (clip[..., axis] > w).all(axis=1) | (clip[..., axis] < -w).all(axis=1)
        visible = np.flatnonzero(~outside)
        dist = np.linalg.norm(self._tile_centre[visible] - eye, axis=1)
        return visible[np.lexsort((dist, self._tile_alpha[visible]))]

    def render(self, T_world_body: np.ndarray, rgb: bool = True) -> dict[str, CameraFrame]:
        """Render every camera of the one rig (``cameras``) for the body pose ``T_world_body`` (4x4, Z-up
        world). With ``rgb=False`` only depth and segmentation are drawn and read back (faster)."""
        return self.render_rigs({"": T_world_body}, rgb)[""]

    def render_rigs(
        self, poses: dict[str, np.ndarray], rgb: bool = True, rigs: Collection[str] | None = None
    ) -> dict[str, dict[str, CameraFrame]]:
        """Render every camera of every rig in ``poses`` (vehicle -> body pose, 4x4, Z-up world) in one
        call, each vehicle's body drawn in the other vehicles' cameras: vehicle -> camera -> frame. With
        ``rigs``, only those vehicles' cameras (every body in ``poses`` is still drawn). The scene's
        buffers are shared by all; nothing is uploaded per frame but the poses."""
        if self.ctx is None:
            raise RuntimeError("renderer is closed")
        shoot = [v for v in poses if rigs is None or v in rigs]
        models = {v: frames.gl_model_matrix(T) for v, T in poses.items() if v in self._bodies}
        targets = [t for t in self.targets if t.vehicle in shoot]
        out: dict[str, dict[str, CameraFrame]] = {v: {} for v in shoot}
        with self.ctx:
            # Draw every camera before reading any back, so one camera's rasterisation overlaps the
            # next camera's vertex work (llvmpipe) or GPU execution (hardware drivers).
            drawn = [self._draw(t, poses[t.vehicle], rgb, models) for t in targets]
            for t, T_wo in zip(targets, drawn, strict=True):
                self._read(t, rgb)
                rgb_image = t.rgb if rgb else None
                frame = CameraFrame(t.cam.name, rgb_image, t.depth, t.seg, t.K.copy(), T_wo)
                out[t.vehicle][t.cam.name] = frame
        return out

    def _draw(
        self, t: _Target, T_world_body: np.ndarray, rgb: bool, models: dict[str, np.ndarray] | None = None
    ) -> np.ndarray:
        """Draw one camera's targets (the scene, then the other vehicles' bodies in ``models``); returns
        its ``T_world_optical``."""
        ctx = self.ctx
        T_wo = frames.T_world_optical(np.asarray(T_world_body, dtype=float), t.T_body_link)
        view = frames.gl_view_matrix(T_wo)
        eye = frames.zup_to_gl(T_wo[:3, 3])
        fbo = t.fbo_color if rgb else t.fbo_geometry
        fbo.use()
        fbo.clear(depth=1.0)
        ctx.enable_only(moderngl.DEPTH_TEST)
        ctx.depth_func = "<"
        self._texture.use(0)
        if self._shadow_map is not None:
            self._shadow_map.use(1)
        if self._n_triangles:
            tiles = self._visible_tiles(t.proj @ view, eye)
            for alpha in (False, True):  # opaque first: alpha-tested fragments then fail the depth test early
                defines = ("COLOR", "TEXCOORD", *self._fog_defines) if rgb else ()
                if rgb and self._shadow_map is not None:
                    defines += ("SHADOWS",)
                if alpha:
                    defines += ("ALPHA_TEST",) if rgb else ("TEXCOORD", "ALPHA_TEST")
                vao = self._vao(_GEOMETRY_VS, _GEOMETRY_FS, defines)
                self._set_uniforms(vao.program, view, t.proj, eye)
                for i in tiles[self._tile_alpha[tiles] == alpha]:
                    vao.render(
                        moderngl.TRIANGLES, vertices=int(self._tile_count[i]), first=int(self._tile_first[i])
                    )
        others = [v for v in (models or {}) if v != t.vehicle]
        if others:
            defines = ("COLOR", "TEXCOORD", "MODEL", *self._fog_defines) if rgb else ("MODEL",)
            if rgb and self._shadow_map is not None:
                defines += ("SHADOWS",)
            for v in others:
                vao = self._body_vao(self._bodies[v], defines)
                self._set_uniforms(vao.program, view, t.proj, eye)
                vao.program["u_model"].write(_mat(models[v]))
                vao.render(moderngl.TRIANGLES)
        ctx.depth_func = "<="
        sky = self._sky_vao if rgb else self._sky_geometry_vao
        if rgb and self._fog_defines:
            if self._sky_fog_vao is None:
                self._sky_fog_vao = ctx.vertex_array(self._program(_SKY_VS, _SKY_FS, ("COLOR", "FOG")), [])
            sky = self._sky_fog_vao
        if rgb:
            P = t.proj
            ray = np.array(
                [[1 / P[0, 0], 0, P[0, 2] / P[0, 0]], [0, 1 / P[1, 1], P[1, 2] / P[1, 1]], [0, 0, -1]]
            )
            sky.program["u_ray"].write(_mat(view[:3, :3].T @ ray))
            sky.program["u_zenith"].value = self._zenith
            sky.program["u_horizon"].value = self._horizon
            if self._fog_defines:
                for name in ("u_fog_beta", "u_fog_color", "u_fog_layer"):
                    sky.program[name].value = self._light_uniforms[name]
        sky.render(moderngl.TRIANGLES, vertices=3)
        return T_wo

    def _read(self, t: _Target, rgb: bool) -> None:
        """Read the camera's targets into its preallocated arrays (row 0 is already the top)."""
        if rgb:
            t.fbo_color.read_into(t.rgb, components=3, attachment=0)
            t.fbo_color.read_into(t.seg, components=1, attachment=1, dtype="u1")
            t.fbo_color.read_into(t.depth, components=1, attachment=2, dtype="f4")
        else:
            t.fbo_geometry.read_into(t.seg, components=1, attachment=0, dtype="u1")
            t.fbo_geometry.read_into(t.depth, components=1, attachment=1, dtype="f4")

    def _set_uniforms(
        self, prog: moderngl.Program, view: np.ndarray, proj: np.ndarray, eye: np.ndarray
    ) -> None:
        prog["u_view"].write(_mat(view))
        prog["u_proj"].write(_mat(proj))
        values = {
            "u_texture": 0,
            "u_texture_size": self._texture_size,
            "u_eye": tuple(eye),
            "u_sun": tuple(self._sun),
            "u_shadow_map": 1,
            "u_normal_offset": self._normal_offset,
        }
        for name, value in values.items():
            if name in prog:
                prog[name].value = value
        if "u_light" in prog:
            prog["u_light"].write(_mat(self._light))
        if "u_sun_color" in prog:  # colour programs only: the depth-only path sets nothing more
            for name, value in self._light_uniforms.items():
                if name in prog:
                    prog[name].value = value

    def render_top_down(
        self, xy_min: tuple[float, float], xy_max: tuple[float, float], width: int, height: int
    ) -> np.ndarray:
        """Orthographic view straight down on the world box ``xy_min`` .. ``xy_max`` (m): (H, W, 3) uint8.

        North (+y) is the top row and +x points right; pixel ``(u, v)`` covers world
        ``x = x_min + (u + 0.5) * (x_max - x_min) / W`` and ``y = y_max - (v + 0.5) * (y_max - y_min) / H``.
        Lit and shadowed like the cameras; where no geometry is hit the sky colour shows. Used for maps.
        """
        if self.ctx is None:
            raise RuntimeError("renderer is closed")
        x0, y0 = (float(v) for v in xy_min)
        x1, y1 = (float(v) for v in xy_max)
        if not (x1 > x0 and y1 > y0 and width > 0 and height > 0):
            raise ValueError(f"render_top_down needs a non-empty box and size, got {xy_min}..{xy_max}")
        top = float(self._bounds[1, 1]) + 10.0 if self._n_triangles else 10.0  # GL y is up
        depth = top - (float(self._bounds[0, 1]) if self._n_triangles else 0.0) + 10.0
        R = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])  # optical axes in the world
        T_wo = frames.make_transform(R, [(x0 + x1) / 2, (y0 + y1) / 2, top])
        view = frames.gl_view_matrix(T_wo)
        ortho = np.diag([2.0 / (x1 - x0), 2.0 / (y1 - y0), -2.0 / (depth - 0.1), 1.0])
        ortho[2, 3] = -(depth + 0.1) / (depth - 0.1)
        proj = _FLIP_Y @ ortho
        eye = frames.zup_to_gl(T_wo[:3, 3])
        rgb = np.empty((height, width, 3), dtype=np.uint8)
        with self.ctx:
            ctx = self.ctx
            color = ctx.renderbuffer((width, height), 4)
            seg = ctx.renderbuffer((width, height), 1, dtype="u1")
            dist = ctx.renderbuffer((width, height), 1, dtype="f4")
            zbuffer = ctx.depth_renderbuffer((width, height))
            fbo = ctx.framebuffer([color, seg, dist], zbuffer)
            try:
                fbo.use()
                fbo.clear(*self._zenith, 1.0, depth=1.0)
                ctx.enable_only(moderngl.DEPTH_TEST)
                ctx.depth_func = "<"
                self._texture.use(0)
                if self._shadow_map is not None:
                    self._shadow_map.use(1)
                if self._n_triangles:
                    tiles = self._visible_tiles(proj @ view, eye)
                    base = ("COLOR", "TEXCOORD") + (("SHADOWS",) if self._shadow_map is not None else ())
                    for alpha in (False, True):
                        vao = self._vao(_GEOMETRY_VS, _GEOMETRY_FS, base + (("ALPHA_TEST",) if alpha else ()))
                        self._set_uniforms(vao.program, view, proj, eye)
                        for i in tiles[self._tile_alpha[tiles] == alpha]:
                            vao.render(
                                moderngl.TRIANGLES,
                                vertices=int(self._tile_count[i]),
                                first=int(self._tile_first[i]),
                            )
                fbo.read_into(rgb, components=3, attachment=0)
            finally:
                for obj in (fbo, color, seg, dist, zbuffer):
                    obj.release()
        return rgb

    # ------------------------------------------------------------------------------------ lifetime
    def close(self) -> None:
        """Release every GL object (and the context when the renderer created it)."""
        if self.ctx is None:
            return
        with self.ctx:
            for t in self.targets:
                t.release()
            for body in set(self._bodies.values()):
                body.release()
            buffers = (
                getattr(self, "_vbo", None),
                getattr(self, "_ibo", None),
                self._texture,
                self._shadow_map,
            )
            for obj in (
                *self._vaos.values(),
                self._sky_vao,
                self._sky_geometry_vao,
                *([self._sky_fog_vao] if self._sky_fog_vao is not None else []),
                *self._programs.values(),
            ):
                obj.release()
            for obj in buffers:
                if obj is not None:
                    obj.release()
        if self._own_ctx:
            self.ctx.release()
        self.ctx = None

    def __enter__(self) -> Renderer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def fleet_renderer(scene: Scene, config: SimConfig) -> Renderer:
    """The renderer of every vehicle's camera rig in ``config``, each vehicle's body drawn in the others'
    cameras (one mesh per airframe; a vehicle alone never sees its own body)."""
    from droneulator.vehicles.params import get_params

    specs = config.vehicle_specs()
    meshes: dict[str, MeshPart] = {}
    bodies: dict[str, MeshPart] = {}
    for v in specs if len(specs) > 1 else ():
        airframe = v.params or config.vehicle.params
        if airframe not in meshes:
            meshes[airframe] = vehicle_mesh(get_params(airframe))
        bodies[v.name] = meshes[airframe]
    rc = config.render
    return Renderer(
        scene,
        rigs=config.camera_rigs(),
        bodies=bodies,
        shadows=rc.shadows,
        shadow_map_size=rc.shadow_map_size,
        light=config_lighting(scene, config),
    )


def config_lighting(scene: Scene, config: SimConfig) -> Lighting:
    """The light of ``scene`` under ``config.light``, the sun computed at ``config.site`` unless the light
    names its own place or clock."""
    return resolve_lighting(config.light, scene, config.site)
