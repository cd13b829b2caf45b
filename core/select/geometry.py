"""The field's geometry in a view's mask (issue 15): a 2D teacher sees one brown surface where the field
knows a loaf standing above a board. Depth discontinuities of the rendered depth become barriers, and a
view's mask is the part of `similarity > threshold` connected to seed pixels without crossing one.

A barrier pixel is the far side of a depth edge: its inverse depth is below what its neighbours on a
line predict by more than `DEPTH_EDGE` of its own value. Inverse depth is affine in pixel coordinates
on any plane, so a table seen at a grazing angle has no edge however fast its depth grows; only the
background side is marked, so the object keeps its silhouette pixels. Pixels without a surface
(opacity below 0.5) are barriers too.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

DEPTH_EDGE = 0.01  # relative inverse-depth jump: a loaf 0.2 above its board at 4 units is ~0.05; a torus 0.1
# behind a cube ~0.015 (0.02 let the "similar" cube leak into it); planes 0 at any angle
MIN_OPACITY = 0.5


def depth_edges(depth: np.ndarray, opacity: np.ndarray | None = None, rel: float = DEPTH_EDGE) -> np.ndarray:
    """Barrier pixels (bool (H, W)) of a z-depth map: far sides of depth discontinuities, and no surface."""
    z = np.asarray(depth, np.float64)
    surface = z > 0 if opacity is None else (np.asarray(opacity) > MIN_OPACITY) & (z > 0)
    w = np.where(surface, 1.0 / np.maximum(z, 1e-9), 0.0)
    edge = np.zeros(z.shape, bool)
    for axis in (0, 1):
        for step in (1, -1):
            near = np.roll(w, -step, axis)      # the neighbour on one side
            far = np.roll(w, step, axis)        # the one on the other side: with p, predicts `near`
            jump = near - (2.0 * w - far)       # > 0: the neighbour is nearer than the line through p predicts
            jump2 = near - w                    # and nearer than p itself (a step, not a bend)
            e = (jump > rel * w) & (jump2 > 0.5 * rel * w)
            # rolled-in borders compare against the opposite edge of the image: no edge on the border lines
            sl = [slice(None)] * 2
            sl[axis] = slice(-1, None)
            e[tuple(sl)] = False
            sl[axis] = slice(0, 1)
            e[tuple(sl)] = False
            edge |= e
    return edge | ~surface


def grow(candidates: np.ndarray, seeds: np.ndarray, barrier: np.ndarray | None = None) -> np.ndarray:
    """The pixels of `candidates | seeds` (minus `barrier`) 4-connected to a seed pixel (a diagonal
    step would cross a one-pixel barrier line) (bool (H, W))."""
    allowed = (np.asarray(candidates, bool) | seeds)
    if barrier is not None:
        allowed &= ~barrier
    start = seeds & allowed
    if not start.any():
        return np.zeros_like(allowed)
    _, lab = cv2.connectedComponents(allowed.astype(np.uint8), connectivity=4)
    keep = np.unique(lab[start])
    return np.isin(lab, keep[keep > 0])


def fill_holes(mask: np.ndarray, barrier: np.ndarray | None = None) -> np.ndarray:
    """`mask` with its holes filled (regions of ~mask not touching the image border), except holes that
    hold a barrier pixel: a printed label's letters join the can, a torus's hole onto the floor does not."""
    inv = (~np.asarray(mask, bool)).astype(np.uint8)
    n, lab = cv2.connectedComponents(inv, connectivity=4)
    if n <= 1:
        return mask.copy()
    border = np.unique(np.concatenate([lab[0], lab[-1], lab[:, 0], lab[:, -1]]))
    bad = set(border.tolist())
    if barrier is not None:
        bad |= set(np.unique(lab[barrier & (inv > 0)]).tolist())
    holes = np.setdiff1d(np.arange(1, n), np.array(sorted(bad), dtype=np.int64))
    return mask | np.isin(lab, holes)


@dataclass(frozen=True)
class GeometryParts:
    """Which geometry parts a mask uses (bench mask measures each): depth-edge barriers, seeded growth
    with seeds carried between views through the surface points, hole filling, and the voxel 3D
    clean-up of cleanup3d (applied last)."""

    edges: bool = True
    grow: bool = True
    holes: bool = True
    cleanup3d: bool = True

    @staticmethod
    def none() -> "GeometryParts":
        return GeometryParts(False, False, False, False)

    def names(self) -> list[str]:
        return [k for k in ("edges", "grow", "holes", "cleanup3d") if getattr(self, k)]


# The default for saved masks: the voxel clean-up only. Edges, growth and holes are measured by bench mask
# but not on by default: on a trained field's depth (tests/test_selection.py's 32 px scene) they cut the
# masks to IoU 0.07, and on true depth the growth carries a leak at one contact line to every view.
DEFAULT_PARTS = GeometryParts(edges=False, grow=False, holes=False, cleanup3d=True)

SEED_DEPTH_TOL = 0.015  # a projected seed point lands on a view's surface when its depth agrees this well (relative)
MAX_SEED_POINTS = 4000


def surface_points(mask: np.ndarray, depth: np.ndarray, cameras, view: int) -> np.ndarray:
    """Field-space points (N, 3) of the pixels of `mask` on view `view`'s rendered z-depth."""
    import torch

    idx = np.flatnonzero(mask)
    if not idx.size:
        return np.zeros((0, 3), np.float32)
    w = np.shape(mask)[1]
    ii = torch.from_numpy(idx)
    o, d, dz = cameras.rays(torch.full_like(ii, int(view)), ii % w, ii // w)  # only the masked pixels' rays
    t = torch.as_tensor(np.asarray(depth, np.float32).reshape(-1)[idx]).to(o) / dz
    return (o + d * t[:, None]).cpu().numpy().astype(np.float32)


def project_seeds(points: np.ndarray, depth: np.ndarray, cameras, view: int, tol: float = SEED_DEPTH_TOL) -> np.ndarray:
    """Pixels of view `view` (bool (H, W)) where one of `points` is seen: it projects inside the image
    and its depth agrees with the view's rendered depth (not hidden behind another surface)."""
    import torch

    h, w = depth.shape
    out = np.zeros((h, w), bool)
    if not len(points):
        return out
    uv, z = cameras.project(torch.from_numpy(points).to(cameras.c2w), int(view))
    uv, z = uv.cpu().numpy(), z.cpu().numpy()
    front = (z > 0) & np.isfinite(uv).all(1)  # points behind the camera project nowhere
    uv, z = uv[front], z[front]
    u, v = np.floor(uv[:, 0]).astype(np.int64), np.floor(uv[:, 1]).astype(np.int64)
    ok = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    u, v, z = u[ok], v[ok], z[ok]
    seen = np.abs(depth[v, u] - z) < tol * z
    out[v[seen], u[seen]] = True
    return out


def _region(sim: np.ndarray, t: float, seeds: np.ndarray, barrier: np.ndarray, parts: GeometryParts) -> np.ndarray:
    region = grow(sim > t, seeds, barrier)
    return fill_holes(region, barrier) if parts.holes else region


def geometric_masks(sims: list[np.ndarray], depths: list[np.ndarray], opacities: list[np.ndarray], cameras,
                    seeds: list[tuple[int, np.ndarray]], threshold: float, parts: GeometryParts = GeometryParts(),
                    rounds: int = 2, rng_seed: int = 0) -> list[np.ndarray]:
    """Masks (bool (H, W) per view) of `similarity > threshold` shaped by the field's geometry.

    `seeds`: (view, bool (H, W) pixels) the user marked on the object (the patch). With `parts.grow`, a
    view's mask is the part of its candidates connected to seed pixels: first the marked views, then,
    `rounds` times, every view seeded by the surface points of all masks so far that it sees (so the
    far side of an object is reached through the views between). Without it, every candidate is kept.
    """
    n = len(sims)
    surface = [np.asarray(o) > MIN_OPACITY for o in opacities]
    barriers = [depth_edges(d, o) if parts.edges else ~s for d, o, s in zip(depths, opacities, surface)]
    if not parts.grow:
        masks = [(np.asarray(s) > threshold) & ok for s, ok in zip(sims, surface)]
        return [fill_holes(m, b) for m, b in zip(masks, barriers)] if parts.holes else masks
    seed_px = [np.zeros(np.shape(s), bool) for s in sims]
    for view, px in seeds:
        seed_px[view] |= np.asarray(px, bool) & surface[view]
    masks = [_region(sims[i], threshold, seed_px[i], barriers[i], parts) if seed_px[i].any()
             else np.zeros(np.shape(sims[i]), bool) for i in range(n)]
    rng = np.random.default_rng(rng_seed)
    for _ in range(rounds):
        # interior pixels only: a silhouette pixel's depth blends object and background
        pts = np.concatenate([surface_points(cv2.erode(m.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0,
                                             depths[i], cameras, i) for i, m in enumerate(masks)])
        if len(pts) > MAX_SEED_POINTS:
            pts = pts[rng.choice(len(pts), MAX_SEED_POINTS, replace=False)]
        new = []
        for i in range(n):
            s = seed_px[i] | project_seeds(pts, np.asarray(depths[i], np.float32), cameras, i)
            s &= (np.asarray(sims[i]) > threshold) | seed_px[i]
            new.append(_region(sims[i], threshold, s, barriers[i], parts))
        if all((a == b).all() for a, b in zip(new, masks)):
            break
        masks = new
    return masks
