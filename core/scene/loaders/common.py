"""Checks and helpers every loader shares: pose validation, the every-8th test split, downscaling."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from repaint_nerf.core.errors import SceneError, UserError
from repaint_nerf.core.scene.cameras import Cameras
from repaint_nerf.core.scene.loaders.images import fit_image, read_image
from repaint_nerf.core.scene.scene import SceneSplit

TEST_EVERY = 8  # LLFF convention: images 0, 8, 16, ... are the test split
# longest image side loaded by default: photos are stored and sampled at the training resolution, and the
# paper trains LLFF at 504x378; `max_size=0` keeps the full size
DEFAULT_MAX_SIZE = 512


def as_float(value) -> float:
    """`value` as a float; NaN when it is not a number (the caller's finiteness check then names the key)."""
    try:
        return float(value)
    except (TypeError, ValueError):
        return float("nan")


def check_downscale(downscale: float) -> float:
    """Validate a --downscale factor (> 0; 2 halves width and height)."""
    try:
        d = float(downscale)
    except (TypeError, ValueError):
        d = float("nan")
    if not math.isfinite(d) or d <= 0:
        raise UserError(f"--downscale must be a positive number, got {downscale!r}", hint="e.g. --downscale 2")
    return d


def check_max_size(max_size) -> int:
    """Validate a --max-size (longest image side in pixels; 0 = no limit)."""
    try:
        m = int(max_size)
    except (TypeError, ValueError):
        m = -1
    if m < 0 or (0 < m < 8) or m != max_size:
        raise UserError(f"--max-size must be 0 (full size) or a whole number of pixels >= 8, got {max_size!r}",
                        hint="e.g. --max-size 512")
    return m


def load_factor(cameras: Cameras, downscale: float, max_size: int = 0) -> float:
    """The factor a split's images are resized by when loaded: 1/downscale, lowered further so the longest
    side of the largest image is at most `max_size` (0 = no limit). One factor per split keeps its cameras'
    intrinsics in proportion."""
    factor = 1.0 / downscale
    if max_size and len(cameras):
        longest = float(max(int(cameras.width.max()), int(cameras.height.max())))
        factor = min(factor, max_size / longest)
    return factor


def check_pose(c2w, path: Path, where: str) -> np.ndarray:
    """A camera-to-world matrix as float64 4x4 with an orthonormal right-handed rotation.

    Non-finite, singular or mirrored poses raise a `SceneError` naming `path` and `where` (the frame).
    A rotation carrying a uniform scale is orthonormalised (polar decomposition).
    """
    m = np.asarray(c2w, dtype=np.float64)
    if m.shape == (3, 4):
        m = np.vstack([m, [0.0, 0.0, 0.0, 1.0]])
    if m.shape != (4, 4):
        raise SceneError(f"{where}: a pose must be a 4x4 (or 3x4) matrix, got shape {m.shape}", path)
    if not np.all(np.isfinite(m)):
        raise SceneError(f"{where}: the pose contains NaN or infinite values", path,
                         hint="remove this frame or fix its transform_matrix")
    rot = m[:3, :3]
    svals = np.linalg.svd(rot, compute_uv=False)
    if svals[-1] < 1e-6 * max(svals[0], 1e-12) or svals[0] < 1e-9:
        raise SceneError(f"{where}: the pose is singular (its rotation has no inverse)", path,
                         hint="remove this frame or fix its transform_matrix")
    if np.linalg.det(rot) < 0:
        raise SceneError(f"{where}: the pose is a reflection (left-handed rotation)", path,
                         hint="fix the transform_matrix; rotations must have determinant +1")
    out = m.copy()
    out[3] = [0.0, 0.0, 0.0, 1.0]
    if np.abs(rot.T @ rot - np.eye(3)).max() > 1e-5:
        u, _, vt = np.linalg.svd(rot)
        out[:3, :3] = u @ vt
    return out


def check_holdout_every(every) -> int:
    """Validate a --holdout-every N (hold out images 0, N, 2N, ...; N >= 2 so that something is trained on)."""
    try:
        n = int(every)
    except (TypeError, ValueError):
        n = 0
    if n < 2 or n != every:
        raise UserError(f"--holdout-every must be a whole number >= 2, got {every!r}",
                        hint=f"e.g. --holdout-every {TEST_EVERY} (nerfstudio's and instant-ngp's every 8th view)")
    return n


def every_eighth_split(n: int, every: int = TEST_EVERY) -> tuple[list[int], list[int]]:
    """(train, test) indices with every `every`-th image (0, 8, ...) as test; one image goes to train only."""
    if n < 2:
        return list(range(n)), []
    test = list(range(0, n, every))
    return [i for i in range(n) if i % every], test


def holdout_note(every: int, order: str) -> dict:
    """What `Scene.extra['holdout']` says of an every-Nth split: the rule and the order it counts in."""
    return {"rule": f"every {every}th image held out (index % {every} == 0), not trained on", "every": every,
            "order": order}


def load_split(cameras: Cameras, paths: list[Path], names: list[str], downscale: float,
               reader=None, max_size: int = 0) -> SceneSplit:
    """Read a split's images and fit them (and the cameras) to the downscaled size (see `load_factor`).

    `cameras` describe the full-resolution images; an image stored at another size (a pre-shrunk
    `images_N/` folder) is resized to the target. `reader(i, path)` may replace `read_image` (e.g. to undistort).
    Only the resized images are kept (one full-size image is held at a time).
    """
    factor = load_factor(cameras, downscale, max_size)
    target = cameras.scaled(factor) if factor != 1.0 else cameras
    images = []
    for i, p in enumerate(paths):
        img = reader(i, p) if reader else read_image(p)
        images.append(fit_image(img, int(target.width[i]), int(target.height[i]), p))
        del img  # else the full-size image lives on while the next one is decoded
    return SceneSplit(target, images, list(names), list(paths))


def wanted(split: str, splits) -> bool:
    """Whether `split` is among the requested `splits` (None = all)."""
    return splits is None or split in splits
