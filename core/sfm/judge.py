"""Is a structure-from-motion model plausible? Judged from facts any camera model must satisfy.

A registration count alone does not prove a model right: with one camera shared by all photos the
mapper can converge to a wrong focal length whose error a strong radial distortion absorbs, and still
register every photo (STACK-FACTS.md). The judge looks at what such a model gets wrong: mean
reprojection error, focal length against the EXIF focal length (or a plausible field of view),
distortion at the image corners, the spread of the camera centres and the fraction registered.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

REPROJECTION_MAX_PX = 2.0  # COLMAP filters observations above 4 px; a sound model's mean is well below 1
FOV_RANGE_DEG = (15.0, 130.0)  # field of view across the long side: telephoto .. ultra-wide (not fisheye)
EXIF_FOCAL_TOLERANCE = 0.25  # relative deviation of the refined focal length from the EXIF one
CORNER_DISTORTION_MAX = 0.10  # radial displacement at the image corner, as a fraction of its radius
BASELINE_MIN = 0.02  # camera spread over the median point depth: below it the photos are rotations only
REGISTERED_MIN = 0.5  # fraction of the photos registered

# models whose first two extra parameters are the radial coefficients k1, k2 (COLMAP's order)
RADIAL_MODELS = ("SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV")


@dataclass
class CameraFacts:
    """One camera of a model: size, refined focal length, radial coefficients, EXIF focal (px) if known."""

    width: int
    height: int
    focal: float
    radial: tuple[float, ...] = ()
    exif_focal: float | None = None
    images: int = 1  # photos sharing it


@dataclass
class ModelFacts:
    """What the judge needs of a model: cameras, camera centres, points, mean reprojection error, counts."""

    cameras: list[CameraFacts]
    centres: np.ndarray  # (N, 3) registered camera centres
    points: np.ndarray  # (M, 3) sparse points
    reprojection_px: float
    registered: int
    total: int


@dataclass
class Verdict:
    """The judgement: trusted or not, the reasons it is not, and the figures behind it."""

    trusted: bool
    reasons: list[str] = field(default_factory=list)
    figures: dict = field(default_factory=dict)
    cameras: str = "shared"  # how photos were assigned cameras: "shared" (one per size) or "per-image"

    def score(self) -> tuple:
        """Larger is better: trusted first, then fewer reasons, more photos registered, lower error."""
        return (self.trusted, -len(self.reasons), self.figures.get("registered", 0),
                -self.figures.get("reprojection_px", math.inf))

    def summary(self) -> str:
        """One line: the verdict and its main figures."""
        f = self.figures
        fov = f.get("fov_deg") or []
        parts = [f"reprojection {f.get('reprojection_px', float('nan')):.2f} px",
                 f"field of view {min(fov):.0f}-{max(fov):.0f} deg" if fov else "",
                 f"corner distortion {100 * f.get('corner_distortion', 0.0):.1f}%",
                 f"camera spread {f.get('baseline', float('nan')):.3f} of the scene depth",
                 f"{self.cameras} cameras"]
        head = "trusted" if self.trusted else "implausible: " + "; ".join(self.reasons)
        return f"{head} ({', '.join(p for p in parts if p)})"

    def to_dict(self) -> dict:
        return {"trusted": self.trusted, "reasons": list(self.reasons), "figures": dict(self.figures),
                "cameras": self.cameras}

    @staticmethod
    def from_dict(d: dict) -> "Verdict":
        return Verdict(bool(d.get("trusted")), list(d.get("reasons", [])), dict(d.get("figures", {})),
                       d.get("cameras", "shared"))


def field_of_view_deg(focal: float, width: int, height: int) -> float:
    """Angle across the long side of the image, in degrees."""
    return math.degrees(2.0 * math.atan(0.5 * max(width, height) / max(focal, 1e-9)))


def corner_distortion(cam: CameraFacts) -> float:
    """|k1 r^2 + k2 r^4| at the image corner (r in normalised units): the relative radial displacement there."""
    if not cam.radial:
        return 0.0
    r2 = (0.25 * (cam.width ** 2 + cam.height ** 2)) / max(cam.focal, 1e-9) ** 2
    k1 = cam.radial[0]
    k2 = cam.radial[1] if len(cam.radial) > 1 else 0.0
    return abs(k1 * r2 + k2 * r2 * r2)


def camera_spread(centres: np.ndarray, points: np.ndarray) -> float:
    """Median distance of the camera centres from their mean over the median distance of points from it."""
    centres = np.asarray(centres, np.float64).reshape(-1, 3)
    points = np.asarray(points, np.float64).reshape(-1, 3)
    if len(centres) < 2 or len(points) == 0:
        return 0.0
    mid = centres.mean(0)
    spread = float(np.median(np.linalg.norm(centres - mid, axis=1)))
    depth = float(np.median(np.linalg.norm(points - mid, axis=1)))
    return spread / max(depth, 1e-12)


def judge(facts: ModelFacts, cameras: str = "shared") -> Verdict:
    """Judge a model against the plausibility bounds above; every failed bound is a reason."""
    reasons: list[str] = []
    fovs = [field_of_view_deg(c.focal, c.width, c.height) for c in facts.cameras]
    dist = [corner_distortion(c) for c in facts.cameras]
    exif_dev = [abs(c.focal / c.exif_focal - 1.0) for c in facts.cameras if c.exif_focal]
    spread = camera_spread(facts.centres, facts.points)
    frac = facts.registered / max(1, facts.total)
    if not facts.reprojection_px <= REPROJECTION_MAX_PX:
        reasons.append(f"mean reprojection error {facts.reprojection_px:.2f} px is above {REPROJECTION_MAX_PX} px")
    lo, hi = FOV_RANGE_DEG
    bad_fov = [f for f in fovs if not lo <= f <= hi]
    if bad_fov:
        reasons.append(f"field of view {bad_fov[0]:.0f} deg is outside {lo:.0f}-{hi:.0f} deg "
                       f"({len(bad_fov)} of {len(fovs)} cameras)")
    bad_exif = [d for d in exif_dev if d > EXIF_FOCAL_TOLERANCE]
    if bad_exif:
        reasons.append(f"focal length is {100 * max(bad_exif):.0f}% off the photos' EXIF focal length "
                       f"({len(bad_exif)} of {len(exif_dev)} cameras)")
    bad_dist = [d for d in dist if d > CORNER_DISTORTION_MAX]
    if bad_dist:
        reasons.append(f"lens distortion moves the image corners by {100 * max(bad_dist):.0f}% "
                       f"(more than {100 * CORNER_DISTORTION_MAX:.0f}%; {len(bad_dist)} of {len(dist)} cameras)")
    if facts.registered >= 2 and spread < BASELINE_MIN:
        reasons.append(f"the cameras barely move (spread {spread:.3f} of the scene depth): depth is unrecoverable")
    if frac < REGISTERED_MIN:
        reasons.append(f"only {facts.registered} of {facts.total} photos registered")
    figures = {"reprojection_px": round(float(facts.reprojection_px), 4),
               "fov_deg": [round(f, 2) for f in fovs], "focal_px": [round(c.focal, 2) for c in facts.cameras],
               "corner_distortion": round(max(dist, default=0.0), 4),
               "exif_focal_deviation": round(max(exif_dev), 4) if exif_dev else None,
               "baseline": round(spread, 4), "registered": facts.registered, "total": facts.total,
               "n_cameras": len(facts.cameras)}
    return Verdict(not reasons, reasons, figures, cameras)


def facts_of(rec, total: int, exif_focals: dict[str, float] | None = None) -> ModelFacts:
    """ModelFacts of a pycolmap Reconstruction; `exif_focals` maps image names to EXIF focal lengths in px."""
    exif_focals = exif_focals or {}
    images = [im for im in rec.images.values() if _has_pose(im)]
    per_cam: dict[int, list] = {}
    for im in images:
        per_cam.setdefault(im.camera_id, []).append(im.name)
    cams = []
    for cid, names in per_cam.items():
        cam = rec.cameras[cid]
        params = [float(p) for p in cam.params]
        radial: tuple[float, ...] = ()
        if cam.model_name in RADIAL_MODELS:
            extra = list(cam.extra_params_idxs())
            radial = tuple(params[i] for i in extra[:2])
        exif = [exif_focals[n] for n in names if n in exif_focals]
        cams.append(CameraFacts(int(cam.width), int(cam.height), float(cam.mean_focal_length()), radial,
                                float(np.median(exif)) if exif else None, len(names)))
    centres = np.array([im.projection_center() if hasattr(im, "projection_center")
                        else _centre(im) for im in images], np.float64).reshape(-1, 3)
    points = np.array([p.xyz for p in rec.points3D.values()], np.float64).reshape(-1, 3)
    err = float(rec.compute_mean_reprojection_error()) if rec.num_points3D() else math.inf
    return ModelFacts(cams, centres, points, err, len(images), total)


def _centre(im) -> np.ndarray:
    pose = im.cam_from_world()
    rot = np.asarray(pose.rotation.matrix())
    return -rot.T @ np.asarray(pose.translation)


def _has_pose(im) -> bool:
    flag = getattr(im, "has_pose", None)
    return bool(flag if flag is not None else getattr(im, "registered", True))
