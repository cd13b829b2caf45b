"""The one renderer: rays -> {rgb, depth, opacity, feature} for training, viewport, bench and export.

Rays are processed in groups whose candidate samples (after empty-space skipping) fit `opts.chunk`.
With gradients (training) a group uses nerfacc's trick: density of all candidates without grad, keep
samples whose transmittance is above `t_threshold`, re-evaluate those with grad. Without gradients
(viewport, export) rays are marched in rounds over the rays still alive, so samples behind opaque
surfaces are never evaluated.
"""
from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field as dc_field

import torch
from torch import Tensor

from repaint_nerf.core.device import synchronize
from repaint_nerf.core.errors import UserError
from repaint_nerf.core.field.appearance import RayAppearance, with_ray_appearance
from repaint_nerf.core.render import march_native
from repaint_nerf.core.render.composite import (apply_background, composite, distortion, first_surface_samples,
                                                optical_depth, segment_sum, transmittance)
from repaint_nerf.core.render.box import cube
from repaint_nerf.core.render.occupancy import OccupancyGrid, default_step
from repaint_nerf.core.render.raymarch import RayPlan, Samples, cat_samples, expand_segments, next_segments, plan_rays
from repaint_nerf.core.scene.cameras import Cameras

OUTPUTS = ("rgb", "depth", "opacity", "feature", "median_depth", "distortion")
STRATEGIES = ("auto", "filter", "rounds")


@dataclass
class RenderOptions:
    """What to render and under which budgets (see docs/CONTRACTS.md, "Renderer")."""

    outputs: tuple = ("rgb", "depth", "opacity")  # any subset of OUTPUTS
    background: Tensor | None = None  # (3,) or (R,3) composited behind; None = black
    t_threshold: float = 1e-4  # early ray termination: samples behind T < t_threshold are dropped
    max_samples: int = 1024  # steps across the field cube's diagonal; also the per-ray cap
    perturb: bool = False  # jitter each sample inside its step (training)
    chunk: int = 1 << 18  # memory budget: candidate samples alive at once
    step_size: float | None = None  # None: 2*sqrt(3)*bound/max_samples (instant-ngp's rule)
    step_stride: float = 1.0  # the step's multiple: a moving view's preview marches coarser (app.resolution)
    near: float = 0.0  # rays start no earlier than this distance
    strategy: str = "auto"  # auto | filter (2 passes; always with grad) | rounds (1 pass, no grad)
    seg_steps: int = 16  # steps per coarse skipping segment
    seg_window: int = 8  # segments a ray looks ahead per marching round
    profile: bool = False  # per-stage seconds in stats['time'] (synchronises the device)
    # inference only: the most field samples a ray evaluates, whatever the resolution (0 = no cap). A foggy
    # (e.g. untrained) field never reaches t_threshold, so without it every ray marches to the far bound;
    # what a capped ray has not met by then counts as background
    sample_cap: int = 0
    # training only: evaluate every candidate with grad in one pass, without the density-only pass that drops
    # those behind T < t_threshold. For a foggy field that pass keeps them all: it is work that need not be there
    one_pass: bool = False
    # per ray: the training image it comes from (R,) long, for fields with appearance codes (core.field.appearance);
    # None: the mean code
    appearance: Tensor | None = None
    # the feature of the ray's first surface only (core.render.composite, `first_surface`): what a selection reads,
    # so a nearer object that covers the selected one is not blended with it; False: composited along the ray
    feature_first_surface: bool = False
    # training only: called at each marching round's start and before the differentiable pass, where the trainer's
    # interlude (Stage1Trainer.step) renders a view the user asked for mid-step, so it waits for a round, not the
    # forward pass (the fox: 50-63 ms of a tool switch's 100-110)
    pause: Callable[[], None] | None = None


@dataclass
class _Acc:
    """Per-group accumulators and statistics."""

    stats: dict = dc_field(default_factory=lambda: {"rays": 0, "marched": 0, "candidates": 0, "samples": 0,
                                                     "density_samples": 0, "peak_samples": 0})
    time: dict = dc_field(default_factory=lambda: {"sampling": 0.0, "field": 0.0, "compositing": 0.0})


