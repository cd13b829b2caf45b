"""Numerically stable volume-rendering compositing on packed samples (paper Eq. for C(r) and T(t)).

alpha = -expm1(-sigma*delta); T from an exclusive per-ray cumulative sum of sigma*delta, T = exp(-sum),
never a cumprod of (1 - alpha); weights = T * alpha; per-ray sums by index_add (differentiable).
"""
from __future__ import annotations

import torch
from torch import Tensor

# Optical thickness per sample is capped here: exp(-80) ~ 2e-35 is already zero for every output, and the
# cap keeps the per-chunk cumulative sum small enough for float64 to subtract segment starts exactly.
TAU_MAX = 80.0


def exclusive_segment_cumsum(x: Tensor, ray: Tensor) -> Tensor:
    """Sum of x over the earlier samples of the same ray (x packed, sorted by ray), in float64."""
    if x.numel() == 0:
        return x.double()
    x64 = x.double()
    excl = torch.cumsum(x64, 0) - x64
    idx = torch.arange(ray.numel(), device=ray.device)
    is_start = torch.ones_like(ray, dtype=torch.bool)
    is_start[1:] = ray[1:] != ray[:-1]
    start = torch.cummax(torch.where(is_start, idx, torch.zeros_like(idx)), 0).values
    return excl - excl[start]


def optical_depth(sigma: Tensor, t_start: Tensor, t_end: Tensor) -> Tensor:
    """sigma * delta per sample, capped at TAU_MAX (finite even for infinite density)."""
    tau = sigma * (t_end - t_start)
    return torch.nan_to_num(tau, nan=0.0, posinf=TAU_MAX).clamp(0.0, TAU_MAX)


def transmittance(tau: Tensor, ray: Tensor, tau_before: Tensor | None = None) -> Tensor:
    """Transmittance in front of each sample, T = exp(-(carried + exclusive sum of tau)), float32."""
    acc = exclusive_segment_cumsum(tau, ray)
    if tau_before is not None:
        acc = acc + tau_before[ray]
    return torch.exp(-acc).to(tau.dtype)


def segment_sum(values: Tensor, ray: Tensor, n_rays: int) -> Tensor:
    """Per-ray sums of packed values (N,) or (N,C) -> (n_rays,) or (n_rays,C)."""
    out = torch.zeros((n_rays,) + tuple(values.shape[1:]), dtype=values.dtype, device=values.device)
    return out.index_add(0, ray, values)


def median_crossing(tau: Tensor, trans: Tensor, t_start: Tensor, t_end: Tensor) -> Tensor:
    """Per sample: the distance inside it where the ray's transmittance falls through 0.5 (T = trans at its
    start, exp(-tau) across it, exponential in between), or 0 where it does not fall through 0.5 there. Summed
    per ray this is the median termination distance (at most one sample of a ray crosses)."""
    after = trans * torch.exp(-tau)
    cross = (trans >= 0.5) & (after < 0.5)
    frac = torch.log(trans.clamp_min(0.5) / 0.5) / tau.clamp_min(1e-12)
    return torch.where(cross, t_start + (t_end - t_start) * frac.clamp(0.0, 1.0), torch.zeros_like(t_start))


def distortion(w: Tensor, s_start: Tensor, s_end: Tensor, ray: Tensor, n_rays: int) -> Tensor:
    """Per-ray distortion loss of mip-NeRF 360 (its Eq. 15) on packed samples sorted by distance, with intervals
    [s_start, s_end] in a normalised distance s: sum_ij w_i w_j |m_i - m_j| + 1/3 sum_i w_i^2 (s_end - s_start),
    m the midpoints. The double sum is 2 sum_i w_i (m_i W_i - M_i) with W_i, M_i the per-ray sums of w and w m over
    the earlier samples (midpoints are sorted along a ray), so it costs O(N)."""
    mid = 0.5 * (s_start + s_end)
    before_w = exclusive_segment_cumsum(w, ray)
    before_wm = exclusive_segment_cumsum(w * mid, ray)
    across = (2.0 * w.double() * (mid.double() * before_w - before_wm)).to(w.dtype)
    within = w * w * (s_end - s_start) / 3.0
    return segment_sum(across + within, ray, n_rays)


FIRST_SURFACE_T = 0.5  # a sample belongs to the ray's first surface while the transmittance in front of it is
# at least this (the median depth's crossing, `median_crossing`, is the last such sample)


def _weights(sigma: Tensor, t_start: Tensor, t_end: Tensor, ray: Tensor,
             tau_before: Tensor | None) -> tuple[Tensor, Tensor, Tensor]:
    """(tau, transmittance in front, weight) per sample."""
    tau = optical_depth(sigma, t_start, t_end)
    trans = transmittance(tau, ray, tau_before)
    return tau, trans, trans * -torch.expm1(-tau)


def first_surface_samples(sigma: Tensor, t_start: Tensor, t_end: Tensor, ray: Tensor,
                          tau_before: Tensor | None = None) -> Tensor:
    """(N,) bool: the samples whose values `composite` sums for its `first_surface` entries (a weight that is not
    0, in front of the transmittance's fall through FIRST_SURFACE_T); the others may hold any finite value."""
    _, trans, w = _weights(sigma, t_start, t_end, ray, tau_before)
    return (w != 0) & (trans >= FIRST_SURFACE_T)


def composite(sigma: Tensor, t_start: Tensor, t_end: Tensor, t: Tensor, ray: Tensor, n_rays: int,
              values: dict[str, Tensor] | None = None, tau_before: Tensor | None = None,
              median: bool = False, first_surface: tuple[str, ...] = ()) -> dict[str, Tensor]:
    """Weights and per-ray sums: 'opacity' (sum w), 'depth_sum' (sum w t), one sum w*v per entry of
    `values` (e.g. 'rgb', 'feature'), 'tau' (per-ray sum of optical thickness, float64, detached),
    'weights' (packed); with `median`, 'median_sum' (`median_crossing`: the median distance, 0 where T stays
    above 0.5). `tau_before` (n_rays,) continues rays composited in earlier rounds. The entries named in
    `first_surface` sum only the samples up to the one where T falls through `FIRST_SURFACE_T` (the first
    surface, at the median depth): what lies behind a nearer object that is only partly opaque on the ray (its
    silhouette, a thin or soft surface) is not mixed into it."""
    tau, trans, w = _weights(sigma, t_start, t_end, ray, tau_before)
    out = {"weights": w, "opacity": segment_sum(w, ray, n_rays), "depth_sum": segment_sum(w * t, ray, n_rays)}
    if median:
        out["median_sum"] = segment_sum(median_crossing(tau, trans, t_start, t_end), ray, n_rays)
    w_front = w * (trans >= FIRST_SURFACE_T) if first_surface else w
    for name, v in (values or {}).items():
        out[name] = segment_sum((w_front if name in first_surface else w)[:, None] * v, ray, n_rays)
    out["tau"] = segment_sum(tau.detach().double(), ray, n_rays)
    return out


def apply_background(rgb: Tensor, opacity: Tensor, background: Tensor | None) -> Tensor:
    """rgb + (1 - opacity) * background, for a (3,) or per-ray (R,3) background; None keeps black."""
    if background is None:
        return rgb
    bg = background.to(rgb.device, rgb.dtype)
    return rgb + (1.0 - opacity)[:, None] * bg
