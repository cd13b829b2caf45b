"""The field's density on a regular lattice of a field-space box (what marching cubes reads), skipping points
far from any occupied cell of the occupancy grid, in chunks with progress and cancel."""
from __future__ import annotations

import numpy as np
import torch

from repaint_nerf.core.errors import UserError
from repaint_nerf.core.export.common import Cancel, Progress, checkpoint

CHUNK = 1 << 18  # lattice points per density query


def field_box(source, bbox_world=None) -> tuple[np.ndarray, np.ndarray]:
    """Field-space (lo, hi) of the export: the field cube, cut to `bbox_world` (xmin, ymin, zmin, xmax, ymax, zmax
    in the scene's world units) when given; a box outside the field is a UserError."""
    bound = float(getattr(getattr(source.field, "cfg", None), "bound", getattr(source.field, "bound", 1.0)))
    lo, hi = np.full(3, -bound), np.full(3, bound)
    if bbox_world is not None:
        b = np.asarray(bbox_world, dtype=np.float64).reshape(-1)
        if b.size != 6 or not np.all(b[:3] < b[3:]):
            raise UserError(f"the box must be xmin,ymin,zmin,xmax,ymax,zmax with min < max, got {list(b)}")
        norm = source.scene.norm
        lo, hi = np.maximum(lo, norm.to_field(b[:3])), np.minimum(hi, norm.to_field(b[3:]))
        if not np.all(lo < hi):
            world = (norm.to_world(np.full(3, -bound)), norm.to_world(np.full(3, bound)))
            raise UserError(f"the box {list(b)} lies outside the field",
                            hint=f"the field spans {np.round(world[0], 3).tolist()} .. "
                                 f"{np.round(world[1], 3).tolist()} in world units")
    return lo, hi


def lattice_points(lo: np.ndarray, hi: np.ndarray, res: int) -> list[np.ndarray]:
    """The three axes' coordinates of a res^3 lattice spanning [lo, hi] (corners included)."""
    return [np.linspace(lo[a], hi[a], res, dtype=np.float64) for a in range(3)]


@torch.no_grad()
def density_lattice(source, lo: np.ndarray, hi: np.ndarray, res: int, cancel: Cancel | None = None,
                    progress: Progress | None = None, span: tuple[float, float] = (0.0, 1.0)) -> np.ndarray:
    """Density sigma (field units) on the res^3 lattice over [lo, hi], float32 (X, Y, Z); zero near no occupied
    cell (the renderer never samples there either)."""
    field, grid, dev = source.field, source.grid, source.device
    axes = [torch.as_tensor(a, dtype=torch.float32) for a in lattice_points(lo, hi, res)]
    spacing = float(max((hi - lo) / max(res - 1, 1)))
    out = np.zeros((res, res, res), np.float32)
    was_training = field.training
    field.eval()
    try:
        rows_per_chunk = max(1, CHUNK // (res * res))
        for x0 in range(0, res, rows_per_chunk):
            checkpoint(cancel, progress, span[0] + (span[1] - span[0]) * x0 / res, "sampling the density")
            xs = axes[0][x0:x0 + rows_per_chunk]
            pts = torch.stack(torch.meshgrid(xs, axes[1], axes[2], indexing="ij"), -1).reshape(-1, 3).to(dev)
            keep = grid.occupied_near(pts, spacing) if grid is not None else torch.ones(len(pts), dtype=torch.bool,
                                                                                          device=dev)
            sigma = torch.zeros(len(pts), device=dev)
            if keep.any():
                sigma[keep] = field.density(pts[keep]).float()
            out[x0:x0 + len(xs)] = sigma.reshape(len(xs), res, res).cpu().numpy()
    finally:
        field.train(was_training)
    return out