class _Timer:
    def __init__(self, acc: _Acc, key: str, on: bool, device):
        self.acc, self.key, self.on, self.device = acc, key, on, device

    def __enter__(self):
        if self.on:
            synchronize(self.device)
            self.t0 = time.perf_counter()

    def __exit__(self, *exc):
        if self.on:
            synchronize(self.device)
            self.acc.time[self.key] += time.perf_counter() - self.t0


WARPED_CAP_FACTOR = 4  # per-ray step cap of warped fields, in units of max_samples
CONE_KNEE = 1.0  # field units: cone stepping grows steps from here on at the latest
NATIVE_FIRST_ROUND = 4  # occupied samples per ray in the native marcher's first round (doubling after)


def _check(opts: RenderOptions) -> None:
    bad = [o for o in opts.outputs if o not in OUTPUTS]
    if bad:
        raise UserError(f"unknown render output(s) {bad}; choose from {list(OUTPUTS)}")
    if opts.strategy not in STRATEGIES:
        raise UserError(f"unknown render strategy '{opts.strategy}'; choose from {list(STRATEGIES)}")
    if opts.sample_cap < 0:
        raise UserError(f"sample_cap must be >= 0 (0 = no cap), got {opts.sample_cap}")
    if opts.max_samples < 1 or opts.seg_steps < 1 or opts.seg_window < 1 or opts.chunk < opts.seg_steps:
        raise UserError(f"render options need max_samples, seg_steps, seg_window >= 1 and chunk >= seg_steps "
                        f"(got {opts.max_samples}, {opts.seg_steps}, {opts.seg_window}, {opts.chunk})")
    if not 0.0 <= opts.t_threshold < 1.0:
        raise UserError(f"t_threshold must be in [0, 1) (got {opts.t_threshold})")
    if not opts.step_stride >= 1.0:
        raise UserError(f"step_stride must be >= 1 (got {opts.step_stride})")


def _field_bound(field) -> float:
    cfg = getattr(field, "cfg", None)
    return float(getattr(cfg, "bound", getattr(field, "bound", 1.0)))


def _march_params(field, grid: OccupancyGrid | None) -> tuple[float, float, float]:
    """(bound, extent, cone): the cube whose diagonal sets the step, the marching box, the step growth.
    A warped field (core.field.contraction) marches past its unit cube with cone steps."""
    bound = grid.bound if grid is not None else _field_bound(field)
    extent, cone = field.march() if hasattr(field, "march") else (bound, 0.0)
    if grid is not None:
        extent = grid.extent
    return bound, extent, cone


def _needs_grad(field) -> bool:
    return torch.is_grad_enabled() and isinstance(field, torch.nn.Module) and any(
        p.requires_grad for p in field.parameters())


def _device_of(field, grid, origins) -> torch.device:
    if isinstance(field, torch.nn.Module):
        for p in field.parameters():
            return p.device
    return grid.device if grid is not None else origins.device


def _evaluate(field, s: Samples, dirs: Tensor, heads: tuple, feature_rows=None) -> tuple[Tensor, dict]:
    """Field at the samples: sigma (N,) and the asked heads; density only when no head is asked. `feature_rows`
    (`_front_rows`) limits the feature head to the rows it picks."""
    if not heads:
        return field.density(s.x).reshape(-1), {}
    kw = {} if feature_rows is None else {"feature_rows": feature_rows}
    if getattr(field, "view_per_ray", False):  # the view-dependent part once per ray with samples here
        rays, local = torch.unique_consecutive(s.ray, return_inverse=True)  # packed: sorted by ray
        fld = field.rows(rays) if isinstance(field, RayAppearance) else field
        out = fld(s.x, dirs[rays], outputs=heads, ray=local, **kw)
    else:
        out = field(s.x, dirs[s.ray], outputs=heads, **kw,
                    **({"ray": s.ray} if getattr(field, "per_ray", False) else {}))
    return out["sigma"].reshape(-1), {h: out[h] for h in heads}


def _first_surface(opts: RenderOptions) -> tuple[str, ...]:
    """The heads composited at the first surface only (RenderOptions.feature_first_surface)."""
    return ("feature",) if opts.feature_first_surface else ()


