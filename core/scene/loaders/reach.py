"""How far a transforms JSON's content reaches, as instant-ngp and nerfstudio say it.

- instant-ngp maps world points into its unit cube by p * scale + offset (`scale` 0.33 and `offset` 0.5 unless
  the JSON gives them, or an `aabb` sets both so that box fits the cube) and `aabb_scale` k says the content
  reaches k times that cube (k = 1: all of it lies inside).
- nerfstudio's dataparser centres, orients and scales the poses (`dataparser_transforms.json`: `transform`, a
  3x4 matrix, and `scale`) and bounds the content by its scene box [-1, 1]^3 in that space; nerfacto contracts
  everything beyond the box.

Either gives a `unit_box` (world units): the region the field cube holds at full resolution (normalize.py), and
a reach beyond it (contraction.warp_spec) that decides the scene kind (kinds.py).
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from repaint_nerf.core.errors import SceneError
from repaint_nerf.core.scene.loaders.common import as_float

NGP_SCALE, NGP_OFFSET = 0.33, 0.5  # instant-ngp's NERF_SCALE and default offset
DATAPARSER_FILE = "dataparser_transforms.json"


def parse_aabb_scale(meta: dict, path: Path) -> float | None:
    """instant-ngp's `aabb_scale` (>= 1), or None when absent."""
    value = meta.get("aabb_scale")
    if value is None:
        return None
    k = as_float(value)
    if not math.isfinite(k) or k < 1.0:
        raise SceneError(f"'aabb_scale' must be a number >= 1 (instant-ngp uses 1, 2, 4, ..., 128), got {value!r}",
                         path, hint="remove the key, or give how many unit cubes the content reaches")
    return k


def _vector(value, path: Path, key: str) -> np.ndarray:
    try:
        v = np.broadcast_to(np.asarray(value, dtype=np.float64).reshape(-1), (3,)).copy()
    except (TypeError, ValueError):
        v = np.full(3, np.nan)
    if not np.all(np.isfinite(v)):
        raise SceneError(f"'{key}' must be a number or three numbers, got {value!r}", path)
    return v


def ngp_unit_box(meta: dict, path: Path, aabb: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """instant-ngp's unit cube in world units: the cube around `aabb` when given, else from `scale`/`offset`."""
    if aabb is not None:
        centre, half = aabb.mean(0), 0.5 * float(np.max(aabb[1] - aabb[0]))
    else:
        scale = float(_vector(meta.get("scale", NGP_SCALE), path, "scale")[0])
        if scale <= 0:
            raise SceneError(f"'scale' must be positive, got {meta.get('scale')!r}", path)
        offset = _vector(meta.get("offset", NGP_OFFSET), path, "offset")
        centre, half = (0.5 - offset) / scale, 0.5 / scale
    return centre - half, centre + half


def nerfstudio_scene_box(root: Path) -> tuple[np.ndarray, np.ndarray] | None:
    """The world-space bounding box of nerfstudio's scene box [-1, 1]^3, from a `dataparser_transforms.json`
    beside the transforms file (what `ns-train` writes); None when there is none."""
    path = root / DATAPARSER_FILE
    if not path.is_file():
        return None
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        m = np.asarray(data["transform"], dtype=np.float64).reshape(3, 4)
        s = float(data.get("scale", 1.0))
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise SceneError(f"not a nerfstudio dataparser file ({type(exc).__name__}: {exc})", path,
                         hint="it needs 'transform' (3x4) and 'scale'; delete it to go without") from exc
    if not (np.all(np.isfinite(m)) and math.isfinite(s) and s > 0) or abs(np.linalg.det(m[:, :3])) < 1e-9:
        raise SceneError("its 'transform' must be an invertible 3x4 matrix and 'scale' positive", path)
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64)
    world = (corners / s - m[:, 3]) @ np.linalg.inv(m[:, :3]).T  # x_ns = s (R x + t)
    return world.min(0), world.max(0)


def content_reach(meta: dict, root: Path, path: Path, aabb: np.ndarray | None) -> dict:
    """Scene extras that bound the content: 'aabb_scale', 'unit_box' (world [lo, hi]) and 'unit_box_from'; {}
    when the files say nothing (then `aabb`, points or the cameras decide, as before)."""
    k = parse_aabb_scale(meta, path)
    if k is not None:
        lo, hi = ngp_unit_box(meta, path, aabb)
        where = "the aabb" if aabb is not None else "scale/offset"
        return {"aabb_scale": k, "unit_box": [lo.tolist(), hi.tolist()],
                "unit_box_from": f"instant-ngp's unit cube ({where}), aabb_scale {k:g}"}
    box = nerfstudio_scene_box(root)
    if box is not None and aabb is None:
        return {"unit_box": [box[0].tolist(), box[1].tolist()],
                "unit_box_from": f"nerfstudio's scene box ({DATAPARSER_FILE})"}
    return {}
