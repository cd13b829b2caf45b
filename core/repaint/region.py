"""The selection's 3D region: the visual hull of its masks, points inside it, and its occupancy cells."""
from __future__ import annotations

import torch
from torch import Tensor


@torch.no_grad()
def selection_region(cameras, masks: list[Tensor], bound: float = 1.0, resolution: int = 64,
                     min_views: int = 2) -> Tensor:
    """Voxels (resolution^3 bool over [-bound, bound]^3) of the selection's visual hull.

    A voxel belongs when every training view whose image holds its centre (in front of the camera)
    sees it inside the mask, and at least `min_views` views hold it. Masks are (H_i, W_i) at each
    camera's resolution (the cameras may be scaled to the masks' size).
    """
    dev = cameras.device
    r = resolution
    ax = (torch.arange(r, device=dev, dtype=torch.float32) + 0.5) * (2 * bound / r) - bound
    pts = torch.stack(torch.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
    seen = torch.zeros(pts.shape[0], dtype=torch.int32, device=dev)
    inside = torch.ones(pts.shape[0], dtype=torch.bool, device=dev)
    for i, m in enumerate(masks):
        uv, z = cameras.project(pts, i)
        h, w = m.shape[-2:]
        u, v = torch.floor(uv[:, 0]).long(), torch.floor(uv[:, 1]).long()
        ok = (z > 1e-6) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        hit = torch.zeros_like(ok)
        hit[ok] = m.to(dev)[v[ok], u[ok]] > 0.5
        seen += ok.int()
        inside &= ~ok | hit
    return (inside & (seen >= min_views)).reshape(r, r, r)


def region_points(region: Tensor, bound: float, n: int, generator: torch.Generator | None = None) -> Tensor:
    """`n` points drawn uniformly inside the region's voxels (jittered), (n, 3); empty when it is empty."""
    idx = region.reshape(-1).nonzero(as_tuple=True)[0]
    if idx.numel() == 0:
        return torch.zeros(0, 3, device=region.device)
    r = region.shape[0]
    pick = idx[torch.randint(0, idx.numel(), (n,), generator=generator, device="cpu").to(idx.device)]
    ijk = torch.stack([pick // (r * r), (pick // r) % r, pick % r], -1).float()
    jitter = torch.rand(n, 3, generator=generator, device="cpu").to(region.device)
    return (ijk + jitter) * (2 * bound / r) - bound


def mark_region_occupied(grid, region: Tensor, bound: float) -> int:
    """Mark the occupancy grid's cells that hold region voxels occupied (new content may grow there).

    Their density is raised to a little above the grid's threshold, so the normal decay frees them again
    after a few hundred steps if nothing grows. Returns the number of cells marked.
    """
    if grid is None or not bool(region.any()):
        return 0
    r = region.shape[0]
    idx = region.reshape(-1).nonzero(as_tuple=True)[0]
    ijk = torch.stack([idx // (r * r), (idx // r) % r, idx % r], -1).float()
    pts = (ijk + 0.5) * (2 * bound / r) - bound
    return grid.mark_occupied(pts)
