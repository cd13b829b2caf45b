"""Ray marching: ray/box intersection, fixed-step samples and empty-space skipping, all vectorised.

Samples are packed: a flat list sorted by ray, then by distance, with `ray` indices. Skipping is
two-level: segments of `seg_steps` steps are tested against the occupancy grid dilated by the
segment's half-length (a conservative test), then only steps of occupied segments are generated and
each is kept if its own cell is occupied. Empty space therefore costs one test per segment.

Steps are uniform (bounded scenes) or, with a cone angle c > 0 (warped scenes), uniform up to the
distance step/c and then growing as c * t (instant-ngp's cone stepping), so a ray reaches far
content in few steps: t_k = t_c (1 + c)^(k - k_c) past the knee k_c.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from repaint_nerf.core.render.box import intersect_box
from repaint_nerf.core.render.occupancy import OccupancyGrid


@dataclass
class RayPlan:
    """Where each ray runs inside the marching box: first distance, last distance and number of steps."""

    t_near: Tensor  # (R,)
    t_far: Tensor  # (R,)
    n_steps: Tensor  # (R,) long, 0 for rays that miss
    step: float
    cone: float = 0.0

    def t_at(self, ray: Tensor, k: Tensor) -> Tensor:
        """Distance of (fractional) step index k on rays `ray`."""
        t0 = self.t_near[ray]
        if self.cone <= 0.0:
            return t0 + k * self.step
        return _cone_t(t0, k, self.step, self.cone)

    def steps_to(self, ray: Tensor, t: Tensor) -> Tensor:
        """Fractional step index of distance t on rays `ray` (the inverse of `t_at`)."""
        t0 = self.t_near[ray]
        if self.cone <= 0.0:
            return (t - t0) / self.step
        return _cone_steps(t0, t, self.step, self.cone)


def _cone_t(t0: Tensor, k: Tensor, step: float, cone: float) -> Tensor:
    tc = step / cone
    kc = ((tc - t0) / step).clamp_min(0.0)
    grown = torch.maximum(t0, torch.full_like(t0, tc)) * torch.exp((k - kc).clamp_min(0.0) * math.log1p(cone))
    return torch.where(k <= kc, t0 + k * step, grown)


def _cone_steps(t0: Tensor, t1: Tensor, step: float, cone: float) -> Tensor:
    """Fractional number of cone steps from t0 to t1 (inverse of `_cone_t`)."""
    tc = step / cone
    kc = ((tc - t0) / step).clamp_min(0.0)
    start = torch.maximum(t0, torch.full_like(t0, tc)).clamp_min(1e-12)
    grown = kc + torch.log(t1.clamp_min(1e-12) / start).clamp_min(0.0) / math.log1p(cone)
    return torch.where(t1 <= start, (t1 - t0) / step, grown)


@dataclass
class Samples:
    """Packed samples sorted by ray then distance; sample i covers [t_start, t_end] and is evaluated at t."""

    ray: Tensor  # (N,) long, local ray index
    t_start: Tensor  # (N,)
    t_end: Tensor  # (N,)
    t: Tensor  # (N,) evaluation distance inside the interval
    x: Tensor  # (N,3) evaluation point

    def __len__(self) -> int:
        return int(self.ray.shape[0])

    def select(self, idx: Tensor) -> "Samples":
        """The subset at `idx` (a bool mask or sorted indices keeps the packed order)."""
        return Samples(self.ray[idx], self.t_start[idx], self.t_end[idx], self.t[idx], self.x[idx])


def plan_rays(origins: Tensor, dirs: Tensor, lo: Tensor, hi: Tensor, step: float, max_samples: int,
              near: float = 0.0, cone: float = 0.0) -> RayPlan:
    """Clip rays to the box (starting no earlier than `near`) and count their steps (at most max_samples)."""
    t_min, t_max = intersect_box(origins, dirs, lo.to(origins), hi.to(origins))
    t_near = t_min.clamp_min(near)
    if cone > 0.0:  # the slack keeps float error from adding a sliver step at the box face
        steps = _cone_steps(t_near, torch.maximum(t_max, t_near), step, cone) - 1e-6
        n = torch.ceil(steps).clamp(0, max_samples).long()
        t_far = torch.minimum(t_max, _cone_t(t_near, n.to(t_near.dtype), step, cone))
    else:
        n = torch.ceil((t_max - t_near).clamp_min(0.0) / step).clamp(0, max_samples).long()
        t_far = torch.minimum(t_max, t_near + n * step)
    return RayPlan(t_near, t_far, n, step, cone)


def next_segments(origins: Tensor, dirs: Tensor, plan: RayPlan, grid: OccupancyGrid | None, ids: Tensor,
                  seg_next: Tensor, seg_steps: int, window: int, take: int) -> tuple[Tensor, Tensor, Tensor]:
    """For rays `ids`, test their next `window` segments of `seg_steps` steps against the dilated grid and
    pick the first `take` occupied ones. Advances `seg_next` in place; returns (ray, first step, count)
    sorted by ray then distance."""
    n = plan.n_steps[ids]
    j = seg_next[ids][:, None] + torch.arange(window, device=ids.device)[None, :]  # (A, window)
    first = j * seg_steps
    occ = first < n[:, None]
    if grid is not None:
        count = (n[:, None] - first).clamp(0, seg_steps)
        o, d = origins[ids][:, None, :], dirs[ids][:, None, :]
        if plan.cone <= 0.0 and grid.warp is None:
            t_mid = plan.t_near[ids][:, None] + (first + 0.5 * count) * plan.step
            pts = o + t_mid[..., None] * d
            occ &= grid.occupied_near(pts.reshape(-1, 3), 0.5 * seg_steps * plan.step).view(occ.shape)
        else:
            rays = ids[:, None].expand_as(first)
            ta = plan.t_at(rays, first.to(o.dtype))
            tb = plan.t_at(rays, (first + count).to(o.dtype))
            a, b = (o + ta[..., None] * d).reshape(-1, 3), (o + tb[..., None] * d).reshape(-1, 3)
            occ &= grid.occupied_segment(a, b).view(occ.shape)
    rank = torch.cumsum(occ.int(), 1)
    chosen = occ & (rank <= take)
    full = rank[:, -1] >= take
    last = torch.where(chosen, j, torch.full_like(j, -1)).amax(1)
    seg_next[ids] = torch.where(full, last + 1, j[:, -1] + 1)
    r, c = chosen.nonzero(as_tuple=True)
    ray = ids[r]
    seg_first = first[r, c]
    return ray, seg_first, (plan.n_steps[ray] - seg_first).clamp(max=seg_steps)


def expand_segments(origins: Tensor, dirs: Tensor, plan: RayPlan, grid: OccupancyGrid | None,
                    seg_ray: Tensor, seg_first: Tensor, seg_count: Tensor, perturb: bool) -> Samples:
    """All steps of the given segments, each kept when its own cell is occupied (packed, sorted)."""
    total = int(seg_count.sum()) if seg_count.numel() else 0
    dev = origins.device
    if total == 0:
        return empty_samples(dev)
    seg_of = torch.repeat_interleave(torch.arange(seg_count.numel(), device=dev), seg_count, output_size=total)
    seg_start = torch.cumsum(seg_count, 0) - seg_count
    k = seg_first[seg_of] + (torch.arange(total, device=dev) - seg_start[seg_of])
    ray = seg_ray[seg_of]
    if plan.cone <= 0.0:
        t_start = plan.t_near[ray] + k * plan.step
        t_end = torch.minimum(t_start + plan.step, plan.t_far[ray])
    else:
        kf = k.to(origins.dtype)
        t_start = plan.t_at(ray, kf)
        t_end = torch.minimum(plan.t_at(ray, kf + 1.0), plan.t_far[ray])
    frac = torch.rand_like(t_start) if perturb else torch.full_like(t_start, 0.5)
    t = t_start + frac * (t_end - t_start)
    x = origins[ray] + t[:, None] * dirs[ray]
    s = Samples(ray, t_start, t_end, t, x)
    if grid is not None:
        s = s.select(grid.is_occupied(x))
    return s


def empty_samples(device) -> Samples:
    """A packed sample set with no samples."""
    z = torch.zeros(0, device=device)
    return Samples(torch.zeros(0, dtype=torch.long, device=device), z, z, z, torch.zeros(0, 3, device=device))


def cat_samples(parts: list[Samples], device) -> Samples:
    """Concatenate sample sets and re-sort by ray (stable, so distances stay ordered within a ray)."""
    parts = [p for p in parts if len(p)]
    if not parts:
        return empty_samples(device)
    s = Samples(*(torch.cat([getattr(p, f) for p in parts]) for f in ("ray", "t_start", "t_end", "t", "x")))
    order = torch.sort(s.ray, stable=True).indices
    return s.select(order)
