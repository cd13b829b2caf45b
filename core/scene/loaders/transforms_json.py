"""Parsing shared by the Blender (NeRF-synthetic) and nerfstudio `transforms*.json` formats.

Both store OpenGL camera-to-world `transform_matrix` per frame and intrinsics either per file or per
frame: `camera_angle_x` (+ optional `camera_angle_y`) or `fl_x`/`fl_y`/`cx`/`cy`, with optional
`w`/`h` and OpenCV distortion `k1..k4`, `p1`, `p2` (`camera_model` names the model).
"""
from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np

from repaint_nerf.core.errors import SceneError
from repaint_nerf.core.scene.cameras import Cameras
from repaint_nerf.core.scene.loaders.common import as_float, check_pose, load_split
from repaint_nerf.core.scene.loaders.images import IMAGE_EXTS, image_size, read_image
from repaint_nerf.core.scene.loaders.undistort import make_camera, needs_undistortion, undistort_image, undistorted_camera
from repaint_nerf.core.scene.scene import SceneSplit

_DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")


def read_json(path: Path) -> dict:
    """Parse a JSON object file; missing, unreadable or non-object files are a `SceneError`."""
    if not path.is_file():
        raise SceneError("file not found", path)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except UnicodeDecodeError as exc:
        raise SceneError("not a text JSON file", path) from exc
    except json.JSONDecodeError as exc:
        raise SceneError(f"not valid JSON (line {exc.lineno}, column {exc.colno}: {exc.msg})", path,
                         hint="fix or regenerate this file") from exc
    if not isinstance(data, dict):
        raise SceneError("expected a JSON object with a 'frames' list at the top level", path)
    return data


def frames_of(meta: dict, path: Path) -> list[dict]:
    """The non-empty `frames` list of a transforms file."""
    frames = meta.get("frames")
    if not isinstance(frames, list):
        raise SceneError("missing key 'frames' (a list of {file_path, transform_matrix})", path)
    if not frames:
        raise SceneError("'frames' is empty: the file lists no images", path)
    for i, fr in enumerate(frames):
        if not isinstance(fr, dict):
            raise SceneError(f"frame {i} is not an object", path)
        for key in ("file_path", "transform_matrix"):
            if key not in fr:
                raise SceneError(f"frame {i} misses key '{key}'", path)
    return frames


