"""Which parametrisation a scene needs, from its camera layout: bounded, forward-facing or unbounded.

- forward: every camera looks roughly the same way (LLFF-like): NDC / a bounded depth parametrisation.
- bounded: cameras surround a centre and the content (sparse points, or the far depth) lies inside
  the camera ring: the field cube holds everything.
- unbounded: cameras surround a centre but much of the content lies beyond them (a room, an outdoor
  360 capture): the mip-NeRF 360 contraction (core.field.contraction). In opaque photos with SfM points a small
  share beyond the cameras is enough (BEYOND_FRACTION_OPAQUE): every pixel shows a surface the field must hold.
  So is a share of the photos' pixels whose rays miss the box the points fill (MISS_FRACTION): the bounded field
  has nothing on those rays to learn what they show.
Without sparse points the dataset's own word decides first (instant-ngp's `aabb_scale`, a nerfstudio scene box:
loaders/reach.py), then a known far depth, then, for opaque images, a quick probe that triangulates a few image
pairs with the known poses (core.scene.probe). A loader's or the user's choice overrides it
(`load_scene(kind=...)`, `--kind`).
"""
from __future__ import annotations

import numpy as np
import torch

from repaint_nerf.core.scene.normalize import axes_centre, content_box, fit_box
from repaint_nerf.core.scene.scene import SCENE_KINDS

FORWARD_MAX_ANGLE = 40.0  # degrees between any camera's view direction and the mean one
BEYOND_FRACTION = 0.2  # share of points farther from the centre than the cameras -> unbounded
# ... in opaque photos, where every pixel shows a surface the field must hold. Far surfaces give few points (less
# texture and parallax), so a small share stands for much of the photos' area: a carved trunk in a forest (4% of
# its SfM points beyond the cameras) and a plush in a bedroom (10%) were read as bounded, and contracted they
# gained 1.2 dB at 180 s and 9.6 dB at 60 s (the bounded field stayed fog: 94% of its grid occupied). The
# synthetic bounded layouts have none beyond; this only has to stand above the stray points of SfM's refined tracks.
BEYOND_FRACTION_OPAQUE = 0.02
# Share of an opaque capture's training pixels whose rays miss the field cube a bounded fit of its points would give
# -> unbounded. Those pixels can never be learned (the ray has no sample; training composites it on a random colour):
# a share s at a squared error e2 caps the PSNR at -10 log10(s e2), 27 dB at 2% and e2 = 0.1 (dark room behind a lit
# object), about what a capture reaches in 5 minutes here. Found on kermit (bundler's 11 photos of a plush on a chair
# in a room, 1% of its SfM points beyond the cameras): 11% of its pixels miss the box, 6.8 dB held out bounded.
MISS_FRACTION = 0.02
MISS_GRID = 24  # a grid of MISS_GRID x MISS_GRID pixels per view is tested
FAR_RATIO = 2.0  # without points: farthest depth over the camera distance -> unbounded


def view_spread_deg(c2w: np.ndarray) -> float:
    """Largest angle (degrees) between a camera's view direction (-z, OpenGL) and the mean direction."""
    d = -np.asarray(c2w, dtype=np.float64)[:, :3, 2]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    m = d.mean(0)
    if np.linalg.norm(m) < 1e-6:
        return 180.0
    m /= np.linalg.norm(m)
    return float(np.degrees(np.arccos(np.clip(d @ m, -1.0, 1.0))).max())


def kind_from_layout(c2w: np.ndarray, points: np.ndarray | None = None,
                     far_depth: float | None = None, what: str = "the sparse points",
                     opaque: bool = False) -> tuple[str, str]:
    """(kind, reason) from camera-to-world poses (N,4,4, OpenGL), optional world points (`what` names them in
    the reason) or far z-depth; `opaque`: the images have no transparent pixels (a capture, not a cut-out)."""
    c2w = np.asarray(c2w, dtype=np.float64)
    spread = view_spread_deg(c2w)
    if spread <= FORWARD_MAX_ANGLE:
        return "forward", f"all cameras look within {spread:.0f} deg of one direction"
    origins, dirs = c2w[:, :3, 3], -c2w[:, :3, 2]
    centre = axes_centre(origins, dirs)
    if centre is None:
        return "forward", "the optical axes do not meet"
    r_cam = float(np.median(np.linalg.norm(origins - centre, axis=1)))
    if points is not None and len(points) >= 8:
        dist = np.linalg.norm(np.asarray(points, dtype=np.float64) - centre, axis=1)
        beyond = float(np.mean(dist > r_cam))
        if beyond > (BEYOND_FRACTION_OPAQUE if opaque else BEYOND_FRACTION):
            return "unbounded", f"{beyond:.0%} of {what} lie beyond the cameras"
        return "bounded", f"cameras surround the content ({beyond:.0%} of {what} beyond them)"
    if far_depth is not None and far_depth > FAR_RATIO * r_cam:
        return "unbounded", f"surfaces up to {far_depth / r_cam:.1f}x the camera distance away"
    return "bounded", "cameras surround a centre"


