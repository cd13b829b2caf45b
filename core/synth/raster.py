"""Offscreen rasterizer (moderngl, standalone EGL context) for the synthetic scenes.

Colour: Lambert + ambient shading of procedural textures (checker, stripes, noise, wood grain, printed
text), optional fine photographic grain and a Blinn-Phong specular highlight, supersampled 3x3 and
box-filtered.
Ground truth: z-depth (-z in camera coordinates, from the interpolated vertex position, float32) and
the object id, both taken from the centre subsample of each 3x3 block, which is exactly the pixel
centre (u + 0.5, v + 0.5), so they are not antialiased.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from repaint_nerf.core.synth.meshes import build
from repaint_nerf.core.synth.presets import TEXTURES, SceneObject

SUPERSAMPLE = 3  # odd, so the middle subsample of each block sits on the pixel centre

_VERT = """
#version 330
uniform mat4 model;
uniform mat4 view;
uniform mat4 proj;
uniform mat3 normal_mat;
in vec3 in_pos;
in vec3 in_normal;
out vec3 v_obj;
out vec3 v_obj_normal;
out vec3 v_world;
out vec3 v_normal;
out float v_zdepth;
void main() {
    vec4 w = model * vec4(in_pos, 1.0);
    vec4 c = view * w;
    v_obj = in_pos;
    v_obj_normal = in_normal;
    v_world = w.xyz;
    v_normal = normal_mat * in_normal;
    v_zdepth = -c.z;
    gl_Position = proj * c;
}
"""

_FRAG = """
#version 330
uniform vec3 color1;
uniform vec3 color2;
uniform int tex_kind;       // 0 plain, 1 checker, 2 stripes, 3 noise, 4 wood, 5 label (printed text)
uniform int uv_cylinder;    // label text wraps around z (cylinders) instead of lying on the faces
uniform float tex_scale;
uniform float grain;        // amplitude of fine multiplicative noise (photographic texture)
uniform float specular;     // strength of the white Blinn-Phong highlight
uniform vec3 tex_offset;
uniform float obj_id;
uniform vec3 cam_pos;
uniform vec3 light_dir0;
uniform vec3 light_dir1;
in vec3 v_obj;
in vec3 v_obj_normal;
in vec3 v_world;
in vec3 v_normal;
in float v_zdepth;
layout(location = 0) out vec4 out_color;
layout(location = 1) out vec2 out_gt;

float hash(ivec3 c) {
    uvec3 p = uvec3(c);
    uint h = p.x * 73856093u ^ p.y * 19349663u ^ p.z * 83492791u;
    h = (h ^ (h >> 16u)) * 0x45d9f3bu;
    h = (h ^ (h >> 16u)) * 0x45d9f3bu;
    h ^= h >> 16u;
    return float(h & 0xffffffu) / 16777215.0;
}

float value_noise(vec3 p) {
    ivec3 i = ivec3(floor(p));
    vec3 f = fract(p);
    f = f * f * (3.0 - 2.0 * f);
    float n000 = hash(i), n100 = hash(i + ivec3(1, 0, 0));
    float n010 = hash(i + ivec3(0, 1, 0)), n110 = hash(i + ivec3(1, 1, 0));
    float n001 = hash(i + ivec3(0, 0, 1)), n101 = hash(i + ivec3(1, 0, 1));
    float n011 = hash(i + ivec3(0, 1, 1)), n111 = hash(i + ivec3(1, 1, 1));
    return mix(mix(mix(n000, n100, f.x), mix(n010, n110, f.x), f.y),
               mix(mix(n001, n101, f.x), mix(n011, n111, f.x), f.y), f.z);
}

// Printed text: lines of 3x5-dot glyphs with word gaps, in (character, line) units.
float glyphs(vec2 uv) {
    vec2 cell = floor(uv);
    vec2 f = fract(uv);
    if (hash(ivec3(int(cell.x), int(cell.y), 7)) < 0.2) return 0.0;
    ivec2 px = ivec2(floor(vec2((f.x - 0.1) / 0.8 * 3.0, (f.y - 0.2) / 0.6 * 5.0)));
    if (px.x < 0 || px.x > 2 || px.y < 0 || px.y > 4) return 0.0;
    return step(0.45, hash(ivec3(int(cell.x), int(cell.y), 11 + px.x + 3 * px.y)));
}

