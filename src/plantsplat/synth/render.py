"""Rasterise the synthetic scene with moderngl (OpenGL 3.3 core on EGL; Mesa llvmpipe on the CPU).

Two passes per frame, both from the same vertex buffer and the same projection:

- colour: 4x MSAA (anti-aliasing), linear radiance in a half-float target: textured albedo (sRGB
  decoded), a shadow-mapped directional key light, a fill light, hemisphere ambient, a specular lobe on
  the fruit and some light transmitted through back-lit leaves; resolved to one sample per pixel;
- id: no MSAA, one class id per pixel: the mask rule is "the surface seen through the pixel centre".

Projection matches OpenCV exactly: pixel (u, v) centre at integer coordinates, ``u = fx X/Z + cx``,
rows counted from the top. The GL image is flipped to top-down rows when read back.

Usage:
    r = Renderer(meshes, layers, intr, lights)
    # rgb_linear [H, W, 3] float32 (linear radiance), ids [H, W] uint8 (class per pixel)
    rgb_linear, ids = r.render(c2w)
"""

from __future__ import annotations

import moderngl
import numpy as np

from plantsplat.errors import PlantsplatError
from plantsplat.synth import textures as T
from plantsplat.synth.mesh import FLOOR, LEAF, WALL, Mesh

_VS = """
#version 330
uniform mat4 u_mvp;
uniform mat4 u_light_mvp;
in vec3 in_pos; in vec3 in_nrm; in vec2 in_uv; in vec3 in_col; in float in_layer; in float in_cls; in float in_spec;
out vec3 v_pos; out vec3 v_nrm; out vec2 v_uv; out vec3 v_col; flat out float v_layer; flat out float v_cls;
out float v_spec; out vec4 v_lpos;
void main() {
    gl_Position = u_mvp * vec4(in_pos, 1.0);
    v_pos = in_pos; v_nrm = in_nrm; v_uv = in_uv; v_col = in_col; v_layer = in_layer; v_cls = in_cls;
    v_spec = in_spec; v_lpos = u_light_mvp * vec4(in_pos, 1.0);
}
"""

_FS = """
#version 330
uniform sampler2DArray u_tex;
uniform sampler2DShadow u_shadow;
uniform vec3 u_eye;
uniform vec3 u_key_dir; uniform vec3 u_key_col; uniform vec3 u_fill_dir; uniform vec3 u_fill_col;
uniform vec3 u_sky; uniform vec3 u_ground;
uniform float u_leaf_top; uniform float u_leaf_bottom; uniform float u_leaf_cls;
in vec3 v_pos; in vec3 v_nrm; in vec2 v_uv; in vec3 v_col; flat in float v_layer; flat in float v_cls;
in float v_spec; in vec4 v_lpos;
out vec4 f_color;
void main() {
    float ln = length(v_nrm);
    vec3 N = ln > 1e-6 ? v_nrm / ln : vec3(0.0, 0.0, 1.0);   // interpolated normals can cancel out
    vec3 V = normalize(u_eye - v_pos);
    float layer = v_layer;
    vec3 tint = v_col;
    if (dot(N, V) < 0.0) {            // two-sided surfaces: light the side we see
        N = -N;
        if (abs(layer - u_leaf_top) < 0.5) { layer = u_leaf_bottom; tint = min(tint * 1.35, vec3(1.0)); }
    }
    // MSAA evaluates attributes at the pixel centre, possibly outside the triangle: clamp extrapolations
    vec3 albedo = pow(clamp(texture(u_tex, vec3(v_uv, layer)).rgb, 0.0, 1.0), vec3(2.2))
                * pow(clamp(tint, 0.0, 1.0), vec3(2.2));
    vec3 lp = v_lpos.xyz / v_lpos.w * 0.5 + 0.5;
    float sh = 1.0;
    if (lp.x > 0.0 && lp.x < 1.0 && lp.y > 0.0 && lp.y < 1.0 && lp.z < 1.0) {
        sh = texture(u_shadow, vec3(lp.xy, lp.z - 0.0004));  // 2x2 PCF by the linear compare filter
    }
    float ndl = dot(N, u_key_dir);
    vec3 hemi = mix(u_ground, u_sky, 0.5 + 0.5 * N.z);
    vec3 light = u_key_col * max(ndl, 0.0) * sh + u_fill_col * max(dot(N, u_fill_dir), 0.0) + hemi;
    if (abs(v_cls - u_leaf_cls) < 0.5 && ndl < 0.0)   // light through a back-lit leaf
        light += 0.35 * u_key_col * (-ndl) * sh * vec3(0.8, 1.0, 0.5);
    vec3 Hv = u_key_dir + V;
    vec3 H = dot(Hv, Hv) > 1e-12 ? normalize(Hv) : N;
    float spec = v_spec * pow(max(dot(N, H), 0.0), 60.0) * sh * step(0.0, ndl);
    f_color = vec4(max(albedo * light + spec * u_key_col, vec3(0.0)), 1.0);
}
"""

