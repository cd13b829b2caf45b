"""Photo folders with known poses, rendered from the synthetic presets, for SfM tests and the bench.

Unlike `core.synth.make_scene` (square NeRF-synthetic datasets) this writes bare RGB photos of any
size (e.g. 400x300) with zero-padded names in capture order, and returns the true poses.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from dataclasses import replace

from repaint_nerf.core.synth.presets import build_spec
from repaint_nerf.core.synth.raster import Rasterizer
from repaint_nerf.core.synth.writer import write_png


def render_photos(preset: str, out: Path, views: int = 20, width: int = 400, height: int = 300,
                  seed: int = 0, texture: str | None = "noise", texture_scale: float = 10.0,
                  fov_x: float | None = None) -> dict:
    """Render `views` RGB photos of `preset` into `out`; returns {"names", "c2w" (N,4,4 OpenGL), "fx", "kind"}.

    The ring and hemisphere rigs are sorted by azimuth so names follow the capture path. `texture`
    replaces every object's texture (the presets' checkers and stripes repeat, so SIFT's ratio test
    rejects most of their matches; value noise is what real surfaces look like to SIFT); None keeps them.
    `fov_x` (radians) replaces the preset's horizontal field of view.
    """
    spec = build_spec(preset)
    if texture is not None:
        spec.objects = [replace(o, texture=texture, texture_scale=texture_scale * max(1.0, o.texture_scale / 4.0))
                        for o in spec.objects]
    rng = np.random.default_rng(seed)
    poses = spec.rig(views, rng)
    if spec.kind != "forward":
        az = np.arctan2(poses[:, 1, 3], poses[:, 0, 3])
        poses = poses[np.argsort(az)]
    fx = 0.5 * width / np.tan(0.5 * (fov_x or spec.camera_angle_x))
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    names = []
    with Rasterizer(width, height, spec.near, spec.far) as ras:
        for i, c2w in enumerate(poses):
            frame = ras.render(spec.objects, c2w, fx, fx, 0.5 * width, 0.5 * height)
            rgba = frame.rgba
            rgb = rgba[..., :3] if spec.opaque else _over_white(rgba)
            name = f"img_{i:03d}.png"
            write_png(out / name, rgb)
            names.append(name)
    return {"names": names, "c2w": poses, "fx": float(fx), "kind": spec.kind}


def _over_white(rgba: np.ndarray) -> np.ndarray:
    a = rgba[..., 3:4].astype(np.float32) / 255.0
    return (rgba[..., :3] * a + 255.0 * (1.0 - a) + 0.5).astype(np.uint8)
