"""The 3D region of the saved selection: the training views' masked surface points (back-projected with the
rendered z-depth, as core.select.cleanup3d does) vote their voxels in, unmasked surface points vote them out;
the voxels won by the selection, filled inside and grown by one voxel, hold the selected object."""
from __future__ import annotations

import numpy as np
import torch

from repaint_nerf.core.errors import UserError, WorkspaceError
from repaint_nerf.core.export.common import Cancel, Progress, checkpoint
from repaint_nerf.core.select.cleanup3d import FOOTPRINT_VOXELS, backproject

MIN_OPACITY = 0.5  # a pixel whose render is less opaque shows no surface to place
MAX_CELLS = 96  # region voxels per axis at most (the vote needs several pixels per voxel)
REGION_VIEWS = 16  # training views that place the selection (evenly spread; each costs a render)


def saved_masks(source, masks=None) -> list[np.ndarray]:
    """The selection's per-view masks (given, else the workspace's saved ones); none or all empty is a UserError."""
    if masks is None:
        from repaint_nerf.core.select.masks import load_masks

        if source.workspace is None:
            raise UserError("nothing is selected", hint="select an object first (repaint-nerf select WS ...)")
        try:
            masks = load_masks(source.workspace.masks_dir)
        except WorkspaceError:
            raise UserError("nothing is selected in this workspace", source.workspace.root,
                            hint="select an object first: repaint-nerf select WS --view I --patch X0,Y0,X1,Y1"
                            ) from None
    masks = [np.asarray(m).astype(bool) for m in masks]
    if not masks or not any(m.any() for m in masks):
        raise UserError("the selection is empty: no pixel of any view is selected",
                        getattr(source.workspace, "root", None),
                        hint="select a patch on the object, or lower the threshold")
    return masks


class SelectionRegion:
    """Coarse voxels of the selected object (the vote above, filled and grown by a voxel), sharpened at pixel
    precision: a point that some view sees (its depth within `tolerance` of that view's rendered depth) outside
    that view's mask, and no view sees inside, is left out. Points no view sees (an object's inside or underside)
    follow the voxels."""

    def __init__(self, voxels: np.ndarray, voxel: float, lo: np.ndarray, cams, depths: list, masks: list,
                 tolerance: float):
        self.voxels, self.voxel, self.lo = voxels, float(voxel), np.asarray(lo, np.float64)
        self.cams, self.depths, self.masks, self.tolerance = cams, depths, masks, float(tolerance)

    def in_voxels(self, points: np.ndarray) -> np.ndarray:
        c = np.floor((points - self.lo) / self.voxel).astype(int)
        ok = np.all((c >= 0) & (c < self.voxels.shape), axis=1)
        out = np.zeros(len(points), bool)
        out[ok] = self.voxels[tuple(c[ok].T)]
        return out

    @torch.no_grad()
    def contains(self, points: np.ndarray) -> np.ndarray:
        """Whether each field-space point (N, 3) belongs to the selected object."""
        keep = self.in_voxels(points)
        idx = np.nonzero(keep)[0]
        if not len(idx):
            return keep
        p = torch.as_tensor(points[idx], dtype=torch.float32)
        seen_in = torch.zeros(len(idx), dtype=torch.bool)
        seen_out = torch.zeros(len(idx), dtype=torch.bool)
        for i, (depth, mask) in enumerate(zip(self.depths, self.masks)):
            uv, z = self.cams.project(p, i)
            h, w = depth.shape
            u, v = torch.floor(uv[:, 0]).long(), torch.floor(uv[:, 1]).long()
            on = (z > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
            u, v = u.clamp(0, w - 1), v.clamp(0, h - 1)
            visible = on & ((z - depth[v, u]).abs() <= self.tolerance)
            sel = mask[v, u]
            seen_in |= visible & sel
            seen_out |= visible & ~sel
        keep[idx[(seen_out & ~seen_in).numpy()]] = False
        return keep


@torch.no_grad()
def selection_region(source, masks: list[np.ndarray], lo: np.ndarray, hi: np.ndarray,
                     cancel: Cancel | None = None, progress: Progress | None = None,
                     span: tuple[float, float] = (0.0, 1.0), tolerance: float = 0.0) -> SelectionRegion:
    """The selected object's region over the field-space box [lo, hi] (see SelectionRegion); `tolerance` (field
    units, at least the pixels' footprint) is how far from a view's rendered depth a point still counts as seen."""
    from scipy import ndimage

    cams = source.scene.field_cameras("train")
    if len(masks) != len(cams):
        raise UserError(f"the saved selection has {len(masks)} masks but the scene {len(cams)} training views",
                        getattr(source.workspace, "root", None), hint="select again in this workspace")
    views = source.train_views(REGION_VIEWS)
    inside, outside, footprint, depths = [], [], [], []
    for k, i in enumerate(views):
        checkpoint(cancel, progress, span[0] + (span[1] - span[0]) * k / len(views), "placing the selection in 3D")
        depth, opacity = source.depth_opacity(i)
        m = masks[i]
        if tuple(m.shape) != tuple(depth.shape):
            raise UserError(f"mask {i} is {m.shape[1]}x{m.shape[0]} px but view {i} is "
                            f"{depth.shape[1]}x{depth.shape[0]}",
                            getattr(source.workspace, "root", None), hint="select again in this workspace")
        surface = opacity > MIN_OPACITY
        depths.append(torch.where(surface, depth, torch.full_like(depth, float("inf"))))
        surface = surface.reshape(-1)
        pts = backproject(depth, cams, i)
        sel = torch.as_tensor(m).reshape(-1)
        inside.append(pts[surface & sel])
        outside.append(pts[surface & ~sel])
        if (surface & sel).any():
            footprint.append(depth.reshape(-1)[surface & sel] / float(cams.fx[i]))
    pin = torch.cat(inside)
    if not len(pin):
        raise UserError("the selection covers no surface of the field", getattr(source.workspace, "root", None),
                        hint="select a patch on an object (not the background)")
    pixel = float(torch.cat(footprint).median())
    voxel = max(float(np.max(hi - lo)) / MAX_CELLS, FOOTPRINT_VOXELS * pixel)
    dims = np.maximum(np.ceil((hi - lo) / voxel).astype(int), 1)

    def votes(p: torch.Tensor) -> np.ndarray:
        c = np.floor((p.double().numpy() - lo) / voxel).astype(int)
        ok = np.all((c >= 0) & (c < dims), axis=1)
        return np.bincount(np.ravel_multi_index(c[ok].T, dims), minlength=int(np.prod(dims))).reshape(dims)

    won = votes(pin) > votes(torch.cat(outside))
    voxels = ndimage.binary_dilation(ndimage.binary_fill_holes(won), iterations=1)
    return SelectionRegion(voxels, voxel, lo, cams[views], depths, [torch.as_tensor(masks[i]) for i in views],
                           max(tolerance, 2.0 * pixel))