_FS_ID = """
#version 330
flat in float v_cls;
in vec3 v_pos; in vec3 v_nrm; in vec2 v_uv; in vec3 v_col; flat in float v_layer; in float v_spec; in vec4 v_lpos;
out vec4 f_id;
void main() { f_id = vec4(v_cls / 255.0, 0.0, 0.0, 1.0); }
"""

_VS_SHADOW = """
#version 330
uniform mat4 u_light_mvp;
in vec3 in_pos;
void main() { gl_Position = u_light_mvp * vec4(in_pos, 1.0); }
"""
_FS_SHADOW = """
#version 330
void main() { }
"""


def projection(intr: dict, near: float = 1.0, far: float = 3000.0) -> np.ndarray:
    """OpenGL clip matrix for OpenCV camera coordinates (x right, y down, z forward) and OpenCV pixels.

    ``x_ndc = 2 (u + 0.5) / W - 1`` and ``y_ndc = 1 - 2 (v + 0.5) / H``: pixel (u, v) centre at integer
    coordinates, row 0 at the top of the (flipped) read-back image.
    """
    W, H = intr["width"], intr["height"]
    fx, fy, cx, cy = intr["fx"], intr["fy"], intr["cx"], intr["cy"]
    A = (far + near) / (far - near)
    B = -2 * far * near / (far - near)
    return np.array([
        [2 * fx / W, 0, 2 * (cx + 0.5) / W - 1, 0],
        [0, -2 * fy / H, 1 - 2 * (cy + 0.5) / H, 0],
        [0, 0, A, B],
        [0, 0, 1, 0],
    ])


def _pack(meshes: list[Mesh]) -> tuple[np.ndarray, np.ndarray]:
    verts, faces, off = [], [], 0
    for m in meshes:
        n = len(m.v)
        attrs = np.concatenate([m.v, m.n, m.uv, m.col, np.full((n, 1), m.layer), np.full((n, 1), m.cls),
                                np.full((n, 1), m.spec)], axis=1)
        verts.append(attrs)
        faces.append(m.f + off)
        off += n
    return np.concatenate(verts).astype("f4"), np.concatenate(faces).astype("u4")


