"""3D clean-up of selection masks (beyond DFF): keep only the selected pixels whose surface point is
connected in 3D to the patch's surface points.

Every masked pixel of every view is back-projected with the rendered z-depth into field space and
dropped into a voxel grid; the voxels reachable from the voxels of the patch's pixels through occupied
voxels (26-neighbourhood, `bridge` voxels of gap allowed) form the object. Masked pixels elsewhere, on
floaters or on a look-alike object, and pixels with no surface (low opacity) are removed.
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as tnf
from torch import Tensor

VOXEL = 2.0 / 128  # field units: the field cube [-1, 1]^3 at 128 voxels a side
MAX_DIM = 256
FOOTPRINT_VOXELS = 1.5  # voxel edge in median pixel footprints (grazing surfaces stretch the spacing)  # voxels per axis; coarser voxels when the masked points spread wider


def backproject(depth: Tensor, cameras, view: int) -> Tensor:
    """Field-space surface points (H*W, 3) of view `view` from its rendered z-depth (H, W)."""
    o, d, dz = cameras.image_rays(int(view))
    t = depth.reshape(-1).to(o) / dz
    return o + d * t[:, None]


def flood_fill(occupied: Tensor, seeds: Tensor, bridge: int = 1) -> Tensor:
    """Voxels of `occupied` (bool (X, Y, Z)) connected to `seeds` (bool, same shape) through occupied
    voxels, stepping up to `bridge` voxels in each axis at a time."""
    k = 2 * bridge + 1
    occ = occupied.float()[None, None]
    reached = (seeds & occupied).float()[None, None]
    count = int(reached.sum())
    while count:
        for _ in range(8):  # several dilations per convergence check
            reached = tnf.max_pool3d(reached, k, stride=1, padding=bridge) * occ
        new = int(reached.sum())
        if new == count:
            break
        count = new
    return reached[0, 0] > 0


def cleanup_masks(masks: list[Tensor], depths: list[Tensor], opacities: list[Tensor], cameras,
                  seeds: list[tuple[int, object]], min_opacity: float = 0.5, voxel: float = VOXEL,
                  bridge: int = 1) -> list[Tensor]:
    """Masks with pixels not 3D-connected to the seed patches removed (see the module docstring).

    `seeds` are (view, bool (H, W)) pixels the user marked (a patch, or a free-view patch's points carried into
    the view); with no seed or no masked surface point the masks come back unchanged.
    """
    cams = cameras.to("cpu")
    pts, flat_idx, footprint = [], [], []
    for i, (m, dep, op) in enumerate(zip(masks, depths, opacities)):
        keep = (m.cpu() & (op.cpu() > min_opacity)).reshape(-1)
        idx = keep.nonzero()[:, 0]
        flat_idx.append(idx)
        pts.append(backproject(dep.cpu().float(), cams, i)[idx] if idx.numel() else torch.zeros(0, 3))
        if idx.numel():  # pixel spacing on the surface: z / focal length
            footprint.append(dep.reshape(-1)[idx].float().cpu() / float(cams.fx[i]))
    allp = torch.cat(pts)
    seed_pts = []
    for view, px in seeds:
        dep, op = depths[view].cpu().float(), opacities[view].cpu()
        sub = torch.as_tensor(px, dtype=torch.bool) & (op > min_opacity) & masks[view].cpu()
        if sub.any():
            seed_pts.append(backproject(dep, cams, view)[sub.reshape(-1)])
    if allp.shape[0] == 0 or not seed_pts:
        return [m.clone() for m in masks]
    lo = allp.min(0).values
    # neighbouring pixels must land in touching voxels: voxels no finer than the pixel footprint
    voxel = max(voxel, FOOTPRINT_VOXELS * float(torch.cat(footprint).median()))
    span = float((allp.max(0).values - lo).max())
    voxel = max(voxel, span / (MAX_DIM - 1))
    dims = [int(math.floor(float(s) / voxel)) + 1 for s in (allp.max(0).values - lo)]

    def cell(p: Tensor) -> Tensor:
        c = torch.floor((p - lo) / voxel).long()
        return torch.minimum(c.clamp_min(0), torch.tensor(dims) - 1)

    occ = torch.zeros(dims, dtype=torch.bool)
    c = cell(allp)
    occ[c[:, 0], c[:, 1], c[:, 2]] = True
    seed = torch.zeros_like(occ)
    s = cell(torch.cat(seed_pts))
    seed[s[:, 0], s[:, 1], s[:, 2]] = True
    reached = flood_fill(occ, seed, bridge)
    out, start = [], 0
    for m, idx in zip(masks, flat_idx):
        n = idx.numel()
        cc = c[start:start + n]
        start += n
        ok = reached[cc[:, 0], cc[:, 1], cc[:, 2]]
        new = torch.zeros(m.numel(), dtype=torch.bool)
        new[idx[ok]] = True
        out.append(new.reshape(m.shape).to(m.device))
    return out
