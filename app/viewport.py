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


class Viewport:
    """Holds the latest frame's textures and draws one view mode of it into a texture for imgui."""

    def __init__(self, ctx: moderngl.Context, shader_dir: Path = SHADER_DIR):
        self.ctx = ctx
        vert = load_shader("viewport.vert", shader_dir)
        self.programs = {m: ctx.program(vertex_shader=vert, fragment_shader=load_shader(f"{m}.frag", shader_dir))
                         for m in MODES}
        self.vaos = {m: ctx.vertex_array(p, []) for m, p in self.programs.items()}
        self.textures: dict[str, moderngl.Texture] = {}
        self.fbo: moderngl.Framebuffer | None = None
        self.color: moderngl.Texture | None = None
        self.depth_range = (0.0, 1.0)
        self.feature_range = ((0.0,) * 3, (1.0,) * 3)
        self.frame_size: tuple[int, int] | None = None  # (w, h) of the last uploaded render
        self._uploads = 0  # bumped by every upload: the drawn texture is stale
        self._drawn: tuple | None = None  # what the viewport texture shows now

    def has(self, name: str) -> bool:
        return name in self.textures

    def _upload(self, name: str, data: np.ndarray) -> None:
        data = np.ascontiguousarray(data, dtype=np.float32)
        h, w = data.shape[:2]
        comps = 1 if data.ndim == 2 else data.shape[2]
        tex = self.textures.get(name)
        if tex is None or tex.size != (w, h) or tex.components != comps:
            if tex is not None:
                tex.release()
            tex = self.ctx.texture((w, h), comps, dtype="f4")
            tex.filter = (moderngl.LINEAR, moderngl.LINEAR)
            tex.repeat_x = tex.repeat_y = False
            self.textures[name] = tex
        tex.write(data.tobytes())
        self._uploads += 1

    def upload_frame(self, frame: dict) -> None:
        """Take a render from the worker: 'rgb' (H,W,3), optional 'depth' (H,W), 'feature_pca' (H,W,3), 'similarity' (H,W)."""
        if "rgb" in frame:
            rgb = frame["rgb"]
            self._upload("rgb", rgb.astype(np.float32) / 255.0 if rgb.dtype == np.uint8 else rgb)
            self.frame_size = (rgb.shape[1], rgb.shape[0])
        if frame.get("depth") is not None:
            d = frame["depth"]
            self._upload("depth", d)
            valid = d[d > 0]
            if valid.size:
                self.depth_range = (float(np.percentile(valid, 1)), float(np.percentile(valid, 99)) + 1e-6)
        if frame.get("feature_pca") is not None:
            f = frame["feature_pca"]
            self._upload("feature", f)
            flat = f.reshape(-1, 3)
            self.feature_range = (tuple(np.percentile(flat, 1, axis=0)), tuple(np.percentile(flat, 99, axis=0)))
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
                    self._uploads += 1
            else:
                self._upload(name, data)

    def available_modes(self) -> list[str]:
        need = {"rgb": ["rgb"], "depth": ["depth"], "feature": ["feature"], "similarity": ["sim"], "mask": ["rgb", "sim"]}
        return [m for m in MODES if all(n in self.textures for n in need[m])]

    def draw(self, size: tuple[int, int], mode: str, threshold: float = 0.5) -> moderngl.Texture | None:
        """Draw `mode` for a viewport of `size` (w, h) pixels into the viewport texture and return it (None before
        a first frame); the caller shows the texture stretched over the viewport."""
        if mode not in self.available_modes():
            mode = "rgb"
        if "rgb" not in self.textures:
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
        names = {"mask": ["rgb", "region" if "region" in self.textures else "similarity"]}.get(mode, [mode])
        for unit, key in enumerate(names):
            uniform, tex = units[key]
            self.textures[tex].use(location=unit)
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
        if self.fbo is not None:
            self.fbo.release()
            self.color.release()
        self.fbo = self.color = self._drawn = None
