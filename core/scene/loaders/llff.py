"""LLFF forward-facing captures: `poses_bounds.npy` plus `images/` (or pre-shrunk `images_N/`).

Each row holds a 3x5 matrix [R | t | (H, W, focal)] whose rotation columns are the camera's
[down, right, back] axes in world space, then the near/far depth bounds of that view.
"""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from repaint_nerf.core.errors import SceneError
from repaint_nerf.core.scene.cameras import Cameras
from repaint_nerf.core.scene.loaders.common import (TEST_EVERY, check_pose, every_eighth_split, holdout_note,
                                                    load_split, wanted)
from repaint_nerf.core.scene.loaders.images import list_images, read_image
from repaint_nerf.core.scene.loaders.masks import find_masks, with_mask
from repaint_nerf.core.scene.scene import Scene


def llff_to_opengl(poses: np.ndarray) -> np.ndarray:
    """(N, 3, 4) LLFF [down, right, back | t] -> (N, 4, 4) OpenGL [right, up, back | t] camera-to-world."""
    out = np.tile(np.eye(4), (poses.shape[0], 1, 1))
    out[:, :3, 0] = poses[:, :, 1]
    out[:, :3, 1] = -poses[:, :, 0]
    out[:, :3, 2] = poses[:, :, 2]
    out[:, :3, 3] = poses[:, :, 3]
    return out


def opengl_to_llff(c2w: np.ndarray) -> np.ndarray:
    """Inverse of `llff_to_opengl`: (N, 4, 4) OpenGL -> (N, 3, 4) LLFF layout (for writers and tests)."""
    return np.stack([-c2w[:, :3, 1], c2w[:, :3, 0], c2w[:, :3, 2], c2w[:, :3, 3]], axis=-1)


def image_folder(root: Path, downscale: float) -> Path:
    """`images_N/` when N equals the downscale factor, else `images/`, else the least-shrunk `images_N/`."""
    if float(downscale).is_integer() and downscale > 1 and list_images(root / f"images_{int(downscale)}"):
        return root / f"images_{int(downscale)}"
    if list_images(root / "images"):
        return root / "images"
    shrunk = sorted((int(m.group(1)), p) for p in root.glob("images_*")
                    if (m := re.fullmatch(r"images_(\d+)", p.name)) and list_images(p))
    if not shrunk:
        raise SceneError("no images found: expected an 'images/' or 'images_N/' folder next to poses_bounds.npy",
                         root)
    return shrunk[0][1]


SHRUNK_SLACK = 0.9  # a pre-shrunk folder whose longest side reaches this share of max_size stands in for images/


def shrunk_for_max_size(root: Path, long_side: float, n: int, max_size: int) -> int:
    """The largest N whose `images_N/` holds all `n` images with a longest side of at least SHRUNK_SLACK *
    `max_size` (1 when none does): LLFF captures ship such copies, and decoding the full-size photos only to
    shrink them took 231-457 s for ethiopian_head's 66 4000-px JPEGs against ~1 s for its 500-px images_8/."""
    best = 1
    for p in root.glob("images_*"):
        m = re.fullmatch(r"images_(\d+)", p.name)
        if m and int(m.group(1)) > best and long_side / int(m.group(1)) >= SHRUNK_SLACK * max_size \
                and len(list_images(p)) == n:
            best = int(m.group(1))
    return best


def load_llff(root: Path, downscale: float = 1.0, splits=None, max_size: int = 0,
              holdout_every: int = TEST_EVERY) -> Scene:
    """Load an LLFF scene; every `holdout_every`-th image is test, near/far come from the per-view bounds;
    `max_size` as in load_split."""
    root = Path(root)
    path = root / "poses_bounds.npy"
    try:
        # mmap: a header claiming a huge shape fails on the file's real size instead of allocating it
        arr = np.array(np.load(path, allow_pickle=False, mmap_mode="r"))
    except FileNotFoundError as exc:
        raise SceneError("file not found", path) from exc
    except Exception as exc:  # noqa: BLE001 - numpy raises ValueError, EOFError, SyntaxError... on garbage headers
        raise SceneError(f"not a readable .npy array ({exc})", path) from exc
    if arr.ndim != 2 or arr.shape[1] != 17 or arr.shape[0] == 0 or arr.dtype.kind not in "fiu":
        raise SceneError(f"expected a numeric array of shape (N, 17) (3x5 pose + near/far per image), "
                         f"got shape {arr.shape}", path, hint="regenerate it with LLFF's imgs2poses.py")
    arr = arr.astype(np.float64)
    n = arr.shape[0]
    raw = arr[:, :15].reshape(n, 3, 5)
    bounds = arr[:, 15:17]
    if not np.all(np.isfinite(bounds)) or np.any(bounds <= 0):
        raise SceneError("near/far bounds must be finite and positive", path)
    hwf = raw[:, :, 4]
    if not np.all(np.isfinite(hwf)) or np.any(hwf <= 0):
        raise SceneError("image height, width and focal (column 5) must be finite and positive", path)
    c2w = llff_to_opengl(raw[:, :, :4])
    c2w = np.stack([check_pose(c2w[i], path, f"image {i}") for i in range(n)])

    if downscale == 1 and max_size > 0:
        downscale = float(shrunk_for_max_size(root, float(np.max(hwf[0, :2])), n, max_size))
    folder = image_folder(root, downscale)
    files = list_images(folder)
    if len(files) != n:
        raise SceneError(f"{folder.name}/ holds {len(files)} images but poses_bounds.npy has {n} poses", path,
                         hint="the images and poses must match one to one (sorted by file name)")
    h, w, f = hwf[:, 0], hwf[:, 1], hwf[:, 2]
    cams = Cameras.create(c2w, f, f, w / 2.0, h / 2.0, np.round(w), np.round(h))
    masks = find_masks(root, folder, files)
    tr, te = every_eighth_split(n, holdout_every)
    out = {}
    for name, idx in (("train", tr), ("test", te)):
        if idx and wanted(name, splits):
            reader = None if masks is None else (lambda i, p, m=[masks[j] for j in idx]: with_mask(read_image(p), m[i]))
            out[name] = load_split(cams[idx], [files[i] for i in idx], [files[i].name for i in idx], downscale,
                                   reader=reader, max_size=max_size)
    extra = {"bounds": bounds, "images_dir": folder.name,
             "holdout": holdout_note(holdout_every, "image file names sorted")}
    if masks is not None:
        extra["masks_dir"] = masks[0].parent.name
    return Scene(root=root, format="llff", splits=out, kind="forward", near=float(bounds.min() * 0.9),
                 far=float(bounds.max() * 1.1), extra=extra)