def pixels_past_box(cameras, lo, hi, grid: int = MISS_GRID) -> float:
    """Share of the views' pixels (a `grid` x `grid` sample of each) whose rays miss the world box [lo, hi] ahead
    of their camera."""
    from repaint_nerf.core.render.box import intersect_box

    n = len(cameras)
    if n == 0:
        return 0.0
    frac = (torch.arange(grid, dtype=torch.float64) + 0.5) / grid
    fv, fu = (t.reshape(-1).repeat(n) for t in torch.meshgrid(frac, frac, indexing="ij"))
    idx = torch.arange(n).repeat_interleave(grid * grid)
    u = fu * cameras.width.double().cpu()[idx] - 0.5  # `rays` adds the pixel centre's 0.5
    v = fv * cameras.height.double().cpu()[idx] - 0.5
    o, d, _ = cameras.to("cpu").rays(idx, u, v)
    t0, t1 = intersect_box(o.double(), d.double(), torch.as_tensor(lo, dtype=torch.float64),
                           torch.as_tensor(hi, dtype=torch.float64))
    return float(((t1 <= t0) | (t1 <= 0)).double().mean())


def reach_kind(extra: dict) -> tuple[str, str] | None:
    """(kind, reason) from what the dataset says about its content's reach (loaders/reach.py), else None."""
    k = extra.get("aabb_scale")
    if k is not None and k > 1:
        return "unbounded", f"aabb_scale {k:g}: the content reaches {k:g}x instant-ngp's unit cube"
    if k is not None:
        return "bounded", "aabb_scale 1: instant-ngp keeps all content inside its unit cube"
    if extra.get("unit_box") is not None:
        return "unbounded", "a nerfstudio scene box: nerfacto contracts what lies beyond it"
    return None


def _opaque(scene) -> bool:
    """Whether the training images have no transparent pixels (a capture, not an object cut out on alpha)."""
    for im in scene.splits["train"].images[:4]:
        if im.ndim == 3 and im.shape[2] == 4 and int(np.asarray(im)[..., 3].min()) < 255:
            return False
    return True


def probe_kind(scene, c2w: np.ndarray) -> tuple[str, str] | None:
    """(kind, reason) from points a quick probe triangulates (core.scene.probe), or None when it finds too few."""
    from repaint_nerf.core.scene.probe import MIN_POINTS, probe_points

    pts = probe_points(scene.train)
    scene.extra["probe_points"] = int(len(pts))
    if len(pts) < MIN_POINTS:
        return None
    # the probe's points are two-view triangulations, not SfM's refined tracks: 5% of them strayed beyond the
    # cameras around an object on a plain backdrop, so they keep the 20% rule
    kind, why = kind_from_layout(c2w, pts, what=f"{len(pts)} points a quick probe triangulated")
    return kind, why


def detect_kind(scene) -> tuple[str, str]:
    """(kind, reason) for a `Scene` from its dataset's reach, all its cameras, its points, any known depth range,
    and else (opaque images, cameras around a centre) a quick probe of its images."""
    extra = scene.extra if isinstance(scene.extra, dict) else {}
    given = reach_kind(extra)
    if given is not None:
        return given
    c2w = np.concatenate([s.cameras.c2w.double().numpy() for s in scene.splits.values()])
    depth_range = extra.get("depth_range")
    far = float(np.max(depth_range)) if depth_range is not None else None
    opaque = "train" in scene.splits and _opaque(scene)
    kind, why = kind_from_layout(c2w, scene.points, far, opaque=opaque)
    no_points = scene.points is None or len(scene.points) < 8
    if kind == "bounded" and opaque and not no_points:
        rule, lo, hi = content_box(scene, scene.splits["train"].cameras, "bounded")
        if rule == "points":
            norm = fit_box(lo, hi)
            half = 1.0 / norm.scale
            miss = pixels_past_box(scene.splits["train"].cameras, norm.center - half, norm.center + half)
            if miss > MISS_FRACTION:
                return "unbounded", f"{miss:.0%} of the photos' pixels look past the box the sparse points fill"
            why += f"; {miss:.0%} of the photos' pixels look past the box they fill"
    if kind == "bounded" and no_points and far is None and opaque:
        return probe_kind(scene, c2w) or (kind, why + "; a quick probe of the images found too few points to tell")
    return kind, why


def choose_kind(scene, override: str | None = None) -> str:
    """Set and return `scene.kind`: the override when given (validated), else the detected kind."""
    if override is not None:
        if override not in SCENE_KINDS:
            from repaint_nerf.core.errors import UserError

            raise UserError(f"unknown scene kind {override!r}", hint=f"use one of {', '.join(SCENE_KINDS)}")
        scene.kind = override
        return override
    scene.kind, why = detect_kind(scene)
    scene.extra["kind_reason"] = why
    return scene.kind