// Label coordinates: around z for cylinders, else the plane of the face's dominant normal axis.
vec2 label_uv(vec3 p) {
    vec3 a = abs(v_obj_normal);
    if (uv_cylinder == 1 && a.z < 0.7) return vec2(atan(v_obj.y, v_obj.x) * length(v_obj.xy), v_obj.z) * tex_scale;
    if (a.z >= a.x && a.z >= a.y) return p.xy;
    return a.x >= a.y ? p.yz : p.xz;
}

float pattern(vec3 p) {
    if (tex_kind == 1) {
        ivec3 c = ivec3(floor(p));
        return float((c.x + c.y + c.z) & 1);
    }
    if (tex_kind == 2) {
        return step(0.5, fract(p.z + 0.35 * p.x));
    }
    if (tex_kind == 3) {
        float n = 0.55 * value_noise(p) + 0.3 * value_noise(2.03 * p) + 0.15 * value_noise(4.11 * p);
        return smoothstep(0.35, 0.65, n);
    }
    if (tex_kind == 4) {   // wood: growth rings around the x axis, warped, with fibres along x
        float r = length(p.yz) + 0.6 * value_noise(p * vec3(0.3, 1.5, 1.5));
        float rings = smoothstep(0.2, 0.8, abs(fract(r) * 2.0 - 1.0));
        float fibre = value_noise(p * vec3(0.8, 14.0, 14.0));
        return clamp(0.75 * rings + 0.45 * (fibre - 0.5), 0.0, 1.0);
    }
    if (tex_kind == 5) {   // label: a heading line of large glyphs, a coloured band, then small text
        vec2 uv = label_uv(p);
        float line = fract(uv.y / 6.0) * 6.0;
        if (line < 1.0) return 1.0;                                  // band
        if (line < 2.8) return glyphs(vec2(uv.x * 0.8, (line - 1.0) / 1.8)); // heading
        return glyphs(vec2(uv.x * 2.2, (line - 2.8) * 1.6));          // body text
    }
    return 0.0;
}

