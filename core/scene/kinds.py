"""Which parametrisation a scene needs, from its camera layout: bounded, forward-facing or unbounded.

- forward: every camera looks roughly the same way (LLFF-like): NDC / a bounded depth parametrisation.
- bounded: cameras surround a centre and the content (sparse points, or the far depth) lies inside
  the camera ring: the field cube holds everything.
- unbounded: cameras surround a centre but much of the content lies beyond them (a room, an outdoor
  360 capture): the mip-NeRF 360 contraction (core.field.contraction).
A loader's or the user's choice overrides it (`load_scene(kind=...)`, `--kind`).
"""
from __future__ import annotations

import numpy as np

from repaint_nerf.core.scene.normalize import axes_centre
from repaint_nerf.core.scene.scene import SCENE_KINDS

FORWARD_MAX_ANGLE = 40.0  # degrees between any camera's view direction and the mean one
BEYOND_FRACTION = 0.2  # share of points farther from the centre than the cameras -> unbounded
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
                     far_depth: float | None = None) -> tuple[str, str]:
    """(kind, reason) from camera-to-world poses (N,4,4, OpenGL), optional world points or far z-depth."""
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
        if beyond > BEYOND_FRACTION:
            return "unbounded", f"{beyond:.0%} of the sparse points lie beyond the cameras"
        return "bounded", f"cameras surround the content ({beyond:.0%} of the points beyond them)"
    if far_depth is not None and far_depth > FAR_RATIO * r_cam:
        return "unbounded", f"surfaces up to {far_depth / r_cam:.1f}x the camera distance away"
    return "bounded", "cameras surround a centre"


def detect_kind(scene) -> tuple[str, str]:
    """(kind, reason) for a `Scene` from all its cameras, its points and any known depth range."""
    c2w = np.concatenate([s.cameras.c2w.double().numpy() for s in scene.splits.values()])
    depth_range = scene.extra.get("depth_range") if isinstance(scene.extra, dict) else None
    far = float(np.max(depth_range)) if depth_range is not None else None
    return kind_from_layout(c2w, scene.points, far)


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
