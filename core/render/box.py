"""Ray-box geometry shared by the occupancy grid and the marcher (its own module, so neither imports the other)."""
from __future__ import annotations

import torch
from torch import Tensor


def intersect_box(origins: Tensor, dirs: Tensor, lo: Tensor, hi: Tensor) -> tuple[Tensor, Tensor]:
    """Slab test against the box [lo, hi] (each (3,)): (t_min, t_max) per ray; a miss has t_max <= t_min."""
    d = torch.where(dirs.abs() < 1e-12, torch.copysign(torch.full_like(dirs, 1e-12), dirs), dirs)
    inv = 1.0 / d
    t0 = (lo - origins) * inv
    t1 = (hi - origins) * inv
    return torch.minimum(t0, t1).amax(dim=-1), torch.maximum(t0, t1).amin(dim=-1)


def cube(extent: float, device=None) -> tuple[Tensor, Tensor]:
    """The box [-extent, extent]^3 as (lo, hi)."""
    e = torch.full((3,), float(extent), device=device)
    return -e, e
