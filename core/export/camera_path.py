"""Camera paths in nerfstudio's `camera_path.json` layout: read one to render along it, and make one from key
views (rotations slerped, positions on a cubic spline through the keys, field of view linear) to save.

Layout: {"camera_type": "perspective", "render_width", "render_height", "fps", "seconds", "camera_path":
[{"camera_to_world": 16 numbers, row-major 4x4, OpenGL (camera looks down -z, +y up), "fov": vertical degrees,
"aspect": w / h}, ...], "keyframes": [...]}. Positions are in the scene's world units (our datasets' own frame;
nerfstudio's viewer writes its dataparser frame, which for its own exports of our datasets is the same up to its
auto-scale).
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from repaint_nerf.core.errors import UserError
from repaint_nerf.core.workspace import atomic


@dataclass
class CameraPath:
    """Frames of a path: world camera-to-world (N, 4, 4) OpenGL, vertical field of view (N,) in degrees."""

    c2w: np.ndarray
    fov: np.ndarray
    width: int
    height: int
    fps: float = 30.0

    def __len__(self) -> int:
        return len(self.c2w)

    def cameras(self, norm, scale: float = 1.0):
        """repaint_nerf.core.scene.cameras.Cameras of the frames in field space (norm: the scene's world -> field map)."""
        import torch

        from repaint_nerf.core.scene.cameras import Cameras

        w, h = max(1, round(self.width * scale)), max(1, round(self.height * scale))
        f = 0.5 * h / np.tan(np.radians(self.fov) / 2)
        cams = Cameras.create(self.c2w, f, f, np.full(len(self), w / 2), np.full(len(self), h / 2),
                              np.full(len(self), w), np.full(len(self), h))
        return cams.with_poses(norm.poses_to_field(cams.c2w.to(torch.float32)))


def _orthonormal(r: np.ndarray) -> np.ndarray:
    u, _, vt = np.linalg.svd(r)
    d = np.sign(np.linalg.det(u @ vt))
    return u @ np.diag([1.0, 1.0, d]) @ vt


def interpolate(key_c2w, key_fov, frames: int, loop: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """`frames` poses through the key views, evenly in key time: slerp between key rotations, a C2 cubic spline
    (scipy) through key positions (periodic with `loop`: the path returns to the first key), linear fov."""
    from scipy.interpolate import CubicSpline
    from scipy.spatial.transform import Rotation, Slerp

    keys = np.asarray(key_c2w, dtype=np.float64).reshape(-1, 4, 4)
    fov = np.asarray(key_fov, dtype=np.float64).reshape(-1)
    if len(keys) == 0 or len(fov) != len(keys):
        raise UserError("a camera path needs at least one key view (with its field of view)")
    if frames < 1:
        raise UserError(f"a camera path needs at least one frame, got {frames}")
    if loop and len(keys) > 1:
        keys, fov = np.concatenate([keys, keys[:1]]), np.concatenate([fov, fov[:1]])
    if len(keys) == 1:
        return np.repeat(keys, frames, 0), np.repeat(fov, frames)
    t_key = np.arange(len(keys), dtype=np.float64)
    t = np.linspace(0.0, t_key[-1], frames, endpoint=not loop)
    rots = Rotation.from_matrix(np.stack([_orthonormal(k[:3, :3]) for k in keys]))
    bc = "periodic" if loop else ("natural" if len(keys) > 2 else "not-a-knot")
    pos = CubicSpline(t_key, keys[:, :3, 3], bc_type=bc)(t)
    out = np.tile(np.eye(4), (frames, 1, 1))
    out[:, :3, :3] = Slerp(t_key, rots)(t).as_matrix()
    out[:, :3, 3] = pos
    return out, np.interp(t, t_key, fov)


def to_json(path: CameraPath, keys: list[dict] | None = None) -> dict:
    """The nerfstudio camera_path.json object of a path."""
    return {"camera_type": "perspective", "render_width": int(path.width), "render_height": int(path.height),
            "fps": float(path.fps), "seconds": len(path) / float(path.fps),
            "camera_path": [{"camera_to_world": c.reshape(-1).tolist(), "fov": float(f),
                             "aspect": path.width / path.height} for c, f in zip(path.c2w, path.fov)],
            "keyframes": keys or []}


def save_camera_path(path: CameraPath, file: str | Path, keys: list[dict] | None = None) -> Path:
    """Write the path as camera_path.json (atomically)."""
    from repaint_nerf.core.export.common import check_output_file

    file = check_output_file(file, (".json",), "camera path")
    atomic.write_json(file, to_json(path, keys))
    return file


def load_camera_path(file: str | Path) -> CameraPath:
    """Read a nerfstudio camera_path.json; anything malformed is a UserError naming the file and the frame."""
    file = Path(file).expanduser()
    if not file.is_file():
        raise UserError("no such camera path file", file, hint="give a camera_path.json (nerfstudio's layout)")
    try:
        meta = json.loads(file.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise UserError(f"cannot read this camera path ({exc})", file,
                        hint="give a nerfstudio camera_path.json") from None
    frames = meta.get("camera_path") if isinstance(meta, dict) else None
    if not isinstance(frames, list) or not frames:
        raise UserError("the file has no 'camera_path' list of frames", file, hint="give a nerfstudio camera_path.json")
    if meta.get("camera_type", "perspective") != "perspective":
        raise UserError(f"camera type '{meta.get('camera_type')}' is not supported", file,
                        hint="only perspective camera paths render here")
    c2w, fov = [], []
    for i, fr in enumerate(frames):
        try:
            m = np.asarray(fr["camera_to_world"], dtype=np.float64).reshape(4, 4)
            f = float(fr["fov"])
        except (KeyError, TypeError, ValueError):
            raise UserError(f"frame {i} needs 'camera_to_world' (16 numbers) and 'fov' (degrees)", file) from None
        if not np.all(np.isfinite(m)) or not 0 < f < 180:
            raise UserError(f"frame {i} has a non-finite pose or a field of view outside (0, 180): {f}", file)
        c2w.append(m)
        fov.append(f)
    try:
        w, h = int(meta["render_width"]), int(meta["render_height"])
        fps = float(meta.get("fps", 30.0))
    except (KeyError, TypeError, ValueError):
        raise UserError("the file needs 'render_width' and 'render_height'", file) from None
    if w < 1 or h < 1 or not fps > 0 or not math.isfinite(fps):
        raise UserError(f"bad size {w}x{h} or frame rate {fps}", file)
    return CameraPath(np.stack(c2w), np.asarray(fov), w, h, fps)
