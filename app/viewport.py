"""The viewport's GPU side: textures streamed from the worker, drawn with the shaders in `shaders/`.

Each view mode is one fragment shader over the same full-target triangle. The frame is drawn into an
offscreen framebuffer, which the window blits to the screen, opaque, before imgui draws its windows over it.
The similarity map is a float texture and the threshold a uniform: moving the slider redraws, it does not
re-render. The mask overlay thresholds the similarity where the selection's region reaches (grown
from its anchors, not across depth edges, as the masks grow it), so it shows the object, not its colour.
"""
from __future__ import annotations

import re
from pathlib import Path

import moderngl
import numpy as np

SHADER_DIR = Path(__file__).resolve().parent.parent / "shaders"
MODES = ("rgb", "depth", "feature", "similarity", "mask")
MODE_LABELS = {"rgb": "RGB", "depth": "Depth", "feature": "Feature (PCA)", "similarity": "Similarity",
               "mask": "Mask overlay"}


def load_shader(name: str, shader_dir: Path = SHADER_DIR) -> str:
    """Read a GLSL file and expand `#include "file"` lines (one level is all the shaders use)."""
    text = (shader_dir / name).read_text()
    return re.sub(r'^#include\s+"([^"]+)"\s*$', lambda m: (shader_dir / m.group(1)).read_text(), text,
                  flags=re.MULTILINE)


# Modes drawn at the render's own resolution, then stretched: for rgb this equals drawing at the viewport's
# size (both interpolate bilinearly), for the colour maps it differs only between render pixels, and the pass
# costs 20x less on a software rasterizer.
# The similarity and mask modes threshold an interpolated map: drawn at the viewport's size for smooth edges.
PER_PIXEL_MODES = ("rgb", "depth", "feature")


DISPLAY_SAMPLES = 1 << 16  # pixels a display range is read from: a percentile of 600k values took the UI 6 ms


