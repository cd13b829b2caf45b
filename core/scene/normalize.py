"""The one place that maps a scene into field space [-1, 1]^3 (a similarity: shift and uniform scale).

Rules, first that applies: a unit box from the dataset (instant-ngp's unit cube with `aabb_scale`, nerfstudio's
scene box: loaders/reach.py; the content may reach beyond it, contraction.warp_spec); an `aabb` from the dataset; for forward-facing captures the region between
near and far that the cameras see; a robust box (1st-99th percentile) of the sparse points; for
object-centric cameras the point nearest all optical axes with a radius from distance and field of view.
"""
from __future__ import annotations

import math

import numpy as np

from repaint_nerf.core.scene.cameras import Cameras
from repaint_nerf.core.scene.scene import Normalization, Scene

MARGIN = 1.05  # the fitted region fills 1/MARGIN of the cube, leaving a small border
POINT_PERCENTILES = (1.0, 99.0)
_DEFAULT_NEAR, _DEFAULT_FAR = 0.0, 1e10


def fit_box(lo, hi, margin: float = MARGIN) -> Normalization:
    """The normalisation that fits the world box [lo, hi] into [-1, 1]^3 (uniform scale, centred)."""
    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    half = float(np.max(hi - lo)) / 2.0
    return Normalization(center=(lo + hi) / 2.0, scale=1.0 / (max(half, 1e-12) * margin))


def robust_box(points: np.ndarray, percentiles=POINT_PERCENTILES) -> tuple[np.ndarray, np.ndarray]:
    """Per-axis percentile box of a point cloud (ignores stray far points)."""
    lo, hi = np.percentile(np.asarray(points, dtype=np.float64), percentiles, axis=0)
    return lo, hi


def _all_cameras(scene: Scene) -> Cameras:
    splits = list(scene.splits.values())
    c2w = np.concatenate([s.cameras.c2w.double().numpy() for s in splits])
    cat = lambda name: np.concatenate([getattr(s.cameras, name).double().numpy() for s in splits])  # noqa: E731
    return Cameras.create(c2w, cat("fx"), cat("fy"), cat("cx"), cat("cy"), cat("width"), cat("height"))


def axes_centre(origins: np.ndarray, dirs: np.ndarray) -> np.ndarray | None:
    """Least-squares point nearest all lines origin + t * dir; None when the lines are (near) parallel."""
    d = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    proj = np.eye(3)[None] - d[:, :, None] * d[:, None, :]
    a, b = proj.sum(0), np.einsum("nij,nj->i", proj, origins)
    s = np.linalg.svd(a, compute_uv=False)
    if s[-1] < 1e-3 * s[0]:
        return None
    return np.linalg.solve(a, b)


def _half_fov(cams: Cameras) -> np.ndarray:
    fx, fy = cams.fx.double().numpy(), cams.fy.double().numpy()
    w, h = cams.width.double().numpy(), cams.height.double().numpy()
    return np.minimum(np.arctan(w / (2 * fx)), np.arctan(h / (2 * fy)))


def frustum_points(cams: Cameras, depths, edges: bool = False) -> np.ndarray:
    """World points on each camera's image corners (and edge midpoints with `edges`) at the given z-depths."""
    pts = []
    for i in range(len(cams)):
        w, h = float(cams.width[i]), float(cams.height[i])
        fx, fy, cx, cy = (float(t[i]) for t in (cams.fx, cams.fy, cams.cx, cams.cy))
        c2w = cams.c2w[i].double().numpy()
        border = [(0, 0), (w, 0), (0, h), (w, h)] + ([(w / 2, 0), (w / 2, h), (0, h / 2), (w, h / 2)] if edges else [])
        for z in depths:
            for u, v in border:
                pts.append(c2w[:3, :3] @ np.array([(u - cx) / fx * z, -(v - cy) / fy * z, -z]) + c2w[:3, 3])
    return np.asarray(pts)


def frustum_box(cams: Cameras, near: float, far: float) -> tuple[np.ndarray, np.ndarray]:
    """Bounding box of the camera frusta between z-depths `near` and `far` (world units)."""
    pts = frustum_points(cams, (near, far))
    return pts.min(0), pts.max(0)