def _front_rows(field, s: Samples, heads: tuple, opts: RenderOptions, carry: Tensor):
    """For a field that evaluates its feature head on chosen rows only (`sparse_features`), when features are
    composited at the first surface: the rows `composite` reads them on (`first_surface_samples`), as a function of
    the round's sigma; None otherwise. Samples behind the first surface or of no weight then cost no feature head
    (a fox feature frame: the head on about a third of its samples)."""
    if "feature" not in heads or "feature" not in _first_surface(opts) or not getattr(field, "sparse_features", False):
        return None
    return lambda sigma: first_surface_samples(sigma, s.t_start, s.t_end, s.ray, carry).nonzero(as_tuple=True)[0]


def _march(field, grid: OccupancyGrid | None, o: Tensor, d: Tensor, plan: RayPlan, heads: tuple,
           opts: RenderOptions, collect: bool, acc: _Acc, dev, cancel) -> tuple[dict, list[Samples]] | None:
    """March rays in rounds over those still alive. collect=False: evaluate the heads and composite each round
    (inference). collect=True: evaluate density only (no grad) and return the samples in front of
    T < t_threshold for a differentiable second pass (training). None when cancelled."""
    prof, k = opts.profile, opts.seg_steps
    n = o.shape[0]
    native = march_native.usable(o, plan, grid)
    # per ray: the next step to march (native) or the next coarse segment to test, and where the ray ends
    cursor = torch.zeros(n, dtype=torch.long, device=dev)
    end = plan.n_steps if native else (plan.n_steps + k - 1) // k
    carry = torch.zeros(n, dtype=torch.float64, device=dev)
    tau_stop = -math.log(opts.t_threshold) if opts.t_threshold > 0 else math.inf
    alive = end > 0
    totals: dict[str, Tensor] = {}
    kept: list[Samples] = []
    rounds = 0
    cap = opts.sample_cap if opts.sample_cap > 0 and not collect else math.inf
    taken = 0  # samples (native) or steps (segments) every live ray has had at most so far
    while True:
        if cancel is not None and cancel():
            return None
        if opts.pause is not None:
            opts.pause()
        with _Timer(acc, "sampling", prof, dev):
            ids = alive.nonzero(as_tuple=True)[0]
            if ids.numel() == 0:
                break
            # work per ray grows each round (rays still alive late are mostly transparent), capped by the
            # look-ahead window and the memory budget
            if native:  # occupied samples per ray: 4, 8, 16, ...
                left = cap - taken if cap < math.inf else k * opts.seg_window
                take = max(1, min(k * opts.seg_window, NATIVE_FIRST_ROUND << rounds, opts.chunk // ids.numel(), left))
                s = march_native.march(o, d, plan, grid, ids, cursor, take, opts.perturb)
                taken += take
            else:  # coarse segments per ray: 1, 2, 4, ...
                left = (cap - taken + k - 1) // k if cap < math.inf else opts.seg_window
                take = max(1, min(opts.seg_window, 1 << rounds, opts.chunk // (ids.numel() * k), left))
                segs = next_segments(o, d, plan, grid, ids, cursor, k, opts.seg_window, take)
                taken += take * k
                s = expand_segments(o, d, plan, grid, *segs, opts.perturb)
            rounds += 1
        acc.stats["candidates"] += len(s)
        acc.stats["peak_samples"] = max(acc.stats["peak_samples"], len(s))
        if collect and opts.one_pass:
            kept.append(s)  # rays march to their end: nothing is known to stop them
        elif collect:
            with _Timer(acc, "field", prof, dev), torch.no_grad():
                sigma = field.density(s.x).reshape(-1) if len(s) else torch.zeros(0, device=dev)
            acc.stats["density_samples"] += len(s)
            with _Timer(acc, "compositing", prof, dev), torch.no_grad():
                tau = optical_depth(sigma, s.t_start, s.t_end)
                visible = transmittance(tau, s.ray, carry) >= opts.t_threshold
                kept.append(s.select(visible))
                carry = carry + segment_sum(tau.double(), s.ray, n)
        else:
            with _Timer(acc, "field", prof, dev):
                sigma, vals = _evaluate(field, s, d, heads, _front_rows(field, s, heads, opts, carry))
            acc.stats["samples"] += len(s)
            with _Timer(acc, "compositing", prof, dev):
                out = composite(sigma, s.t_start, s.t_end, s.t, s.ray, n, vals, tau_before=carry,
                                median="median_depth" in opts.outputs, first_surface=_first_surface(opts))
                for name, v in out.items():
                    if name not in ("weights", "tau"):
                        totals[name] = totals[name] + v if name in totals else v
                carry = carry + out["tau"]
        alive = (cursor < end) & (carry < tau_stop)
        if taken >= cap:
            break
    return totals, kept


def _render_block(field, grid, o, d, plan, heads, opts, strategy, acc, dev, cancel) -> dict | None:
    """Outputs of one block of rays: per-ray sums 'opacity', 'depth_sum' and the heads."""
    prof = opts.profile
    marched = _march(field, grid, o, d, plan, heads, opts, strategy == "filter", acc, dev, cancel)
    if marched is None:
        return None
    totals, kept = marched
    if strategy == "filter" or not totals:
        if opts.pause is not None:
            opts.pause()
        with _Timer(acc, "sampling", prof, dev):
            s = cat_samples(kept, dev)
        with _Timer(acc, "field", prof, dev):
            sigma, vals = _evaluate(field, s, d, heads)  # with grad; also run on no samples to keep the graph
        acc.stats["samples"] += len(s)
        acc.stats["peak_samples"] = max(acc.stats["peak_samples"], len(s))
        with _Timer(acc, "compositing", prof, dev):
            totals = composite(sigma, s.t_start, s.t_end, s.t, s.ray, o.shape[0], vals,
                               median="median_depth" in opts.outputs, first_surface=_first_surface(opts))
            if "distortion" in opts.outputs:  # in steps over the diagonal's budget: 1 across the field cube
                lo, hi = (plan.steps_to(s.ray, t) / opts.max_samples for t in (s.t_start, s.t_end))
                totals["distortion"] = distortion(totals["weights"], lo, hi, s.ray, o.shape[0])
    return totals


def _render(field, grid: OccupancyGrid | None, origins: Tensor, dirs: Tensor, opts: RenderOptions,
            cancel: Callable[[], bool] | None) -> dict | None:
    _check(opts)
    dev = _device_of(field, grid, origins)
    origins = origins.to(dev, torch.float32).reshape(-1, 3)
    dirs = dirs.to(dev, torch.float32).reshape(-1, 3)
    n_rays = origins.shape[0]
    heads = tuple(h for h in ("rgb", "feature") if h in opts.outputs)
    need = set(opts.outputs) | ({"opacity"} if {"rgb", "depth"} & set(opts.outputs) else set())
    # the distortion needs every sample of a ray at once: only the filter strategy composites them together
    strategy = "filter" if opts.strategy == "filter" or _needs_grad(field) or "distortion" in opts.outputs \
        else "rounds"
    bound, extent, cone = _march_params(field, grid)
    step = (opts.step_size or default_step(bound, opts.max_samples)) * opts.step_stride
    if cone > 0.0:  # steps start growing no farther than one field unit out (coarse steps: sooner)
        cone = max(cone, step / CONE_KNEE)
    # warped fields reach far content with growing steps; the cap leaves room for them past the unit cube
    cap = opts.max_samples if cone <= 0.0 else WARPED_CAP_FACTOR * opts.max_samples
    acc = _Acc()
    acc.stats["rays"] = n_rays

    if grid is not None:
        lo, hi = grid.occupied_bbox()
    else:
        lo, hi = cube(extent, dev)
    pieces: list[dict] = []
    block = max(1, opts.chunk // opts.seg_steps)
    for b0 in range(0, n_rays, block):
        o, d = origins[b0:b0 + block], dirs[b0:b0 + block]
        with _Timer(acc, "sampling", opts.profile, dev):
            plan = plan_rays(o, d, lo, hi, step, cap, opts.near, cone)
        acc.stats["marched"] += int(plan_rays(o, d, *cube(extent, dev), step, cap, opts.near,
                                              cone).n_steps.sum())
        fld = with_ray_appearance(field, opts.appearance, b0, block)
        out = _render_block(fld, grid, o, d, plan, heads, opts, strategy, acc, dev, cancel)
        if out is None:
            return None
        pieces.append(out)

    result: dict = {}
    sums = ("opacity", "depth_sum", *heads) + (("median_sum",) if "median_depth" in opts.outputs else ()) \
        + (("distortion",) if "distortion" in opts.outputs else ())
    cat = {k: torch.cat([p[k] for p in pieces]) if pieces else None for k in sums}
    opacity = cat["opacity"] if pieces else torch.zeros(0, device=dev)
    if "opacity" in need:
        result["opacity"] = opacity
    if "rgb" in opts.outputs:
        bg = opts.background
        if bg is not None and bg.dim() == 2 and bg.shape[0] != n_rays:
            raise UserError(f"per-ray background has {bg.shape[0]} rows for {n_rays} rays")
        result["rgb"] = apply_background(cat["rgb"] if pieces else torch.zeros(0, 3, device=dev), opacity, bg)
    if "depth" in opts.outputs or "median_depth" in opts.outputs:
        # expected distance of termination: sum(w t) / sum(w), bounded by the ray's last sample
        expected = (cat["depth_sum"] / opacity.clamp_min(1e-6)) if pieces else torch.zeros(0, device=dev)
        if "depth" in opts.outputs:
            result["depth"] = expected
        if "median_depth" in opts.outputs:
            # where the transmittance falls through 0.5 (nerfstudio's median depth): one surface's distance where
            # a noisy or half-transparent one lies in front of it, which the expected depth blends; expected where
            # the ray never gets that opaque
            result["median_depth"] = torch.where(cat["median_sum"] > 0, cat["median_sum"], expected) if pieces \
                else expected
    if "feature" in opts.outputs:
        result["feature"] = cat["feature"]
    if "distortion" in opts.outputs:
        result["distortion"] = cat["distortion"]
    if "opacity" not in opts.outputs:
        result.pop("opacity", None)
    stats = dict(acc.stats)
    stats["samples_per_ray"] = stats["samples"] / max(1, n_rays)
    stats["candidates_per_ray"] = stats["candidates"] / max(1, n_rays)
    stats["marched_per_ray"] = stats["marched"] / max(1, n_rays)
    stats["strategy"] = strategy
    if opts.profile:
        stats["time"] = dict(acc.time)
    result["stats"] = stats
    return result


def render_rays(field, grid: OccupancyGrid | None, origins: Tensor, dirs: Tensor,
                opts: RenderOptions | None = None) -> dict:
    """Render unit-direction rays (R,3) in field space: the asked outputs ('rgb' (R,3), 'depth' (R,) along
    the ray, 'median_depth' (R,) where T falls through 0.5, 'opacity' (R,), 'feature' (R,F), 'distortion' (R,):
    core.render.composite.distortion in steps over max_samples) plus 'stats'.
    Differentiable; grid=None disables skipping."""
    return _render(field, grid, origins, dirs, opts or RenderOptions(), None)


@torch.no_grad()
def render_camera(field, grid: OccupancyGrid | None, cameras: Cameras, i: int, opts: RenderOptions | None = None,
                  scale: float = 1.0, cancel: Callable[[], bool] | None = None) -> dict | None:
    """Render camera i (field space) at `scale` times its resolution: 'rgb' (H,W,3), 'depth' and 'median_depth'
    (H,W) z-depth, 'opacity' (H,W), 'feature' (H,W,F) as asked, plus 'stats'; None when `cancel()` turns true."""
    cam = cameras[int(i)]
    if scale != 1.0:
        cam = cam.scaled(scale)
    h, w = int(cam.height[0]), int(cam.width[0])
    if h < 1 or w < 1:
        raise UserError(f"render size {w}x{h} is empty (scale {scale}); use a larger scale")
    origins, dirs, dz = cam.image_rays(0)
    out = _render(field, grid, origins, dirs, opts or RenderOptions(), cancel)
    if out is None:
        return None
    img: dict = {"stats": out["stats"]}
    for k, v in out.items():
        if k == "stats":
            continue
        if k in ("depth", "median_depth"):
            v = v * dz.to(v.device)
        img[k] = v.reshape(h, w, *v.shape[1:])
    return img
