"""Occupancy grid for empty-space skipping, with instant-ngp's update rules.

Each cascade c is a resolution^3 grid over the cube [-bound*2^c, bound*2^c]^3 holding a decayed
maximum of sampled density (`density`) and a boolean `occupied` field derived from it by a threshold.
For a field with a space warp (unbounded or forward-facing scenes) the grid has one cascade over the
warped cube [-1, 1]^3: lookups warp their field-space points first, updates unwarp the cell points.
Cells that no training camera sees (`restrict_to_views`) are never occupied nor evaluated.
"""
from __future__ import annotations

import math
from collections.abc import Callable

import torch
import torch.nn.functional as F
from torch import Tensor

from repaint_nerf.core.device import get_device
from repaint_nerf.core.render.box import intersect_box
from repaint_nerf.core.errors import UserError

MIN_OPTICAL_THICKNESS = 0.01  # instant-ngp: a cell is empty when sigma * min_step stays below this
SEGMENT_SLACK = 1.25  # warped segments bend: the test box reaches 25% past the warped chord
MAX_SEGMENT_CELLS = 8  # a segment spanning more cells than this is simply marched


def default_step(bound: float, max_samples: int) -> float:
    """Marching step so that `max_samples` steps cross the diagonal of [-bound, bound]^3 (instant-ngp: 1024)."""
    return 2.0 * math.sqrt(3.0) * bound / max_samples