def object_sphere(cams: Cameras) -> tuple[np.ndarray, float]:
    """(centre, radius) of the object the cameras look at: nearest point to all optical axes; radius
    such that the sphere fills the narrower field of view at the median camera distance."""
    origins = cams.c2w[:, :3, 3].double().numpy()
    dirs = -cams.c2w[:, :3, 2].double().numpy()
    centre = axes_centre(origins, dirs)
    if centre is None:  # axes (near) parallel: one camera or a pure translation
        dist = 1.0
        centre = origins.mean(0) + dirs.mean(0) / max(np.linalg.norm(dirs.mean(0)), 1e-12) * dist
    dist = np.linalg.norm(origins - centre, axis=1)
    radius = float(np.median(dist * np.sin(_half_fov(cams))))
    return centre, max(radius, 1e-6)


def _hold_cameras(lo: np.ndarray, hi: np.ndarray, cams: Cameras) -> tuple[np.ndarray, np.ndarray, float]:
    """The box [lo, hi] grown to hold every camera centre, and by how much (its largest side's factor; 0 when
    it already did). A contracted scene needs its cameras inside the field cube, as nerfstudio scales poses
    into its scene box: a camera outside marches its whole view through the contraction, whose cells grow with
    distance, and the fox capture (cameras 2.7 cube half-sizes out) learned a radial blur, 13.6 dB held-out
    after 60 s on one core against 19.5 dB with its cameras inside."""
    centres = cams.c2w[:, :3, 3].double().numpy()
    new_lo, new_hi = np.minimum(lo, centres.min(0)), np.maximum(hi, centres.max(0))
    if np.all(new_lo >= lo) and np.all(new_hi <= hi):
        return lo, hi, 0.0
    return new_lo, new_hi, float(np.max(new_hi - new_lo) / max(float(np.max(hi - lo)), 1e-12))


def content_box(scene: Scene, cams: Cameras, kind: str) -> tuple[str, np.ndarray, np.ndarray]:
    """(rule, lo, hi): the world box a scene of `kind` fits into the field cube, by the first rule that applies
    (this module's docstring); an unbounded scene's is then grown to hold its cameras."""
    aabb = scene.extra.get("aabb")
    unit_box = scene.extra.get("unit_box")
    points = scene.points if scene.points is not None and len(scene.points) >= 8 else None
    if unit_box is not None:
        return ("unit_box", *np.asarray(unit_box, dtype=np.float64))
    if aabb is not None:
        return ("aabb", *np.asarray(aabb, dtype=np.float64))
    if kind == "forward":
        bounds = scene.extra.get("bounds", scene.extra.get("depth_range"))
        near, far = (float(np.min(bounds)), float(np.max(bounds))) if bounds is not None else (scene.near, scene.far)
        if not (0 < near < far < _DEFAULT_FAR):
            near, far = 1.0, 10.0
        return ("frustum", *frustum_box(cams, near, far))
    if points is not None and np.max(np.subtract(*robust_box(points)[::-1])) > 0:
        return ("points", *robust_box(points))
    centre, radius = object_sphere(cams)
    return "cameras", centre - radius, centre + radius


def normalize_scene(scene: Scene) -> Normalization:
    """Choose and record `scene.norm` (world -> field); fills near/far (world units) when the loader did not."""
    cams = _all_cameras(scene)
    rule, lo, hi = content_box(scene, cams, scene.kind)
    held = None
    if scene.kind == "unbounded":
        lo, hi, held = _hold_cameras(lo, hi, cams)
    norm = fit_box(lo, hi)
    scene.norm = norm
    scene.extra["normalization"] = {"rule": rule, "box": [[float(x) for x in lo], [float(x) for x in hi]]}
    if held:
        scene.extra["normalization"]["grown_for_cameras"] = held
    if scene.near == _DEFAULT_NEAR and scene.far == _DEFAULT_FAR:
        cube_radius = math.sqrt(3.0) / norm.scale  # the field cube's circumradius in world units
        dist = np.linalg.norm(cams.c2w[:, :3, 3].double().numpy() - norm.center, axis=1)
        scene.near = float(max(dist.min() - cube_radius, 0.01 * cube_radius))
        scene.far = float(dist.max() + cube_radius)
    return norm
