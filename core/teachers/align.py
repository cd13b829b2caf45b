"""Robust per-image scale/shift alignment of a relative depth map to sparse metric depth.

Fits target ~= s * pred + t: RANSAC over 2-point samples picks the inlier set (threshold from the
median absolute deviation), then least squares on the inliers, then a few Huber-weighted refits.
"""
from __future__ import annotations

import numpy as np


def fit_scale_shift(pred: np.ndarray, target: np.ndarray, weights: np.ndarray | None = None,
                    iters: int = 200, seed: int = 0, inlier_k: float = 3.0) -> tuple[float, float]:
    """(s, t) minimising a robust |s * pred + t - target| over matching 1-D samples."""
    x = np.asarray(pred, dtype=np.float64).reshape(-1)
    y = np.asarray(target, dtype=np.float64).reshape(-1)
    w = np.ones_like(x) if weights is None else np.asarray(weights, dtype=np.float64).reshape(-1)
    ok = np.isfinite(x) & np.isfinite(y) & (w > 0)
    x, y, w = x[ok], y[ok], w[ok]
    if x.size < 2 or np.ptp(x) <= 0:
        return 1.0, float(np.median(y - x)) if x.size else 0.0
    rng = np.random.default_rng(seed)
    scale_y = 1.4826 * np.median(np.abs(y - np.median(y))) + 1e-12
    best, best_count = None, -1
    for _ in range(iters):
        i, j = rng.choice(x.size, 2, replace=False)
        if x[i] == x[j]:
            continue
        s = (y[i] - y[j]) / (x[i] - x[j])
        t = y[i] - s * x[i]
        r = np.abs(s * x + t - y)
        # a model's own residual spread sets its inlier band; 5% of the target spread caps it
        band = inlier_k * 1.4826 * np.median(r) + 1e-12
        band = min(band, 0.05 * scale_y * inlier_k)
        count = int(np.sum(w[r <= band]))
        if count > best_count:
            best, best_count = (s, t, band), count
    s, t, band = best if best is not None else (1.0, 0.0, scale_y)
    inl = np.abs(s * x + t - y) <= max(band, 1e-12)
    if inl.sum() >= 2:
        s, t = _weighted_lstsq(x[inl], y[inl], w[inl])
    for _ in range(5):  # Huber IRLS on all points: smooth refinement, outliers down-weighted
        r = s * x + t - y
        sigma = 1.4826 * np.median(np.abs(r)) + 1e-12
        hub = np.minimum(1.0, 1.345 * sigma / np.maximum(np.abs(r), 1e-12))
        hub[np.abs(r) > 6.0 * sigma] = 0.0
        if np.count_nonzero(hub) < 2:
            break
        s, t = _weighted_lstsq(x, y, w * hub)
    return float(s), float(t)


def _weighted_lstsq(x: np.ndarray, y: np.ndarray, w: np.ndarray) -> tuple[float, float]:
    sw = np.sqrt(w)
    a = np.stack([x * sw, sw], 1)
    sol, *_ = np.linalg.lstsq(a, y * sw, rcond=None)
    return float(sol[0]), float(sol[1])


def align_inverse_depth(rel_inv: np.ndarray, u: np.ndarray, v: np.ndarray, z: np.ndarray,
                        min_depth: float = 1e-3) -> tuple[np.ndarray, np.ndarray, tuple[float, float]]:
    """Dense z-depth from a relative inverse-depth map (MiDaS-style) and sparse (u, v, z) points.

    Fits 1/z ~= s * rel_inv + t at the points' pixels (paper: the depth prior "aligned" to the scene),
    returns (depth (H, W) float32, valid mask (H, W) bool, (s, t)). Where s * rel + t <= 0 the
    prediction has no valid depth and the mask is False.
    """
    h, w = rel_inv.shape
    ui = np.clip(np.floor(u).astype(int), 0, w - 1)
    vi = np.clip(np.floor(v).astype(int), 0, h - 1)
    keep = z > min_depth
    s, t = fit_scale_shift(rel_inv[vi[keep], ui[keep]], 1.0 / z[keep])
    inv = s * rel_inv.astype(np.float64) + t
    floor = 1.0 / (np.max(z[keep]) * 10.0) if keep.any() else 1e-6
    valid = inv > floor
    depth = np.where(valid, 1.0 / np.maximum(inv, floor), 0.0).astype(np.float32)
    return depth, valid, (s, t)