class OccupancyGrid:
    """Per-cascade density grid (float) and occupancy (bool), updated every `update_every` steps."""

    def __init__(self, resolution: int = 128, cascades: int = 1, bound: float = 1.0, device=None,
                 min_step: float | None = None, update_every: int = 16, warmup_steps: int = 256,
                 decay: float = 0.95, eval_chunk: int = 1 << 18, warp=None, march_extent: float | None = None,
                 spread: bool = False):
        if resolution < 1 or cascades < 1 or bound <= 0:
            raise UserError(f"occupancy grid needs resolution >= 1, cascades >= 1 and bound > 0 "
                            f"(got {resolution}, {cascades}, {bound})")
        self.warp = warp
        self.resolution = int(resolution)
        self.cascades = 1 if warp is not None else int(cascades)
        self.bound = 1.0 if warp is not None else float(bound)
        self._march_extent = float(march_extent) if warp is not None and march_extent else None
        self.device = torch.device(device) if device is not None else get_device()
        self.min_step = float(min_step) if min_step else default_step(self.bound, 1024)
        self.update_every = int(update_every)
        self.warmup_steps = int(warmup_steps)
        self.decay = float(decay)
        self.eval_chunk = int(eval_chunk)
        self.spread = bool(spread)  # see update()
        self._pending: tuple[list[Tensor], Tensor, int] | None = None
        self._reopen: Tensor | None = None  # cells queued by reopen() for the next update
        self._seeded = False  # the density holds at least one update (or a checkpoint's)
        n = self.resolution ** 3
        self.density = torch.zeros(self.cascades, n, device=self.device)
        self.occupied = torch.ones(self.cascades, n, dtype=torch.bool, device=self.device)
        self.visible = torch.ones(self.cascades, n, dtype=torch.bool, device=self.device)  # restrict_to_views
        self._visible_idx: list[Tensor] | None = None  # per cascade, its visible cells; None: all are
        self.mean_density = 0.0
        self._version = 0
        self._dilated: dict[tuple, Tensor] = {}
        self._weights: dict[torch.device, Tensor] = {}

    # --- geometry ---------------------------------------------------------------------------
    def cascade_extent(self, c: int) -> float:
        """Half-size of cascade c's cube."""
        return self.bound * 2.0 ** c

    @property
    def extent(self) -> float:
        """Rays are marched inside [-extent, extent]^3 (field space): the outermost cascade, or the warp's reach."""
        if self._march_extent is not None:
            return self._march_extent
        return self.cascade_extent(self.cascades - 1)

    def to_grid(self, x: Tensor) -> Tensor:
        """Field-space points (N,3) in the grid's space (warped when the field has a warp)."""
        return self.warp(x) if self.warp is not None else x

    def _cell_index(self, x: Tensor, c: int) -> Tensor:
        """Flat cell index (N,) of points (N,3) in cascade c, clamped to the grid."""
        e = self.cascade_extent(c)
        r = self.resolution
        if r ** 3 > 1 << 24:  # past float32's exact integers
            ijk = ((x + e) * (r / (2.0 * e))).long().clamp_(0, r - 1)  # truncation == floor after the clamp
            return (ijk[:, 0] * r + ijk[:, 1]) * r + ijk[:, 2]  # not a matmul: CUDA has no integer matmul
        # float cell coordinates and a float matmul, exact below 2^24 cells: on CPU 9x faster at 262k points than
        # integer arithmetic on (N,3) longs; the last clamp keeps a NaN point's index inside the grid
        ijk = ((x.float() + e) * (r / (2.0 * e))).clamp_(0, r - 1).floor_()
        return (ijk @ self._cell_weights(x.device)).long().clamp_(0, r ** 3 - 1)

    def _cell_weights(self, device: torch.device) -> Tensor:
        """(r^2, r, 1) as a float32 vector on `device`: `_cell_index`'s row-major flattening."""
        w = self._weights.get(device)
        if w is None:
            r = float(self.resolution)
            w = self._weights[device] = torch.tensor([r * r, r, 1.0], device=device)
        return w

    def occupied_bbox(self) -> tuple[Tensor, Tensor]:
        """Axis-aligned box (lo, hi) around all occupied cells (cell bounds); a point when nothing is occupied."""
        if self.warp is not None:  # a box in warped space is no box in field space
            e = torch.full((3,), self.extent, device=self.device)
            return -e, e
        key = (self._version, "bbox")
        if key not in self._dilated:
            r = self.resolution
            lo = torch.full((3,), math.inf, device=self.device)
            hi = torch.full((3,), -math.inf, device=self.device)
            for c in range(self.cascades):
                occ = self.occupied[c].view(r, r, r)
                if not bool(occ.any()):
                    continue
                e = self.cascade_extent(c)
                for a in range(3):
                    other = tuple(b for b in range(3) if b != a)
                    idx = occ.any(dim=other[1]).any(dim=other[0]).nonzero(as_tuple=True)[0]
                    lo[a] = min(float(lo[a]), float(idx[0]) * 2 * e / r - e)
                    hi[a] = max(float(hi[a]), float(idx[-1] + 1) * 2 * e / r - e)
            if not bool(torch.isfinite(lo).all()):
                lo, hi = torch.zeros(3, device=self.device), torch.zeros(3, device=self.device)
            self._dilated[key] = (lo, hi)
        return self._dilated[key]

    def cascade_of(self, x: Tensor) -> Tensor:
        """Smallest cascade whose cube holds each point (N,) long, clamped to the outermost."""
        if self.cascades == 1:
            return torch.zeros(x.shape[0], dtype=torch.long, device=x.device)
        m = x.abs().amax(dim=-1).clamp_min(1e-30) / self.bound
        return torch.ceil(torch.log2(m)).clamp(0, self.cascades - 1).long()

    def _cells(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """Cascade (N,) and flat cell index (N,) of grid-space points (N,3), each in the smallest cascade
        holding it (clamped to the outermost)."""
        c = self.cascade_of(x)
        if self.cascades == 1:
            return c, self._cell_index(x, 0)
        idx = torch.zeros(x.shape[0], dtype=torch.long, device=x.device)
        for ci in range(self.cascades):
            sel = (c == ci).nonzero(as_tuple=True)[0]
            if sel.numel():
                idx[sel] = self._cell_index(x[sel], ci)
        return c, idx

    def is_occupied(self, x: Tensor) -> Tensor:
        """Occupancy of the cell holding each point (N,3) -> (N,) bool; points outside every cascade are empty."""
        x = self.to_grid(x.to(self.device))
        inside = (x.abs().amax(dim=-1) <= self.cascade_extent(self.cascades - 1))
        c, idx = self._cells(x)
        return self.occupied[c, idx] & inside

    def _derived(self, key: tuple, make: Callable[[], Tensor]) -> Tensor:
        """A map derived from the current occupancy, made once per update (older ones are dropped)."""
        key = (self._version, *key)
        if key not in self._dilated:
            self._dilated = {k: v for k, v in self._dilated.items() if k[0] == self._version}
            self._dilated[key] = make()
        return self._dilated[key]

    def dilated(self, c: int, radius: int) -> Tensor:
        """Cascade c's occupancy dilated by `radius` cells in each axis (box max filter), cached per update."""
        def make() -> Tensor:
            r = self.resolution
            g = self.occupied[c].view(1, 1, r, r, r).float()
            if radius > 0:
                k = 2 * radius + 1
                for ks in ((k, 1, 1), (1, k, 1), (1, 1, k)):  # separable box max
                    pad = tuple(s // 2 for s in ks)
                    g = F.max_pool3d(g, ks, stride=1, padding=pad)
            return g.view(-1) > 0
        return self._derived((c, radius), make)

    def blocks(self, factor: int) -> Tensor:
        """(cascades, (resolution/factor)^3) bool: whether any cell of each factor^3 block is occupied (a coarse
        level for skipping large empty regions in one jump), cached per update."""
        def make() -> Tensor:
            r = self.resolution
            g = self.occupied.view(self.cascades, 1, r, r, r).float()
            return (F.max_pool3d(g, factor, stride=factor) > 0).reshape(self.cascades, -1)
        return self._derived(("blocks", factor), make)

    def occupied_segment(self, a: Tensor, b: Tensor) -> Tensor:
        """Whether any occupied cell lies near each segment a -> b (N,3 field-space endpoints), for any warp:
        a box around the warped midpoint reaching past both warped ends (with slack for the warp's bend).
        Segments spanning more than `MAX_SEGMENT_CELLS` cells count as occupied (conservative)."""
        ym = self.to_grid(0.5 * (a + b))
        if self.warp is None:
            half = 0.5 * (b - a).abs().amax(dim=-1)
            if self.cascades > 1:
                return self.occupied_near(ym, float(half.max()) if half.numel() else 0.0)
        else:
            ya, yb = self.to_grid(a), self.to_grid(b)
            half = SEGMENT_SLACK * torch.maximum((ya - ym).abs().amax(-1), (yb - ym).abs().amax(-1))
        e = self.bound
        cells = torch.ceil(half * (self.resolution / (2.0 * e)) - 1e-6).clamp_min(0).long()
        out = cells > MAX_SEGMENT_CELLS
        for r in cells[~out].unique().tolist():
            sel = (cells == r).nonzero(as_tuple=True)[0]
            out[sel] = self.dilated(0, int(r))[self._cell_index(ym[sel], 0)]
        return out & (ym.abs() <= e + half[:, None]).all(-1)

    def occupied_near(self, x: Tensor, half: float) -> Tensor:
        """Whether any occupied cell lies within `half` (per axis) of each point (N,3): a conservative test
        for a ray segment of half-length `half` centred at x (unwarped grids)."""
        if self.cascades == 1:
            radius = int(math.ceil(half * self.resolution / (2.0 * self.bound) - 1e-9))
            return self.dilated(0, radius)[self._cell_index(x, 0)]
        out = torch.zeros(x.shape[0], dtype=torch.bool, device=x.device)
        m = x.abs().amax(dim=-1)
        for c in range(self.cascades):
            e = self.cascade_extent(c)
            radius = int(math.ceil(half * self.resolution / (2.0 * e) - 1e-9))
            near_box = m <= e + half
            if c > 0:  # points well inside the inner cascade use its finer cells only
                near_box &= m + half > self.cascade_extent(c - 1)
            occ = self.dilated(c, radius)[self._cell_index(x, c)]
            out |= near_box & occ
        return out

    # --- updates ----------------------------------------------------------------------------
    def mark_all(self) -> None:
        """Mark every cell occupied (before training, or to render without skipping)."""
        self.occupied.fill_(True)
        self._version += 1

    def occupied_fraction(self) -> float:
        """Fraction of occupied cells over all cascades."""
        return float(self.occupied.float().mean())

    def threshold(self) -> float:
        """Density above which a cell is occupied: min(mean density of cascade 0, 0.01 / min_step)."""
        return min(self.mean_density, MIN_OPTICAL_THICKNESS / self.min_step)

    def _cell_points(self, idx: Tensor, c: int) -> Tensor:
        r = self.resolution
        ijk = torch.stack([idx // (r * r), (idx // r) % r, idx % r], dim=-1).float()
        ijk += torch.rand_like(ijk)  # a jittered point inside each cell
        e = self.cascade_extent(c)
        y = ijk * (2.0 * e / r) - e
        return self.warp.inverse(y) if self.warp is not None else y

    def mark_occupied(self, x: Tensor, level: float | None = None) -> int:
        """Mark the cells holding field-space points (N,3) occupied, their density raised to at least `level`
        (default twice the threshold), so new content is marched before the next update sees it.
        Returns the number of cells marked."""
        cells = self._cell_index(self.to_grid(x.to(self.device)), 0).unique()
        cells = cells[self.visible[0, cells]]
        lvl = max(2.0 * float(self.threshold()), 1e-3) if level is None else float(level)
        self.density[0, cells] = torch.clamp_min(self.density[0, cells], lvl)
        self.occupied[0, cells] = True
        self._version += 1
        return int(cells.numel())

    def _update_cells(self, step: int) -> list[Tensor]:
        """Per cascade, the cells an update evaluates: all visible ones during warm-up, else 1/4 of them uniformly
        + a quarter of all cells' count drawn from the occupied ones (instant-ngp's rule; visibility leaves each
        occupied cell's refresh rate as it was)."""
        n = self.resolution ** 3
        cells = []
        for c in range(self.cascades):
            seen = self._visible_idx[c] if self._visible_idx is not None else None
            m = n if seen is None else seen.numel()
            if step < self.warmup_steps:
                idx = torch.arange(n, device=self.device) if seen is None else seen
            else:
                idx = torch.randint(0, n, (n // 4,), device=self.device) if seen is None \
                    else seen[torch.randint(0, m, (m // 4,), device=self.device)]
                occ = self.occupied[c].nonzero(as_tuple=True)[0]
                if occ.numel():
                    idx = torch.cat([idx, occ[torch.randint(0, occ.numel(), (n // 4,), device=self.device)]])
            cells.append(idx)
        return cells

    def _sample(self, cells: list[Tensor], fresh: Tensor, density_fn: Callable[[Tensor], Tensor]) -> None:
        for c, idx in enumerate(cells):
            for s in range(0, idx.numel(), self.eval_chunk):
                part = idx[s:s + self.eval_chunk]
                sigma = density_fn(self._cell_points(part, c)).reshape(-1).float()
                sigma = torch.nan_to_num(sigma, nan=0.0, posinf=3.0e38).clamp_min(0.0).to(self.device)
                fresh[c].scatter_reduce_(0, part, sigma, reduce="amax")

    def _apply(self, fresh: Tensor) -> None:
        self._seeded = True
        self.density = torch.maximum(self.density * self.decay, fresh)
        self.mean_density = self._visible_mean()
        self.occupied = self.density > self.threshold()
        if self._reopen is not None:  # open for one period; their density is untouched, so the next
            self.occupied |= self._reopen  # update prunes them again unless the field has filled them
            self._reopen = None
        if self._visible_idx is not None:
            self.occupied &= self.visible
        self._version += 1

    def _visible_mean(self) -> float:
        """Mean density of cascade 0's visible cells: the unseen ones hold no content, so they do not lower the
        threshold."""
        d = self.density[0]
        return float(d.mean() if self._visible_idx is None else d[self._visible_idx[0]].mean())

    @torch.no_grad()
    def restrict_to_views(self, cameras) -> float:
        """Never occupy (nor evaluate) a cell that no camera of `cameras` (field space) sees; returns the visible
        fraction of the cells.

        Why: content only trains where some training ray passes, so elsewhere an update can only find fog the
        field was initialised with. Seen from a new angle (an orbit behind a capture's arc), that fog costs
        samples and looks like floaters. instant-ngp marks such cells untrained the same way: a cell is seen
        when one of its 8 corners projects inside an image in front of its camera; here also when a neighbour
        is, so that a frustum's tip slipping between corners keeps its cells."""
        cams = cameras.to(self.device)
        r = self.resolution
        visible = torch.zeros_like(self.visible)
        ax = torch.arange(r + 1, device=self.device, dtype=torch.float32)
        corner = torch.stack(torch.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
        for c in range(self.cascades):
            e = self.cascade_extent(c)
            y = corner * (2.0 * e / r) - e
            x = self.warp.inverse(y.clamp(-e * (1 - 1e-6), e * (1 - 1e-6))) if self.warp is not None else y
            seen = torch.zeros(x.shape[0], dtype=torch.bool, device=self.device)
            left = torch.arange(x.shape[0], device=self.device)
            for v in range(len(cams)):  # each camera projects only the corners no earlier one saw
                view = torch.tensor([v])
                hit = cams.in_image(*cams.project_views(x[left], view), view)[0]
                seen[left[hit]] = True
                left = left[~hit]
                if left.numel() == 0:
                    break
            g = F.max_pool3d(seen.view(1, 1, r + 1, r + 1, r + 1).float(), 2, stride=1)  # any corner
            g = F.max_pool3d(g, 3, stride=1, padding=1)  # or a neighbour's
            visible[c] = g.reshape(-1) > 0
        self._set_visible(visible)
        return float(visible.float().mean())

    def _set_visible(self, visible: Tensor) -> None:
        """Take `visible` (cascades, resolution^3) bool as the cells that may hold content; clear the others."""
        self.visible = visible
        self._visible_idx = None if bool(visible.all()) else [v.nonzero(as_tuple=True)[0] for v in visible]
        self.density.mul_(visible)
        self.occupied &= visible
        self._version += 1

    @torch.no_grad()
    def reopen(self, origins: Tensor, dirs: Tensor, t_end: Tensor | None = None) -> int:
        """Queue every cell that rays (R,3) in field space cross before distance `t_end` (R,; inf = the whole
        ray) to be occupied from the next update until the one after.

        Why: a structure thinner than a cell (a pole, a wire) can be pruned before the field has learned
        it, and a pruned cell is never sampled, so the field never does. The trainer reopens the path of
        the rays it renders worst, giving the field one update period to put density there.
        Returns the number of distinct cells queued."""
        if origins.shape[0] == 0:
            return 0
        o = origins.to(self.device, torch.float32).reshape(-1, 3)
        d = dirs.to(self.device, torch.float32).reshape(-1, 3)
        e = torch.full((3,), self.extent, device=self.device)
        t0, t1 = intersect_box(o, d, -e, e)
        t0 = t0.clamp_min(0.0)
        if t_end is not None:
            t1 = torch.minimum(t1, t_end.to(t1).reshape(-1))
        ok = t1 > t0
        if not bool(ok.any()):
            return 0
        o, d, t0, t1 = o[ok], d[ok], t0[ok], t1[ok]
        n = 2 * self.resolution
        s = torch.linspace(0.0, 1.0, n, device=self.device)
        # uniform steps for the cube, geometric ones as well for warped / cascaded grids (far cells are big)
        fr = [s] if self.warp is None and self.cascades == 1 else [s, torch.expm1(s * 6.0) / math.expm1(6.0)]
        t = torch.cat([t0[:, None] + (t1 - t0)[:, None] * f[None, :] for f in fr], 1)
        x = self.to_grid((o[:, None, :] + d[:, None, :] * t[..., None]).reshape(-1, 3))
        x = x[torch.isfinite(x).all(-1) & (x.abs().amax(-1) <= self.cascade_extent(self.cascades - 1))]
        if self._reopen is None:
            self._reopen = torch.zeros_like(self.occupied)
        before = int(self._reopen.sum())
        self._reopen[self._cells(x)] = True
        return int(self._reopen.sum()) - before

    @torch.no_grad()
    def update(self, step: int, density_fn: Callable[[Tensor], Tensor]) -> None:
        """Call every training step; acts every `update_every` steps: evaluate density at jittered cell points
        (all cells during warm-up, else 1/4 uniform + 1/4 occupied), new = max(decay * old, sampled).

        With `spread`, each call evaluates 1/update_every of the cells instead, and the period's last call
        applies the rule: the same work, but no step pays a whole sweep (an interactive viewport waits for at
        most one step, and a warm-up sweep of 64^3 cells takes a quarter second on a 2-core CPU). The first
        update of a fresh grid is whole either way: until it, every cell is occupied and steps cost 3x more."""
        if not self.spread or not self._seeded:
            if step % self.update_every == 0:
                fresh = torch.zeros_like(self.density)
                self._sample(self._update_cells(step), fresh, density_fn)
                self._apply(fresh)
            return
        if self._pending is None:
            self._pending = (self._update_cells(step), torch.zeros_like(self.density), 0)
        cells, fresh, k = self._pending
        u = self.update_every
        self._sample([idx[idx.numel() * k // u: idx.numel() * (k + 1) // u] for idx in cells], fresh, density_fn)
        if k + 1 == u:
            self._pending = None
            self._apply(fresh)
        else:
            self._pending = (cells, fresh, k + 1)

    # --- checkpoints ------------------------------------------------------------------------
    def state_dict(self) -> dict[str, Tensor]:
        """Tensors for a checkpoint (safetensors-compatible)."""
        return {"density": self.density.detach().cpu().clone(),
                "occupied": self.occupied.detach().cpu().clone(),
                "visible": self.visible.detach().cpu().clone(),
                "mean_density": torch.tensor([self.mean_density], dtype=torch.float64)}

    def load_state_dict(self, state: dict[str, Tensor]) -> None:
        """Restore from `state_dict()`; the grid's resolution and cascades must match."""
        for key in ("density", "occupied", "visible"):
            if key == "visible" and key not in state:
                continue  # older checkpoints have none: the visibility this grid has stays
            if key not in state:
                raise UserError(f"occupancy grid state has no '{key}' tensor",
                                hint="the checkpoint is incomplete or of another format; retrain or re-save it")
            if tuple(state[key].shape) != tuple(self.density.shape):
                raise UserError(f"occupancy grid state '{key}' has shape {tuple(state[key].shape)}, but this grid "
                                f"is {tuple(self.density.shape)} (cascades x resolution^3)",
                                hint="create the grid with the checkpoint's resolution and cascades")
        self.density = state["density"].to(self.device, torch.float32).clone()
        self.occupied = state["occupied"].to(self.device).bool().clone()
        seen = state.get("visible")
        self._set_visible(seen.to(self.device).bool().clone() if seen is not None else self.visible)
        md = state.get("mean_density")
        self.mean_density = float(md.reshape(-1)[0]) if md is not None else float(self.density[0].mean())
        self._version += 1
        self._seeded = True


def grid_for_field(field, resolution: int = 128, cascades: int = 1, **kw) -> OccupancyGrid:
    """The occupancy grid that fits a field: over its cube, or over its warped space when it has a warp."""
    warp = getattr(field, "warp", None)
    cfg = getattr(field, "cfg", None)
    bound = float(getattr(cfg, "bound", 1.0))
    extent = field.march()[0] if warp is not None else None
    return OccupancyGrid(resolution=resolution, cascades=cascades, bound=bound, warp=warp, march_extent=extent,
                         **kw)