def _look_dir_matrix(direction: np.ndarray, centre: np.ndarray, radius: float) -> np.ndarray:
    """Orthographic light view-projection looking along ``-direction`` at a sphere (centre, radius)."""
    d = direction / np.linalg.norm(direction)
    eye = centre + d * radius * 3
    z = -d
    x = np.cross(z, [0.0, 0.0, 1.0]) if abs(z[2]) < 0.99 else np.cross(z, [1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    view = np.eye(4)
    view[:3, :3] = np.stack([x, y, z])
    view[:3, 3] = -view[:3, :3] @ eye
    near, far = radius, radius * 5
    ortho = np.diag([1 / radius, 1 / radius, 2 / (far - near), 1.0])
    ortho[2, 3] = -(far + near) / (far - near)
    return ortho @ view


def _set(prog, name: str, value) -> None:
    if name in prog:  # the GLSL compiler drops unused uniforms
        prog[name].value = value


class Renderer:
    """Owns one headless GL context, the scene's buffers, the texture array and the shadow map."""

    def __init__(self, meshes: list[Mesh], layers: np.ndarray, intr: dict, lights: dict, samples: int = 4,
                 shadow_centre=(0.0, 0.0, 10.0), shadow_radius: float = 150.0, shadow_size: int = 4096,
                 object_classes: tuple[int, ...] = ()):
        try:
            self.ctx = moderngl.create_standalone_context(backend="egl")
        except Exception as exc:  # no EGL / Mesa
            raise PlantsplatError(
                f"headless OpenGL (EGL) is not available ({exc}); install Mesa EGL "
                "(Debian: libegl1 libegl-mesa0 libgl1-mesa-dri libgbm1) and check with `plantsplat doctor`") from exc
        ctx = self.ctx
        self.intr = intr
        W, H = intr["width"], intr["height"]
        samples = int(min(samples, ctx.max_samples))
        self.samples = samples
        verts, faces = _pack(meshes)
        self.vbo = ctx.buffer(verts.tobytes())
        self.ibo = ctx.buffer(faces.tobytes())
        fmt = "3f 3f 2f 3f 1f 1f 1f"
        names = ["in_pos", "in_nrm", "in_uv", "in_col", "in_layer", "in_cls", "in_spec"]
        self.prog = ctx.program(vertex_shader=_VS, fragment_shader=_FS)
        self.prog_id = ctx.program(vertex_shader=_VS, fragment_shader=_FS_ID)
        self.vao = ctx.vertex_array(self.prog, [(self.vbo, fmt, *names)], self.ibo, skip_errors=True)
        self.vao_id = ctx.vertex_array(self.prog_id, [(self.vbo, fmt, *names)], self.ibo, skip_errors=True)
        self.vao_obj = None  # the meshes of `object_classes` alone, for render_objects
        if object_classes:
            ov, of = _pack([m for m in meshes if m.cls in object_classes])
            self.vbo_obj, self.ibo_obj = ctx.buffer(ov.tobytes()), ctx.buffer(of.tobytes())
            self.vao_obj = ctx.vertex_array(self.prog, [(self.vbo_obj, fmt, *names)], self.ibo_obj, skip_errors=True)
        # shadow casters: everything but the room shell
        casters = [m for m in meshes if m.cls not in (WALL, FLOOR)]
        cv, cf = _pack(casters)
        self.vbo_sh = ctx.buffer(cv[:, :3].copy().tobytes())
        self.ibo_sh = ctx.buffer(cf.tobytes())
        self.prog_sh = ctx.program(vertex_shader=_VS_SHADOW, fragment_shader=_FS_SHADOW)
        self.vao_sh = ctx.vertex_array(self.prog_sh, [(self.vbo_sh, "3f", "in_pos")], self.ibo_sh)
        # textures
        n, s = layers.shape[0], layers.shape[1]
        self.tex = ctx.texture_array((s, s, n), 3, np.ascontiguousarray(layers).tobytes())
        self.tex.build_mipmaps()
        self.tex.filter = (moderngl.LINEAR_MIPMAP_LINEAR, moderngl.LINEAR)
        self.tex.repeat_x = self.tex.repeat_y = True
        # shadow map (static scene and light: rendered once)
        light_mvp = _look_dir_matrix(np.asarray(lights["key_dir"]), np.asarray(shadow_centre, float), shadow_radius)
        self.shadow = ctx.depth_texture((shadow_size, shadow_size))
        self.shadow.compare_func = "<="
        self.shadow.filter = (moderngl.LINEAR, moderngl.LINEAR)
        fbo_sh = ctx.framebuffer(depth_attachment=self.shadow)
        fbo_sh.use()
        fbo_sh.clear(depth=1.0)
        ctx.enable(moderngl.DEPTH_TEST)
        self.prog_sh["u_light_mvp"].write(light_mvp.T.astype("f4").tobytes())
        self.vao_sh.render(moderngl.TRIANGLES)
        if "u_light_mvp" in self.prog:
            self.prog["u_light_mvp"].write(light_mvp.T.astype("f4").tobytes())
        for k, name in (("key_dir", "u_key_dir"), ("key_colour", "u_key_col"), ("fill_dir", "u_fill_dir"),
                        ("fill_colour", "u_fill_col"), ("sky_colour", "u_sky"), ("ground_colour", "u_ground")):
            _set(self.prog, name, tuple(float(x) for x in lights[k]))
        _set(self.prog, "u_leaf_top", float(T.LEAF_TOP))
        _set(self.prog, "u_leaf_bottom", float(T.LEAF_BOTTOM))
        _set(self.prog, "u_leaf_cls", float(LEAF))
        _set(self.prog, "u_tex", 0)
        _set(self.prog, "u_shadow", 1)
        # render targets
        self.fbo_ms = ctx.framebuffer(ctx.renderbuffer((W, H), 4, samples=samples, dtype="f2"),
                                      ctx.depth_renderbuffer((W, H), samples=samples))
        self.fbo_res = ctx.framebuffer(ctx.renderbuffer((W, H), 4, dtype="f2"))
        self.fbo_id = ctx.framebuffer(ctx.renderbuffer((W, H), 1, dtype="f1"), ctx.depth_renderbuffer((W, H)))
        self.P = projection(intr)

    def render(self, c2w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Render one view: ``(linear RGB [H, W, 3] float32, class ids [H, W] uint8)``, rows top-down."""
        W, H = self.intr["width"], self.intr["height"]
        rgb = self._colour(c2w, self.vao)
        self.prog_id["u_mvp"].write(self._mvp(c2w))
        self.fbo_id.use()
        self.fbo_id.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
        self.vao_id.render(moderngl.TRIANGLES)
        ids = np.frombuffer(self.fbo_id.read(components=1, dtype="f1"), dtype=np.uint8).reshape(H, W)[::-1]
        return np.ascontiguousarray(rgb), np.ascontiguousarray(ids)

    def render_objects(self, c2w: np.ndarray) -> np.ndarray:
        """The colour pass of the ``object_classes`` meshes alone over black (linear RGB ``[H, W, 3]``; lit and
        shadowed as in :meth:`render`, so they match it wherever nothing of the rest stands in front)."""
        if self.vao_obj is None:
            raise ValueError("Renderer(..., object_classes=...) was not given")
        return self._colour(c2w, self.vao_obj)

    def _mvp(self, c2w: np.ndarray) -> bytes:
        return (self.P @ np.linalg.inv(c2w)).T.astype("f4").tobytes()

    def _colour(self, c2w: np.ndarray, vao) -> np.ndarray:
        ctx = self.ctx
        W, H = self.intr["width"], self.intr["height"]
        ctx.enable(moderngl.DEPTH_TEST)
        ctx.disable(moderngl.CULL_FACE)
        self.tex.use(0)
        self.shadow.use(1)
        self.prog["u_mvp"].write(self._mvp(c2w))
        _set(self.prog, "u_eye", tuple(float(x) for x in c2w[:3, 3]))
        self.fbo_ms.use()
        self.fbo_ms.clear(0.0, 0.0, 0.0, 1.0, depth=1.0)
        vao.render(moderngl.TRIANGLES)
        ctx.copy_framebuffer(self.fbo_res, self.fbo_ms)
        rgb = np.frombuffer(self.fbo_res.read(components=3, dtype="f4"), dtype="f4").reshape(H, W, 3)[::-1]
        return np.ascontiguousarray(rgb)

    def release(self) -> None:
        self.ctx.release()
