"""A montage of every preset (a few views, depth and mask ground truth, the edited view) for the docs."""
from __future__ import annotations

import tempfile
from pathlib import Path

import cv2
import numpy as np

from repaint_nerf.core.synth.generate import list_presets, make_scene
from repaint_nerf.core.synth.writer import write_png

_PALETTE = np.array([[255, 255, 255], [150, 150, 150], [230, 25, 75], [60, 180, 75], [255, 225, 25],
                     [0, 130, 200], [245, 130, 48], [145, 30, 180], [70, 240, 240], [240, 50, 230],
                     [128, 0, 0], [0, 0, 128]], dtype=np.uint8)
COLUMNS = ("view 0", "view 1", "view 2", "depth 0", "mask 0", "edited 0")


def _on_white(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    img = img[..., [2, 1, 0, 3]] if img.shape[2] == 4 else np.dstack([img[..., ::-1], np.full(img.shape[:2], 255)])
    a = img[..., 3:].astype(np.float32) / 255.0
    return np.round(img[..., :3] * a + 255.0 * (1.0 - a)).astype(np.uint8)


def depth_image(depth: np.ndarray) -> np.ndarray:
    """Colour-mapped z-depth (near = warm), white where there is no surface."""
    hit = depth > 0
    out = np.full((*depth.shape, 3), 255, np.uint8)
    if hit.any():
        lo, hi = depth[hit].min(), depth[hit].max()
        norm = np.zeros_like(depth)
        norm[hit] = 1.0 - (depth[hit] - lo) / max(hi - lo, 1e-6)
        colored = cv2.applyColorMap(np.round(norm * 255).astype(np.uint8), cv2.COLORMAP_TURBO)[..., ::-1]
        out[hit] = colored[hit]
    return out


def mask_image(mask: np.ndarray) -> np.ndarray:
    """Object ids as distinct colours, background white."""
    return _PALETTE[mask % len(_PALETTE)]


def _label(img: np.ndarray, text: str) -> np.ndarray:
    img = img.copy()
    cv2.putText(img, text, (3, 11), cv2.FONT_HERSHEY_SIMPLEX, 0.33, (0, 0, 0), 1, cv2.LINE_AA)
    return img


def write_montage(out_png: Path, size: int = 96) -> Path:
    """Render every preset small and write one PNG grid: a row per preset, columns as in COLUMNS."""
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name in list_presets():
            scene = make_scene(name, Path(tmp) / name, size=size, views=3, test_views=1, seed=0)
            tiles = [_on_white(scene / "train" / f"r_{i}.png") for i in range(3)]
            tiles.append(depth_image(np.load(scene / "gt" / "train" / "r_0_depth.npy")))
            tiles.append(mask_image(cv2.imread(str(scene / "gt" / "train" / "r_0_mask.png"), cv2.IMREAD_UNCHANGED)))
            tiles.append(_on_white(scene / "edited" / "train" / "r_0.png"))
            tiles = [_label(t, f"{name}: {c}" if j == 0 else c) for j, t in enumerate(tiles) for c in [COLUMNS[j]]]
            rows.append(np.hstack([np.pad(t, ((1, 1), (1, 1), (0, 0)), constant_values=255) for t in tiles]))
    out_png = Path(out_png)
    write_png(out_png, np.vstack(rows))
    return out_png
