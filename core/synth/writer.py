"""File writers for generated scenes: PNG (via OpenCV), depth .npy and the NeRF-synthetic transforms JSON.

Byte-for-byte deterministic: the same arrays always give the same files.
"""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np


def write_png(path: Path, image: np.ndarray) -> None:
    """Write a uint8 (H,W), (H,W,3) RGB or (H,W,4) RGBA image as PNG, creating the parent folder."""
    path.parent.mkdir(parents=True, exist_ok=True)
    img = np.ascontiguousarray(image, dtype=np.uint8)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_RGBA2BGRA if img.shape[2] == 4 else cv2.COLOR_RGB2BGR)
    ok, buf = cv2.imencode(".png", img)
    if not ok:
        raise OSError(f"could not encode {path}")
    path.write_bytes(buf.tobytes())


def write_depth(path: Path, depth: np.ndarray) -> None:
    """Write a float32 (H,W) z-depth map as .npy."""
    path.parent.mkdir(parents=True, exist_ok=True)
    np.save(path, np.ascontiguousarray(depth, dtype=np.float32), allow_pickle=False)


def write_json(path: Path, data: dict) -> None:
    """Write `data` as indented JSON, creating the parent folder."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data, indent=2) + "\n")


def transforms(c2w: np.ndarray, split: str, fx: float, fy: float, cx: float, cy: float, width: int,
               height: int, extra: dict) -> dict:
    """A NeRF-synthetic transforms dict for poses (N,4,4) of `split`; `extra` adds top-level keys (aabb, ...)."""
    return {
        "camera_angle_x": float(2.0 * np.arctan(0.5 * width / fx)),
        "camera_angle_y": float(2.0 * np.arctan(0.5 * height / fy)),
        "fl_x": float(fx), "fl_y": float(fy), "cx": float(cx), "cy": float(cy),
        "w": int(width), "h": int(height),
        **extra,
        "frames": [{"file_path": f"./{split}/r_{i}", "transform_matrix": np.asarray(m, dtype=np.float64).tolist()}
                   for i, m in enumerate(c2w)],
    }
