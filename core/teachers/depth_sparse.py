"""Sparse depth priors: structure-from-motion points projected into each training camera, or, for
scenes with known poses and no points, points triangulated from SIFT matches across nearby views.

All depths are z-depth in world units; (u, v) are continuous pixel coordinates with pixel centres
at +0.5 (core.scene.cameras convention).
"""
from __future__ import annotations

import cv2
import numpy as np

from repaint_nerf.core.scene.cameras import Cameras, opencv_to_opengl
from repaint_nerf.core.teachers.depth import DepthPriors, SparseDepth


def project_points(points: np.ndarray, cameras: Cameras, i: int, visible: np.ndarray | None = None,
                   cell: int = 4, tolerance: float = 0.03) -> SparseDepth:
    """Sparse z-depth of world points (M, 3) seen by camera i.

    Keeps points in front of the camera and inside the image. `visible` (indices into `points`, e.g. an
    SfM track) decides visibility when given; otherwise a z-buffer on a grid of `cell`-pixel cells
    drops points more than `tolerance` (relative) behind the nearest point of their 3x3 cells.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if visible is not None:
        pts = pts[np.asarray(visible, dtype=np.int64)]
    c2w = cameras.c2w[i].double().numpy()
    w2c = np.linalg.inv(c2w)
    pc = pts @ w2c[:3, :3].T + w2c[:3, 3]
    z = -pc[:, 2]
    h, w = int(cameras.height[i]), int(cameras.width[i])
    fx, fy, cx, cy = (float(t[i]) for t in (cameras.fx, cameras.fy, cameras.cx, cameras.cy))
    front = z > 1e-6
    zs = np.where(front, z, 1.0)
    u = fx * pc[:, 0] / zs + cx
    v = -fy * pc[:, 1] / zs + cy
    keep = front & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    u, v, z = u[keep], v[keep], z[keep]
    if visible is None and z.size:
        gw, gh = (w + cell - 1) // cell, (h + cell - 1) // cell
        gx = np.clip((u // cell).astype(np.int64), 0, gw - 1)
        gy = np.clip((v // cell).astype(np.int64), 0, gh - 1)
        zmin = np.full((gh, gw), np.inf, np.float32)
        np.minimum.at(zmin, (gy, gx), z.astype(np.float32))
        # nearest depth over the 3x3 cells around: an occluder just across a cell border still counts
        zmin = cv2.erode(np.where(np.isfinite(zmin), zmin, 3e38).astype(np.float32), np.ones((3, 3), np.uint8))
        ok = z <= zmin[gy, gx] * (1.0 + tolerance)
        u, v, z = u[ok], v[ok], z[ok]
    return SparseDepth(u.astype(np.float32), v.astype(np.float32), z.astype(np.float32))


def depth_from_points(points: np.ndarray, cameras: Cameras, visibility: list | None = None,
                      **kwargs) -> DepthPriors:
    """DepthPriors for every camera from SfM points (optionally with per-image visible point indices)."""
    priors = [project_points(points, cameras, i, None if visibility is None else visibility[i], **kwargs)
              for i in range(len(cameras))]
    return DepthPriors(priors, cameras.sizes(), source="sfm-points")


def triangulate_known_poses(images: list[np.ndarray], cameras: Cameras, neighbours: int = 6,
                            max_reproj: float = 1.0, min_angle_deg: float = 2.0, max_view_angle_deg: float = 60.0,
                            ratio: float = 0.9, epipolar_px: float = 1.5, n_features: int = 2000,
                            background: tuple[float, float, float] | None = (1.0, 1.0, 1.0),
                            min_support: int = 2, agree: float = 0.02) -> DepthPriors:
    """Sparse depth for posed images without points: SIFT matches between each view and its nearest
    views, filtered by the ratio test and the epipolar constraint of the known poses, triangulated
    (DLT), kept when in front of both cameras, reprojecting within `max_reproj` px and seen under a
    triangulation angle of at least `min_angle_deg`. A keypoint is kept when at least `min_support`
    pairs agree on its depth within `agree` (relative): repeated textures (checker floors) give
    epipolar-consistent false matches, and those rarely agree across pairs. Its depth is their median.
    """
    n = len(images)
    sift = cv2.SIFT_create(nfeatures=n_features)
    kps, descs = [], []
    for im in images:
        gray = cv2.cvtColor(_composite(im, background), cv2.COLOR_RGB2GRAY)
        k, d = sift.detectAndCompute(gray, None)
        # OpenCV puts pixel centres at integers; ours are at +0.5
        kps.append(np.array([p.pt for p in k], np.float64).reshape(-1, 2) + 0.5)
        descs.append(d if d is not None else np.zeros((0, 128), np.float32))
    kmat = [_intrinsics(cameras, i) for i in range(n)]
    w2c_cv = [np.linalg.inv(opencv_to_opengl(cameras.c2w[i].double().numpy())) for i in range(n)]
    proj = [kmat[i] @ w2c_cv[i][:3] for i in range(n)]
    centres = cameras.c2w[:, :3, 3].double().numpy()
    axes = -cameras.c2w[:, :3, 2].double().numpy()  # viewing direction (OpenGL looks down -z)
    obs: list[dict[int, list[float]]] = [dict() for _ in range(n)]
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    done = set()
    for i in range(n):
        for j in _nearest_views(i, centres, axes, neighbours, max_view_angle_deg):
            if (min(i, j), max(i, j)) in done or len(descs[i]) < 2 or len(descs[j]) < 2:
                continue
            done.add((min(i, j), max(i, j)))
            pairs = matcher.knnMatch(descs[i], descs[j], k=2)
            good = [m[0] for m in pairs if len(m) == 2 and m[0].distance < ratio * m[1].distance]
            if not good:
                continue
            qi = np.array([m.queryIdx for m in good])
            qj = np.array([m.trainIdx for m in good])
            xi, xj = kps[i][qi], kps[j][qj]
            fmat = _fundamental(kmat[i], w2c_cv[i], kmat[j], w2c_cv[j])
            ok = _sampson(fmat, xi, xj) < epipolar_px ** 2
            if not ok.any():
                continue
            qi, qj, xi, xj = qi[ok], qj[ok], xi[ok], xj[ok]
            xh = cv2.triangulatePoints(proj[i], proj[j], xi.T.copy(), xj.T.copy())
            x3 = (xh[:3] / xh[3:]).T
            zi, ei = _depth_and_error(x3, proj[i], w2c_cv[i], xi)
            zj, ej = _depth_and_error(x3, proj[j], w2c_cv[j], xj)
            ri, rj = x3 - centres[i], x3 - centres[j]
            cosang = np.sum(ri * rj, 1) / (np.linalg.norm(ri, axis=1) * np.linalg.norm(rj, axis=1) + 1e-12)
            good3 = (zi > 0) & (zj > 0) & (ei < max_reproj) & (ej < max_reproj) & \
                    (cosang < np.cos(np.deg2rad(min_angle_deg)))
            for a, b, za, zb in zip(qi[good3], qj[good3], zi[good3], zj[good3]):
                obs[i].setdefault(int(a), []).append(float(za))
                obs[j].setdefault(int(b), []).append(float(zb))
    priors = []
    for i in range(n):
        idx, z = [], []
        for k, zs in sorted(obs[i].items()):
            zs = np.asarray(zs)
            m = np.median(zs)
            close = zs[np.abs(zs - m) <= agree * m]
            if close.size >= min_support:
                idx.append(k)
                z.append(np.median(close))
        idx, z = np.array(idx, dtype=np.int64), np.array(z, np.float32)
        uv = kps[i][idx] if idx.size else np.zeros((0, 2))
        priors.append(SparseDepth(uv[:, 0].astype(np.float32), uv[:, 1].astype(np.float32), z))
    return DepthPriors(priors, cameras.sizes(), source="triangulated")


def _composite(im: np.ndarray, background) -> np.ndarray:
    im = np.asarray(im)
    if im.ndim == 3 and im.shape[2] == 4:
        a = im[..., 3:4].astype(np.float32) / 255.0
        bg = np.asarray(background if background is not None else (0.0, 0.0, 0.0), np.float32) * 255.0
        return (im[..., :3].astype(np.float32) * a + bg * (1 - a) + 0.5).clip(0, 255).astype(np.uint8)
    return np.ascontiguousarray(im[..., :3])


def _intrinsics(cameras: Cameras, i: int) -> np.ndarray:
    # OpenCV image axes (y down) with our +0.5 pixel-centre coordinates: v = fy * y / z + cy
    return np.array([[float(cameras.fx[i]), 0.0, float(cameras.cx[i])],
                     [0.0, float(cameras.fy[i]), float(cameras.cy[i])],
                     [0.0, 0.0, 1.0]])


def _nearest_views(i: int, centres: np.ndarray, axes: np.ndarray, k: int, max_angle: float) -> list[int]:
    cos = axes @ axes[i]
    dist = np.linalg.norm(centres - centres[i], axis=1)
    cand = [j for j in np.argsort(dist) if j != i and cos[j] > np.cos(np.deg2rad(max_angle)) and dist[j] > 0]
    return [int(j) for j in cand[:k]]


def _fundamental(ki, w2ci, kj, w2cj) -> np.ndarray:
    rel = w2cj @ np.linalg.inv(w2ci)  # camera i -> camera j
    r, t = rel[:3, :3], rel[:3, 3]
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    return np.linalg.inv(kj).T @ tx @ r @ np.linalg.inv(ki)


def _sampson(f: np.ndarray, xi: np.ndarray, xj: np.ndarray) -> np.ndarray:
    hi = np.concatenate([xi, np.ones((len(xi), 1))], 1)
    hj = np.concatenate([xj, np.ones((len(xj), 1))], 1)
    fx, ftx = hi @ f.T, hj @ f
    num = np.sum(hj * fx, 1) ** 2
    return num / (fx[:, 0] ** 2 + fx[:, 1] ** 2 + ftx[:, 0] ** 2 + ftx[:, 1] ** 2 + 1e-12)


def _depth_and_error(x3: np.ndarray, proj: np.ndarray, w2c: np.ndarray, uv: np.ndarray):
    pc = x3 @ w2c[:3, :3].T + w2c[:3, 3]
    xh = np.concatenate([x3, np.ones((len(x3), 1))], 1) @ proj.T
    err = np.linalg.norm(xh[:, :2] / xh[:, 2:3] - uv, axis=1)
    return pc[:, 2], err


def depth_for_scene(scene, split: str = "train") -> DepthPriors:
    """Default sparse prior of a scene: its SfM points when it has them, else triangulation."""
    sp = scene.split(split)
    if scene.points is not None and len(scene.points):
        vis = scene.extra.get("visibility") if isinstance(scene.extra, dict) else None
        return depth_from_points(scene.points, sp.cameras, vis)
    return triangulate_known_poses(sp.images, sp.cameras, background=scene.background or (1.0, 1.0, 1.0))


__all__ = ["project_points", "depth_from_points", "triangulate_known_poses", "depth_for_scene"]
