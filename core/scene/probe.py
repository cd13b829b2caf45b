"""A quick look at where a capture's surfaces are, from its posed images alone (no sparse points needed).

SIFT features of a few neighbouring image pairs are matched (ratio test), kept only where the known poses agree
(epipolar distance), and triangulated with those poses. One point per image cell (the median depth of those
triangulated there) is kept, so the points sample what the views show by area. A few hundred are enough to tell
whether much of what the cameras see lies beyond them (a room, an outdoor background: core.scene.kinds). Cost: about a second for
a dozen 512-px pairs on one core; nothing is fitted or refined.
"""
from __future__ import annotations

import cv2
import numpy as np

from repaint_nerf.core.scene.cameras import opencv_to_opengl

PROBE_PAIRS = 12  # image pairs matched
PROBE_MAX_SIDE = 512  # images are matched at most this large
RATIO = 0.8  # Lowe's ratio test
EPIPOLAR_PX = 2.0  # largest distance (pixels) of a match from its epipolar line
MIN_POINTS = 24  # fewer probe points than this decide nothing
CELLS = 8  # each view of a pair is split into CELLS x CELLS cells, one point per cell: points sample the image
# area evenly, not the texture (features crowd on textured objects; a plain far wall gives few)


def _gray(img: np.ndarray) -> tuple[np.ndarray, float]:
    """A uint8 grey image at most PROBE_MAX_SIDE wide or high, and the factor it was resized by."""
    g = cv2.cvtColor(np.ascontiguousarray(img[..., :3]), cv2.COLOR_RGB2GRAY) if img.ndim == 3 else img
    f = min(1.0, PROBE_MAX_SIDE / max(g.shape[:2]))
    if f < 1.0:
        g = cv2.resize(g, (round(g.shape[1] * f), round(g.shape[0] * f)), interpolation=cv2.INTER_AREA)
    return g, f


def _projection(cams, i: int, f: float) -> np.ndarray:
    """The 3x4 OpenCV projection matrix of camera i (OpenGL camera-to-world) at image scale f."""
    k = np.array([[float(cams.fx[i]) * f, 0.0, float(cams.cx[i]) * f],
                  [0.0, float(cams.fy[i]) * f, float(cams.cy[i]) * f], [0.0, 0.0, 1.0]])
    w2c = np.linalg.inv(opencv_to_opengl(cams.c2w[i].double().numpy()))
    return k @ w2c[:3, :4]


def neighbour_pairs(centres: np.ndarray, dirs: np.ndarray, n: int) -> list[tuple[int, int]]:
    """Up to n pairs (i, j): cameras spread over the capture, each with its nearest camera looking the same way."""
    m = len(centres)
    firsts = np.unique(np.linspace(0, m - 1, min(n, m)).round().astype(int)) if m > 1 else []
    pairs = []
    for i in firsts:
        d = np.linalg.norm(centres - centres[i], axis=1)
        d[(dirs @ dirs[i]) < 0.5] = np.inf  # views more than 60 degrees apart share little
        d[i] = np.inf
        j = int(np.argmin(d))
        if np.isfinite(d[j]) and d[j] > 0:
            pairs.append((int(i), j))
    return pairs


def fundamental(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The fundamental matrix of projections a, b: x_b^T F x_a = 0 (F = [e_b]_x P_b P_a^+)."""
    c1 = np.linalg.svd(a)[2][-1]  # camera centre of a (its null vector)
    return np.cross(np.eye(3), b @ c1) @ b @ np.linalg.pinv(a)


def guided_matches(k1: np.ndarray, d1: np.ndarray, k2: np.ndarray, d2: np.ndarray, f: np.ndarray) -> tuple:
    """Matches (idx1, idx2) whose keypoints lie within EPIPOLAR_PX of each other's epipolar line and pass the ratio
    test among such candidates only: repeated texture (a checker floor) has one look-alike per line, not dozens."""
    lines = np.c_[k1, np.ones(len(k1))] @ f.T  # (N1, 3) lines in image 2
    dist = np.abs(lines @ np.c_[k2, np.ones(len(k2))].T) / np.linalg.norm(lines[:, :2], axis=1, keepdims=True).clip(1e-12)
    desc = np.sqrt(np.maximum(0.0, (d1 ** 2).sum(1)[:, None] + (d2 ** 2).sum(1)[None] - 2.0 * d1 @ d2.T))
    desc[dist > EPIPOLAR_PX] = np.inf
    if desc.shape[1] < 2:
        return np.zeros(0, int), np.zeros(0, int)
    two = np.partition(desc, 1, axis=1)[:, :2]
    best = desc.argmin(1)
    ok = np.isfinite(two[:, 0]) & (two[:, 0] < RATIO * two[:, 1])
    return np.nonzero(ok)[0], best[ok]


def per_cell(x: np.ndarray, uv: np.ndarray, depth: np.ndarray, size: np.ndarray) -> np.ndarray:
    """One of the points x per CELLS x CELLS cell of the image (by pixel uv): the one of median depth there."""
    cell = np.clip((uv / size * CELLS).astype(int), 0, CELLS - 1)
    key = cell[:, 1] * CELLS + cell[:, 0]
    keep = []
    for c in np.unique(key):
        idx = np.nonzero(key == c)[0]
        keep.append(idx[np.argsort(depth[idx])[len(idx) // 2]])
    return x[np.asarray(keep, dtype=int)]


def probe_points(split, pairs: int = PROBE_PAIRS) -> np.ndarray:
    """World points (M, 3) triangulated from SIFT matches of neighbouring training views with their known poses,
    one per image cell of each pair (per_cell)."""
    cams = split.cameras
    centres = cams.c2w[:, :3, 3].double().numpy()
    dirs = -cams.c2w[:, :3, 2].double().numpy()
    sift = cv2.SIFT_create(nfeatures=1000, contrastThreshold=0.01)
    cache: dict[int, tuple] = {}

    def features(i: int):
        if i not in cache:
            g, f = _gray(np.asarray(split.images[i]))
            kp, desc = sift.detectAndCompute(g, None)
            cache[i] = (np.array([k.pt for k in kp], dtype=np.float64).reshape(-1, 2), desc, f)
        return cache[i]

    out = []
    for i, j in neighbour_pairs(centres, dirs, pairs):
        (k1, d1, f1), (k2, d2, f2) = features(i), features(j)
        if d1 is None or d2 is None or len(k1) < 2 or len(k2) < 2:
            continue
        a, b = _projection(cams, i, f1), _projection(cams, j, f2)
        q, t = guided_matches(k1, d1.astype(np.float32), k2, d2.astype(np.float32), fundamental(a, b))
        if not len(q):
            continue
        p1, p2 = k1[q], k2[t]
        h = cv2.triangulatePoints(a, b, p1.T, p2.T).T
        h = h[np.abs(h[:, 3]) > 1e-12]
        x = h[:, :3] / h[:, 3:4]
        ha, hb = np.c_[x, np.ones(len(x))] @ a.T, np.c_[x, np.ones(len(x))] @ b.T
        front = (ha[:, 2] > 0) & (hb[:, 2] > 0)
        out.append(per_cell(x[front], p1[front], ha[front, 2], f1 * np.array([float(cams.width[i]),
                                                                              float(cams.height[i])])))
    return np.concatenate(out) if out else np.zeros((0, 3))