void main() {
    vec3 n = normalize(v_normal);
    if (dot(n, cam_pos - v_world) < 0.0) n = -n;   // two-sided: room walls are seen from inside
    float shade = 0.35 + 0.55 * max(dot(n, light_dir0), 0.0) + 0.2 * max(dot(n, light_dir1), 0.0);
    vec3 albedo = mix(color1, color2, pattern(v_obj * tex_scale + tex_offset));
    if (grain > 0.0) {
        float g = 0.6 * value_noise(v_obj * 45.0 + tex_offset) + 0.4 * value_noise(v_obj * 110.0);
        albedo *= 1.0 + grain * (2.0 * g - 1.0);
    }
    vec3 rgb = albedo * shade;
    if (specular > 0.0) {
        vec3 h = normalize(light_dir0 + normalize(cam_pos - v_world));
        rgb += specular * pow(max(dot(n, h), 0.0), 48.0);
    }
    out_color = vec4(min(rgb, vec3(1.0)), 1.0);
    out_gt = vec2(v_zdepth, obj_id);
}
"""

# Reduces each SUPERSAMPLE x SUPERSAMPLE block to one pixel: colour box-filtered (premultiplied, then
# back to straight alpha), ground truth copied from the middle subsample (the pixel centre).
_RESOLVE_VERT = """
#version 330
void main() {
    vec2 p = vec2((gl_VertexID << 1) & 2, gl_VertexID & 2);
    gl_Position = vec4(p * 2.0 - 1.0, 0.0, 1.0);
}
"""

_RESOLVE_FRAG = """
#version 330
uniform sampler2D color_ss;
uniform sampler2D gt_ss;
uniform int ss;
layout(location = 0) out vec4 out_color;
layout(location = 1) out vec2 out_gt;
void main() {
    ivec2 base = ivec2(gl_FragCoord.xy) * ss;
    vec4 acc = vec4(0.0);
    for (int j = 0; j < ss; ++j)
        for (int i = 0; i < ss; ++i) {
            vec4 c = texelFetch(color_ss, base + ivec2(i, j), 0);
            acc += vec4(c.rgb * c.a, c.a);
        }
    acc /= float(ss * ss);
    out_color = vec4(acc.a > 0.0 ? acc.rgb / acc.a : vec3(0.0), acc.a);
    out_gt = texelFetch(gt_ss, base + ivec2(ss / 2), 0).xy;
}
"""

_LIGHTS = (np.array([0.45, 0.3, 0.84]), np.array([-0.6, -0.5, 0.3]))


def projection(fx: float, fy: float, cx: float, cy: float, width: int, height: int,
               near: float, far: float) -> np.ndarray:
    """OpenGL clip matrix of a pinhole camera: pixel (u, v) centres at +0.5, v down, like Cameras.project."""
    return np.array([
        [2 * fx / width, 0.0, 1.0 - 2 * cx / width, 0.0],
        [0.0, 2 * fy / height, 2 * cy / height - 1.0, 0.0],
        [0.0, 0.0, -(far + near) / (far - near), -2 * far * near / (far - near)],
        [0.0, 0.0, -1.0, 0.0],
    ])


@dataclass
class Frame:
    """One rendered view: straight-alpha RGBA uint8 (H,W,4), z-depth float32 (H,W), object ids uint8 (H,W)."""

    rgba: np.ndarray
    depth: np.ndarray
    mask: np.ndarray


_egl_used = False  # a standalone EGL context exists in this process (Mesa then refuses GLX ones)


def egl_context_made() -> bool:
    """Whether this process has created the rasterizer's EGL context: with Mesa, a GLX context made after it
    fails (BadAccess in glXMakeCurrent), so a window opened later must use EGL too."""
    return _egl_used


def standalone_context(require: int = 330):
    """A headless moderngl context on EGL, noted so that a window opened later in this process uses EGL as well."""
    import moderngl

    global _egl_used
    _egl_used = True
    return moderngl.create_standalone_context(backend="egl", require=require)


class Rasterizer:
    """Renders lists of SceneObject from pinhole cameras with one standalone EGL context (use as a context manager)."""

    def __init__(self, width: int, height: int, near: float = 0.05, far: float = 50.0):
        self.width, self.height, self.near, self.far = width, height, near, far
        self.ctx = standalone_context()
        self.prog = self.ctx.program(vertex_shader=_VERT, fragment_shader=_FRAG)
        s = SUPERSAMPLE
        self.color = self.ctx.texture((width * s, height * s), 4, dtype="f4")
        self.gt = self.ctx.texture((width * s, height * s), 2, dtype="f4")
        self.depth_rb = self.ctx.depth_renderbuffer((width * s, height * s))
        self.fbo = self.ctx.framebuffer([self.color, self.gt], self.depth_rb)
        self.resolve_prog = self.ctx.program(vertex_shader=_RESOLVE_VERT, fragment_shader=_RESOLVE_FRAG)
        self.resolve_prog["color_ss"].value = 0
        self.resolve_prog["gt_ss"].value = 1
        self.resolve_prog["ss"].value = s
        self.resolve_vao = self.ctx.vertex_array(self.resolve_prog, [])
        self.out_color = self.ctx.texture((width, height), 4, dtype="f4")
        self.out_gt = self.ctx.texture((width, height), 2, dtype="f4")
        self.out_fbo = self.ctx.framebuffer([self.out_color, self.out_gt])
        self._vaos: dict = {}

    def __enter__(self) -> "Rasterizer":
        return self

    def __exit__(self, *exc) -> None:
        self.release()

    def release(self) -> None:
        """Free the GL objects and the context."""
        for vao, vbo, ibo in self._vaos.values():
            vao.release()
            vbo.release()
            ibo.release()
        self._vaos.clear()
        for obj in (self.resolve_vao, self.resolve_prog, self.out_fbo, self.out_color, self.out_gt):
            obj.release()
        self.fbo.release()
        self.color.release()
        self.gt.release()
        self.depth_rb.release()
        self.prog.release()
        self.ctx.release()

    def _vao(self, obj: SceneObject):
        key = (obj.mesh, tuple(sorted(obj.params.items())))
        if key not in self._vaos:
            verts, idx = build(obj.mesh, **obj.params)
            vbo = self.ctx.buffer(np.ascontiguousarray(verts, dtype="f4").tobytes())
            ibo = self.ctx.buffer(np.ascontiguousarray(idx, dtype="u4").tobytes())
            vao = self.ctx.vertex_array(self.prog, [(vbo, "3f 3f", "in_pos", "in_normal")], ibo, index_element_size=4)
            self._vaos[key] = (vao, vbo, ibo)
        return self._vaos[key][0]

    def render(self, objects: list[SceneObject], c2w: np.ndarray, fx: float, fy: float, cx: float,
               cy: float, ids: list[int] | None = None) -> Frame:
        """Render `objects` (ids 1..n unless `ids` is given) from the OpenGL camera-to-world pose `c2w`."""
        import moderngl

        s = SUPERSAMPLE
        w, h = self.width, self.height
        proj = projection(fx * s, fy * s, cx * s, cy * s, w * s, h * s, self.near, self.far)
        view = np.linalg.inv(np.asarray(c2w, dtype=np.float64))
        self.fbo.use()
        self.fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
        self.ctx.enable(moderngl.DEPTH_TEST)
        self.ctx.disable(moderngl.CULL_FACE)
        p = self.prog
        p["view"].write(view.T.astype("f4").tobytes())
        p["proj"].write(proj.T.astype("f4").tobytes())
        p["cam_pos"].value = tuple(float(x) for x in c2w[:3, 3])
        for i, light in enumerate(_LIGHTS):
            p[f"light_dir{i}"].value = tuple(float(x) for x in light / np.linalg.norm(light))
        for k, obj in enumerate(objects):
            model = model_matrix(obj)
            normal_mat = np.linalg.inv(model[:3, :3]).T
            p["model"].write(model.T.astype("f4").tobytes())
            p["normal_mat"].write(normal_mat.T.astype("f4").tobytes())
            p["color1"].value = tuple(float(c) for c in obj.color)
            p["color2"].value = tuple(float(c) for c in obj.second_color())
            p["tex_kind"].value = TEXTURES.index(obj.texture)
            p["tex_scale"].value = float(obj.texture_scale)
            p["uv_cylinder"].value = int(obj.mesh == "cylinder")
            p["grain"].value = float(obj.grain)
            p["specular"].value = float(obj.specular)
            p["tex_offset"].value = (0.137 + 0.31 * k, 0.271, 0.419)  # keeps pattern edges off flat faces
            p["obj_id"].value = float(ids[k] if ids is not None else k + 1)
            self._vao(obj).render(moderngl.TRIANGLES)
        self.ctx.disable(moderngl.DEPTH_TEST)
        self.out_fbo.use()
        self.color.use(0)
        self.gt.use(1)
        self.resolve_vao.render(moderngl.TRIANGLES, vertices=3)
        color = np.frombuffer(self.out_color.read(), dtype="f4").reshape(h, w, 4)[::-1]
        gt = np.frombuffer(self.out_gt.read(), dtype="f4").reshape(h, w, 2)[::-1]
        rgba = np.round(np.clip(color, 0.0, 1.0) * 255).astype(np.uint8)
        return Frame(rgba, np.ascontiguousarray(gt[..., 0]), np.round(gt[..., 1]).astype(np.uint8))


def model_matrix(obj: SceneObject) -> np.ndarray:
    """Object-to-world 4x4: rotation by `yaw` about +z, then translation to `position`."""
    a = np.radians(obj.yaw)
    m = np.eye(4)
    m[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    m[:3, 3] = obj.position
    return m


def world_bbox(obj: SceneObject) -> np.ndarray:
    """World-space axis-aligned bounding box of an object's mesh: [[min xyz], [max xyz]]."""
    verts, _ = build(obj.mesh, **obj.params)
    pts = verts[:, :3].astype(np.float64) @ model_matrix(obj)[:3, :3].T + obj.position
    return np.stack([pts.min(0), pts.max(0)])