def _percentiles(values: np.ndarray, qs: tuple[float, float]) -> np.ndarray:
    """`qs` percentiles of `values` (N, ...) along axis 0, from at most DISPLAY_SAMPLES evenly strided rows."""
    step = max(1, len(values) // DISPLAY_SAMPLES)
    return np.percentile(values[::step], qs, axis=0)


def display_frame(frame: dict) -> dict:
    """A render made ready to show, on the thread that rendered it: 'rgb' as uint8 (a quarter of the upload), and
    the depth and feature maps' display ranges (1st to 99th percentile) as 'depth_range' and 'feature_range'.
    'depth_range' is always set (None without a depth map): `Viewport.upload_frame` reads it as the mark of a frame
    made ready."""
    rgb = frame.get("rgb")
    if rgb is not None and rgb.dtype != np.uint8:
        frame["rgb"] = (np.clip(rgb, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    d = frame.get("depth")
    if d is not None:
        sample = d.reshape(-1)[::max(1, d.size // DISPLAY_SAMPLES)]
        valid = sample[sample > 0]
        if valid.size:
            lo, hi = np.percentile(valid, (1, 99))
            frame["depth_range"] = (float(lo), float(hi) + 1e-6)
    f = frame.get("feature_pca")
    if f is not None:
        lo, hi = _percentiles(f.reshape(-1, 3), (1, 99))
        frame["feature_range"] = (tuple(map(float, lo)), tuple(map(float, hi)))
    frame.setdefault("depth_range", None)
    return frame


class Viewport:
    """Holds the latest frame's textures and draws one view mode of it into a texture for imgui."""

    def __init__(self, ctx: moderngl.Context, shader_dir: Path = SHADER_DIR):
        self.ctx = ctx
        vert = load_shader("viewport.vert", shader_dir)
        self.programs = {m: ctx.program(vertex_shader=vert, fragment_shader=load_shader(f"{m}.frag", shader_dir))
                         for m in MODES}
        self.vaos = {m: ctx.vertex_array(p, []) for m, p in self.programs.items()}
        self.textures: dict[str, moderngl.Texture] = {}
        self._pending: dict[str, np.ndarray] = {}  # content not uploaded yet (`_upload`)
        self.fbo: moderngl.Framebuffer | None = None
        self.color: moderngl.Texture | None = None
        self.depth_range = (0.0, 1.0)
        self.feature_range = ((0.0,) * 3, (1.0,) * 3)
        self.frame_size: tuple[int, int] | None = None  # (w, h) of the last uploaded render
        self._uploads = 0  # bumped by every upload: the drawn texture is stale
        self._drawn: tuple | None = None  # what the viewport texture shows now

    def has(self, name: str) -> bool:
        return name in self.textures or name in self._pending

    def _upload(self, name: str, data: np.ndarray) -> None:
        """Keep `data` as texture `name`'s next content; it goes to the GPU when a draw first reads it (`_texture`):
        a frame's depth and feature maps are drawn only in their own view modes (at 780 px their 10 MB of floats
        cost the UI thread about 3 ms a frame)."""
        self._pending[name] = data
        self._uploads += 1

    def _texture(self, name: str) -> moderngl.Texture:
        """Texture `name`, its pending content uploaded first: uint8 as normalised bytes (a quarter of a float's
        upload), anything else as float32."""
        data = self._pending.pop(name, None)
        if data is None:
            return self.textures[name]
        dtype = "f1" if data.dtype == np.uint8 else "f4"
        data = np.ascontiguousarray(data, dtype=np.uint8 if dtype == "f1" else np.float32)
        h, w = data.shape[:2]
        comps = 1 if data.ndim == 2 else data.shape[2]
        tex = self.textures.get(name)
        if tex is None or tex.size != (w, h) or tex.components != comps or tex.dtype != dtype:
            if tex is not None:
                tex.release()
            tex = self.ctx.texture((w, h), comps, dtype=dtype)
            tex.filter = (moderngl.LINEAR, moderngl.LINEAR)
            tex.repeat_x = tex.repeat_y = False
            self.textures[name] = tex
        tex.write(data)
        return tex

    def upload_frame(self, frame: dict) -> None:
        """Take a render from the worker: 'rgb' (H,W,3; uint8 or float in [0, 1]), optional 'depth' (H,W),
        'feature_pca' (H,W,3), 'similarity' (H,W) and 'region', and the display ranges `display_frame` put there
        (computed here when missing)."""
        if "depth_range" not in frame:  # not made ready by the worker
            frame = display_frame(dict(frame))
        if "rgb" in frame:
            rgb = frame["rgb"]
            self._upload("rgb", rgb)
            self.frame_size = (rgb.shape[1], rgb.shape[0])
        if frame.get("depth") is not None:
            self._upload("depth", frame["depth"])
            self.depth_range = frame.get("depth_range") or self.depth_range
        if frame.get("feature_pca") is not None:
            self._upload("feature", frame["feature_pca"])
            self.feature_range = frame.get("feature_range") or self.feature_range
        if frame.get("similarity") is not None:
            self.upload_similarity(frame["similarity"], frame.get("region"))

    def upload_similarity(self, sim: np.ndarray | None, region: np.ndarray | None = None) -> None:
        """The similarity map (None clears it) and the overlay's map (the similarity where the selection's region
        reaches, Selection.region_map): the mask mode thresholds the latter when there is one."""
        for name, data in (("sim", sim), ("region", None if sim is None else region)):
            if data is None:
                tex = self.textures.pop(name, None)
                if tex is not None:
                    tex.release()
                if self._pending.pop(name, None) is not None or tex is not None:
                    self._uploads += 1
            else:
                self._upload(name, data)

    def available_modes(self) -> list[str]:
        need = {"rgb": ["rgb"], "depth": ["depth"], "feature": ["feature"], "similarity": ["sim"], "mask": ["rgb", "sim"]}
        return [m for m in MODES if all(self.has(n) for n in need[m])]

    def draw(self, size: tuple[int, int], mode: str, threshold: float = 0.5) -> moderngl.Texture | None:
        """Draw `mode` for a viewport of `size` (w, h) pixels into the viewport texture and return it (None before
        a first frame); the caller shows the texture stretched over the viewport."""
        if mode not in self.available_modes():
            mode = "rgb"
        if not self.has("rgb"):
            return None
        w, h = max(int(size[0]), 1), max(int(size[1]), 1)
        if mode in PER_PIXEL_MODES and self.frame_size is not None:
            w, h = self.frame_size  # colour maps of the render itself: imgui's bilinear upsampling does the rest
        state = (mode, float(threshold), w, h, self._uploads, self.depth_range, self.feature_range)
        if state == self._drawn and self.color is not None:
            return self.color  # unchanged: on a software rasterizer a full-viewport pass costs milliseconds
        self._drawn = state
        if self.color is None or self.color.size != (w, h):
            if self.fbo is not None:
                self.fbo.release()
                self.color.release()
            self.color = self.ctx.texture((w, h), 4)
            self.fbo = self.ctx.framebuffer(color_attachments=[self.color])
        prog = self.programs[mode]
        units = {"rgb": ("rgb_tex", "rgb"), "depth": ("depth_tex", "depth"), "feature": ("feature_tex", "feature"),
                 "similarity": ("sim_tex", "sim"), "region": ("sim_tex", "region")}
        names = {"mask": ["rgb", "region" if self.has("region") else "similarity"]}.get(mode, [mode])
        for unit, key in enumerate(names):
            uniform, tex = units[key]
            self._texture(tex).use(location=unit)
            prog[uniform] = unit
        if mode == "depth":
            prog["near"], prog["far"] = self.depth_range
        elif mode == "feature":
            prog["lo"], prog["hi"] = self.feature_range
        elif mode in ("similarity", "mask"):
            prog["threshold"] = float(threshold)
            if mode == "mask":
                prog["tint"] = (1.0, 0.9, 0.1)
                prog["strength"] = 0.6
        self.fbo.use()
        self.ctx.viewport = (0, 0, w, h)
        self.ctx.disable(moderngl.BLEND | moderngl.DEPTH_TEST)
        self.vaos[mode].render(moderngl.TRIANGLES, vertices=3)
        return self.color

    def release(self) -> None:
        for tex in self.textures.values():
            tex.release()
        self.textures.clear()
        self._pending.clear()
        if self.fbo is not None:
            self.fbo.release()
            self.color.release()
        self.fbo = self.color = self._drawn = None