def frame_pose(frame: dict, path: Path, i: int) -> np.ndarray:
    """The validated OpenGL camera-to-world matrix of frame i."""
    try:
        m = np.asarray(frame["transform_matrix"], dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise SceneError(f"frame {i} ('{frame.get('file_path')}'): transform_matrix is not a numeric matrix",
                         path) from exc
    return check_pose(m, path, f"frame {i} ('{frame.get('file_path')}')")


def find_image(root: Path, file_path: str, path: Path, i: int) -> Path | None:
    """The image file a frame names, relative to the JSON's folder, with or without an extension; None when
    it is not there (a path leaving the dataset folder is a `SceneError`)."""
    rel = str(file_path).replace("\\", "/")
    # lexically inside the folder ('..' cannot climb out); a symlinked images folder is the user's own choice
    p = Path(os.path.normpath(root.absolute() / rel))
    if Path(rel).is_absolute() or not p.is_relative_to(Path(os.path.normpath(root.absolute()))):
        raise SceneError(f"frame {i}: image '{file_path}' points outside the dataset folder", path,
                         hint="file_path must be relative to the folder of the JSON file and stay inside it")
    if p.is_file():
        return p
    for ext in IMAGE_EXTS + tuple(e.upper() for e in IMAGE_EXTS):
        q = p.with_name(p.name + ext)
        if q.is_file():
            return q
    return None


def resolve_image(root: Path, file_path: str, path: Path, i: int) -> Path:
    """`find_image`, with a missing image a `SceneError`."""
    found = find_image(root, file_path, path, i)
    if found is not None:
        return found
    p = (root / str(file_path).replace("\\", "/")).resolve()
    raise SceneError(f"frame {i}: image '{file_path}' not found (looked for {p} with and without an extension)",
                     path, hint="check file_path or add the missing image")


def _relative_name(p: Path, root: Path) -> str:
    try:
        return p.relative_to(root.resolve()).as_posix()
    except ValueError:
        return p.name


def _number(meta: dict, frame: dict, key: str, path: Path, i: int):
    value = frame.get(key, meta.get(key))
    if value is None:
        return None
    v = as_float(value)
    if not math.isfinite(v):
        raise SceneError(f"frame {i}: '{key}' is not a finite number ({value!r})", path)
    return v


def frame_intrinsics(meta: dict, frame: dict, path: Path, i: int, image_size: tuple[int, int]):
    """Return (pycolmap camera of the stored image, its pinhole (fx, fy, cx, cy, w, h) after undistortion).

    Per-frame values override per-file ones. Intrinsics given for a `w`x`h` other than the stored
    image size are rescaled to it.
    """
    iw, ih = image_size
    get = lambda key: _number(meta, frame, key, path, i)  # noqa: E731
    w, h = get("w") or iw, get("h") or ih
    fx, fy = get("fl_x"), get("fl_y")
    if fx is None:
        ax = get("camera_angle_x")
        if ax is None:
            raise SceneError(f"frame {i}: missing intrinsics: give 'camera_angle_x' or 'fl_x' (per file or per frame)",
                             path)
        if not 0 < ax < math.pi:
            raise SceneError(f"frame {i}: camera_angle_x must be in (0, pi) radians, got {ax}", path)
        fx = 0.5 * w / math.tan(0.5 * ax)
    if fy is None:
        ay = get("camera_angle_y")
        fy = 0.5 * h / math.tan(0.5 * ay) if ay else fx
    cx, cy = get("cx"), get("cy")
    cx = w / 2.0 if cx is None else cx
    cy = h / 2.0 if cy is None else cy
    if fx <= 0 or fy <= 0:
        raise SceneError(f"frame {i}: focal length must be positive (fl_x={fx}, fl_y={fy})", path)
    dist = {k: get(k) or 0.0 for k in _DISTORTION_KEYS}
    model = str(frame.get("camera_model", meta.get("camera_model", "OPENCV"))).upper()
    if "FISHEYE" in model:
        cam = make_camera("OPENCV_FISHEYE", [fx, fy, cx, cy, dist["k1"], dist["k2"], dist["k3"], dist["k4"]], w, h)
    elif dist["k3"] or dist["k4"]:
        cam = make_camera("FULL_OPENCV", [fx, fy, cx, cy, dist["k1"], dist["k2"], dist["p1"], dist["p2"],
                                          dist["k3"], dist["k4"], 0.0, 0.0], w, h)
    elif any(dist.values()):
        cam = make_camera("OPENCV", [fx, fy, cx, cy, dist["k1"], dist["k2"], dist["p1"], dist["p2"]], w, h)
    else:
        cam = make_camera("PINHOLE", [fx, fy, cx, cy], w, h)
    if (round(w), round(h)) != (iw, ih):
        if abs(w / h - iw / ih) > 0.01 * iw / ih:
            raise SceneError(f"frame {i}: the image is {iw}x{ih} but the file says w={w:g}, h={h:g}", path,
                             hint="use the images the intrinsics were written for")
        cam.rescale(int(iw), int(ih))
    return cam, undistorted_camera(cam)


def load_frames(meta: dict, frames: list[dict], idx: list[int], root: Path, path: Path, downscale: float,
                same_size: bool, max_size: int = 0, models: set | None = None) -> SceneSplit:
    """Build one split from frames `idx` of a transforms file: validated poses, intrinsics, images.

    `same_size` (Blender) makes images of different sizes within the split a `SceneError`. Sizes come
    from the file headers; pixels are decoded one image at a time (full-size images are never all held).
    `models`, when given, collects the names of the lens models undistorted (for `info`).
    """
    paths = [resolve_image(root, frames[i]["file_path"], path, i) for i in idx]
    poses = [frame_pose(frames[i], path, i) for i in idx]
    sizes = [image_size(p) for p in paths]
    if same_size:
        for p, size in zip(paths, sizes):
            if size != sizes[0]:
                raise SceneError(f"images of one split differ in size: {paths[0].name} is "
                                 f"{sizes[0][0]}x{sizes[0][1]}, {p.name} is {size[0]}x{size[1]}", path,
                                 hint="resize all images of a split to one size")
    cams, pins = [], []
    for k, i in enumerate(idx):
        cam, pin = frame_intrinsics(meta, frames[i], path, i, sizes[k])
        cams.append(cam)
        pins.append(pin)
        if models is not None and needs_undistortion(cam):
            models.add(cam.model_name)
    pin = np.asarray(pins, dtype=np.float64)
    cameras = Cameras.create(np.stack(poses), pin[:, 0], pin[:, 1], pin[:, 2], pin[:, 3], pin[:, 4], pin[:, 5])

    def reader(k: int, p: Path) -> np.ndarray:
        img = read_image(p)
        if (img.shape[1], img.shape[0]) != sizes[k]:
            raise SceneError(f"decoded size {img.shape[1]}x{img.shape[0]} differs from the header's "
                             f"{sizes[k][0]}x{sizes[k][1]}", p)
        return undistort_image(img, cams[k])[0] if needs_undistortion(cams[k]) else img

    names = [_relative_name(p, root) for p in paths]
    return load_split(cameras, paths, names, downscale, reader=reader, max_size=max_size)


def parse_background(meta: dict, path: Path):
    """An optional background colour ('background' or 'background_color'), as RGB floats in [0, 1]."""
    value = meta.get("background", meta.get("background_color"))
    if value is None:
        return None
    try:
        rgb = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        rgb = np.zeros(0)
    if rgb.size not in (3, 4) or not np.all(np.isfinite(rgb)):
        raise SceneError(f"'background' must be an RGB triple, got {value!r}", path)
    rgb = rgb[:3] / 255.0 if rgb.max() > 1.0 else rgb[:3]
    return tuple(float(c) for c in np.clip(rgb, 0.0, 1.0))


def parse_aabb(meta: dict, path: Path):
    """An optional `aabb` [[xmin, ymin, zmin], [xmax, ymax, zmax]] in world units, as a (2, 3) array."""
    value = meta.get("aabb")
    if value is None:
        return None
    try:
        box = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        box = np.zeros(0)
    if box.shape != (2, 3) or not np.all(np.isfinite(box)) or np.any(box[1] <= box[0]):
        raise SceneError(f"'aabb' must be [[xmin, ymin, zmin], [xmax, ymax, zmax]] with min < max, got {value!r}",
                         path)
    return box


def parse_kind(meta: dict, path: Path) -> str | None:
    """The optional `scene_kind` ('bounded', 'forward', 'unbounded'); None when absent (detected at load)."""
    from repaint_nerf.core.scene.scene import SCENE_KINDS

    kind = meta.get("scene_kind")
    if kind is None:
        return None
    if kind not in SCENE_KINDS:
        raise SceneError(f"'scene_kind' must be one of {', '.join(SCENE_KINDS)}, got {kind!r}", path)
    return kind


def parse_depth_range(meta: dict, path: Path):
    """The optional `depth_range` [near, far] of visible surfaces (z-depth, world units), or None."""
    value = meta.get("depth_range")
    if value is None:
        return None
    try:
        lo, hi = (float(v) for v in value)
    except (TypeError, ValueError):
        raise SceneError(f"'depth_range' must be [near, far], got {value!r}", path) from None
    if not (math.isfinite(lo) and math.isfinite(hi) and 0 < lo < hi):
        return None  # a scene that sees no surface at all writes [0, 0]
    return lo, hi
