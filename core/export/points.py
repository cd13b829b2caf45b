"""A coloured point cloud of the field's surface: every training view's pixels that show a surface (opacity above
one half) placed at their rendered expected z-depth, coloured by the render, in world units; written as .ply by
trimesh. `selection=True` keeps the selected pixels (the saved masks) only."""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import torch

from repaint_nerf.core.errors import UserError
from repaint_nerf.core.export.common import Cancel, Progress, atomic_output, check_output_file, checkpoint
from repaint_nerf.core.export.region import MIN_OPACITY, saved_masks
from repaint_nerf.core.select.cleanup3d import backproject

POINT_SUFFIXES = (".ply",)


@torch.no_grad()
def surface_points(source, selection: bool = False, masks=None, max_points: int | None = None, seed: int = 0,
                   cancel: Cancel | None = None, progress: Progress | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(world points (N, 3) float64, colours (N, 3) uint8) from the training views' renders."""
    from repaint_nerf.core.render.renderer import render_camera

    cams = source.scene.field_cameras("train")
    masks = saved_masks(source, masks) if selection else None
    opts = source.render_options(("rgb", "depth", "opacity"))  # black background: rgb / opacity is the surface colour
    dev_cams = cams.to(source.device)
    pts, cols = [], []
    for i in range(len(cams)):
        checkpoint(cancel, progress, 0.95 * i / len(cams), f"rendering view {i + 1}/{len(cams)}")
        out = render_camera(source.field, source.grid, dev_cams, i, opts)
        alpha = out["opacity"].float().cpu().reshape(-1)
        keep = alpha > MIN_OPACITY
        if masks is not None:
            keep &= torch.as_tensor(masks[i]).reshape(-1)
        if not keep.any():
            continue
        pts.append(backproject(out["depth"].float().cpu(), cams, i)[keep].double().numpy())
        rgb = out["rgb"].float().cpu().reshape(-1, 3)[keep] / alpha[keep, None]
        cols.append((rgb.clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8))
    if not pts:
        raise UserError("no view shows a surface" + (" in the selection" if selection else ""),
                        getattr(source.workspace, "root", None), hint="train longer, or select an object")
    xyz, rgb = np.concatenate(pts), np.concatenate(cols)
    if max_points is not None and len(xyz) > max_points:
        pick = np.sort(np.random.default_rng(seed).choice(len(xyz), int(max_points), replace=False))
        xyz, rgb = xyz[pick], rgb[pick]
    return source.scene.norm.to_world(xyz), rgb


def write_points(xyz: np.ndarray, rgb: np.ndarray, path: str | Path) -> Path:
    """Write a coloured point cloud as binary .ply (trimesh), atomically."""
    import trimesh

    path = check_output_file(path, POINT_SUFFIXES, "point cloud")
    data = trimesh.PointCloud(xyz, colors=rgb).export(file_type="ply")
    with atomic_output(path, "point cloud") as tmp:
        tmp.write_bytes(data)
    return path


def export_points(source, path: str | Path, selection: bool = False, masks=None, max_points: int | None = None,
                  cancel: Cancel | None = None, progress: Progress | None = None) -> dict:
    """Compute and write the point cloud; returns facts for the message (path, points, bytes, seconds)."""
    if max_points is not None and max_points < 1:
        raise UserError(f"--max-points must be at least 1, got {max_points}")
    path = check_output_file(path, POINT_SUFFIXES, "point cloud")
    t0 = time.perf_counter()
    xyz, rgb = surface_points(source, selection, masks, max_points, cancel=cancel, progress=progress)
    write_points(xyz, rgb, path)
    checkpoint(None, progress, 1.0, "points written")
    return {"path": str(path), "points": int(len(xyz)), "bytes": path.stat().st_size,
            "seconds": time.perf_counter() - t0, "bounds": [xyz.min(0).tolist(), xyz.max(0).tolist()]}
