"""Pose accuracy of structure-from-motion against known poses, after a similarity alignment.

SfM recovers poses up to scale, rotation and translation; `align_similarity` (Umeyama's closed form)
maps the recovered camera centres onto the true ones, then rotation and position errors are measured.
"""
from __future__ import annotations

import numpy as np


def align_similarity(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """(s, R, t) minimising sum |s R src_i + t - dst_i|^2 over points (N,3), N >= 3 (Umeyama 1991)."""
    src, dst = np.asarray(src, dtype=np.float64), np.asarray(dst, dtype=np.float64)
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    cov = b.T @ a / len(src)
    u, sig, vt = np.linalg.svd(cov)
    fix = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        fix[2, 2] = -1.0
    rot = u @ fix @ vt
    var = (a ** 2).sum() / len(src)
    s = float(np.trace(np.diag(sig) @ fix) / max(var, 1e-300))
    return s, rot, mu_d - s * rot @ mu_s


def pose_errors(est_c2w: np.ndarray, gt_c2w: np.ndarray, scene_radius: float | None = None) -> dict:
    """Rotation (degrees) and position errors of estimated poses (N,4,4) against the truth (same order).

    Positions are compared after aligning the estimated centres to the true ones; the relative error
    divides by `scene_radius` (default: the largest distance of a true centre from their mean).
    """
    est, gt = np.asarray(est_c2w, dtype=np.float64), np.asarray(gt_c2w, dtype=np.float64)
    s, rot, t = align_similarity(est[:, :3, 3], gt[:, :3, 3])
    centres = s * est[:, :3, 3] @ rot.T + t
    pos_err = np.linalg.norm(centres - gt[:, :3, 3], axis=1)
    r_est = np.einsum("ij,njk->nik", rot, est[:, :3, :3])
    cos = (np.einsum("nij,nij->n", r_est, gt[:, :3, :3]) - 1.0) / 2.0
    rot_err = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    radius = scene_radius or float(np.linalg.norm(gt[:, :3, 3] - gt[:, :3, 3].mean(0), axis=1).max())
    return {"rotation_deg_max": float(rot_err.max()), "rotation_deg_mean": float(rot_err.mean()),
            "position_max": float(pos_err.max()), "position_mean": float(pos_err.mean()),
            "position_rel_max": float(pos_err.max() / radius), "scene_radius": radius, "scale": s}
