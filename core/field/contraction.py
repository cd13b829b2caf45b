"""Bounded parametrisations of unbounded space, so one hash grid over [-1, 1]^3 holds any scene.

- unbounded 360 captures: the mip-NeRF 360 scene contraction (paper ref. [mipnerf360], its Eq. 10)
  contract(x) = x for |x| <= 1, (2 - 1/|x|) x/|x| otherwise, which maps R^3 into the radius-2 ball
  (L2 norm) or the [-2, 2]^3 cube (L-inf norm, which fills a cubic grid); we halve it into [-1, 1]^3.
- forward-facing captures: NeRF's normalised device coordinates of a reference camera (NeRF appendix C),
  x' = -ax x/z, y' = -ay y/z, z' = 1 + 2 near/z, mapping the frustum from the near plane to infinity
  onto [-1, 1]^3 (camera looks down -z, OpenGL).

Both act point-wise: the renderer keeps marching straight rays in field space (with steps that grow
with distance, `cone`), the field evaluates its hash grid at warped points and the occupancy grid
lives in warped space. A warp is described by a JSON-able spec (saved in the field config):
{"kind": "contract" | "ndc", "extent": marching half-size in field units, "cone": step growth, ...}.
"""
from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from repaint_nerf.core.scene.normalize import frustum_points

SCENE_WARPS = {"bounded": None, "unbounded": "contract", "forward": "ndc"}
CONE = 1.0 / 256.0  # instant-ngp's cone angle for large scenes: a step is at least t/256
CONTRACT_EXTENT = 16.0  # rays stop where the contraction has covered 97% of its range
CONTRACT_MIN_EXTENT = 2.0  # the least reach of a dataset-given aabb_scale (contraction covers half its range)
NDC_FAR_FACTOR = 4.0  # forward scenes: march to 4x the farthest training depth


def _norm(x: Tensor, kind: str) -> Tensor:
    return x.abs().amax(dim=-1, keepdim=True) if kind == "inf" else x.norm(dim=-1, keepdim=True)


def contract(x: Tensor, norm: str = "inf") -> Tensor:
    """mip-NeRF 360 contraction, halved: R^3 -> [-1, 1]^3 (norm 'inf') or the unit ball ('l2').

    Continuous with a continuous first derivative at |x| = 1; the unit region maps linearly onto half its size.
    """
    n = _norm(x, norm).clamp_min(1e-12)
    outer = (2.0 - 1.0 / n) * (x / n)
    return 0.5 * torch.where(n <= 1.0, x, outer)


def uncontract(y: Tensor, norm: str = "inf") -> Tensor:
    """Inverse of `contract` for points strictly inside its image (|y| < 1)."""
    z = 2.0 * y
    n = _norm(z, norm).clamp_min(1e-12)
    r = 1.0 / (2.0 - n).clamp_min(1e-12)  # |x| from |z| = 2 - 1/|x|
    return torch.where(n <= 1.0, z, z / n * r)


class ContractWarp:
    """Unbounded scenes: field-space points -> the halved L-inf contraction in [-1, 1]^3."""

    def __call__(self, x: Tensor) -> Tensor:
        return contract(x, "inf")

    def inverse(self, y: Tensor) -> Tensor:
        """Field-space points for grid points y (clamped inside the open box so infinity is not reached)."""
        return uncontract(y.clamp(-1.0 + 1e-4, 1.0 - 1e-4), "inf")


class NDCWarp:
    """Forward-facing warp: field-space points -> NDC of a reference camera, [-1, 1]^3 inside its frustum.

    Points behind the near plane map outside the box (z' < -1), so the field gives them no density.
    """

    def __init__(self, ref_c2w: np.ndarray | Tensor | None = None, fx: float = 1.0, fy: float = 1.0,
                 width: float = 2.0, height: float = 2.0, near: float = 1.0, spec: dict | None = None):
        if spec is not None:
            self.w2c = torch.tensor(spec["w2c"], dtype=torch.float32)
            self.ax, self.ay, self.near = float(spec["ax"]), float(spec["ay"]), float(spec["near"])
            return
        c2w = torch.as_tensor(np.asarray(ref_c2w, dtype=np.float64))
        self.w2c = torch.linalg.inv(c2w).float()
        self.ax, self.ay = float(2.0 * fx / width), float(2.0 * fy / height)
        self.near = float(near)

    def __call__(self, x: Tensor) -> Tensor:
        w2c = self.w2c.to(x.device, x.dtype)
        p = x @ w2c[:3, :3].T + w2c[:3, 3]
        z = p[:, 2:3].clamp(max=-1e-6)  # behind the camera: z' << -1, outside the box
        return torch.cat([-self.ax * p[:, 0:1] / z, -self.ay * p[:, 1:2] / z, 1.0 + 2.0 * self.near / z], dim=-1)

    def inverse(self, y: Tensor) -> Tensor:
        """Field-space points for NDC points y (z' clamped below 1, i.e. short of infinity)."""
        w2c = self.w2c.to(y.device, y.dtype)
        z = 2.0 * self.near / (y[:, 2:3].clamp(max=1.0 - 1e-4) - 1.0)
        p = torch.cat([-y[:, 0:1] * z / self.ax, -y[:, 1:2] * z / self.ay, z], dim=-1)
        r = w2c[:3, :3]
        return (p - w2c[:3, 3]) @ r  # r^T (p - t), row-vector form

    def to_dict(self) -> dict:
        return {"kind": "ndc", "w2c": self.w2c.tolist(), "ax": self.ax, "ay": self.ay, "near": self.near}


def make_warp(spec: dict | None):
    """The warp object for a spec (None for bounded scenes)."""
    if not spec:
        return None
    from repaint_nerf.core.errors import UserError

    if spec.get("kind") == "contract":
        return ContractWarp()
    if spec.get("kind") == "ndc":
        return NDCWarp(spec=spec)
    raise UserError(f"unknown space warp {spec.get('kind')!r} in the field config",
                    hint="the checkpoint comes from a newer version; retrain or update")


def mean_pose(c2w: np.ndarray) -> np.ndarray:
    """Average camera-to-world pose (mean centre, mean axes re-orthonormalised): the NDC reference camera."""
    c2w = np.asarray(c2w, dtype=np.float64)
    back = c2w[:, :3, 2].mean(0)
    back /= np.linalg.norm(back)
    up = c2w[:, :3, 1].mean(0)
    right = np.cross(up, back)
    right /= np.linalg.norm(right)
    out = np.eye(4)
    out[:3, 0], out[:3, 1], out[:3, 2], out[:3, 3] = right, np.cross(back, right), back, c2w[:, :3, 3].mean(0)
    return out


def ndc_spec(cams, near: float, far: float) -> dict:
    """NDC warp for forward-facing training cameras (field space) seeing z-depths [near, far] (field units).

    The reference camera is the mean pose moved back behind every camera; its field of view and near
    plane are widened so every training frustum from `near` on lies inside the NDC box.
    """
    ref = mean_pose(cams.c2w.double().numpy())
    centres = cams.c2w[:, :3, 3].double().numpy()
    back = ref[:3, 2]
    ref[:3, 3] += back * max(0.0, float(((centres - ref[:3, 3]) @ back).max()))
    depths = near * np.geomspace(1.0, max(far / near, 1.0 + 1e-6), 6)
    pts = frustum_points(cams, depths, edges=True)
    w2c = np.linalg.inv(ref)
    p = pts @ w2c[:3, :3].T + w2c[:3, 3]
    zf = np.maximum(-p[:, 2], 1e-9)
    ref_near = 0.9 * float(zf.min())
    ax = 1.0 / (1.05 * float(np.abs(p[:, 0] / zf).max()))
    ay = 1.0 / (1.05 * float(np.abs(p[:, 1] / zf).max()))
    extent = max(1.0, NDC_FAR_FACTOR * float(np.abs(pts).max()))
    spec = NDCWarp(ref, 1.0, 1.0, 2.0, 2.0, ref_near).to_dict()
    spec.update(ax=ax, ay=ay, extent=extent, cone=CONE)
    return spec


def contract_extent(scene) -> float:
    """How far (field units) a contracted scene's rays march: instant-ngp's `aabb_scale` when the dataset gives one
    above 1 (its unit cube is the field cube: normalize.py), else CONTRACT_EXTENT."""
    k = scene.extra.get("aabb_scale")
    if k is None or k <= 1:
        return CONTRACT_EXTENT
    box = scene.extra.get("unit_box")
    if box is None or scene.norm is None:
        return float(k)
    # the reach in field units: k unit cubes around the unit cube's centre, in a field cube that may have grown
    # to hold the cameras (normalize._hold_cameras); never less than CONTRACT_MIN_EXTENT, so content just past
    # the cameras keeps a place
    lo, hi = np.asarray(box, dtype=np.float64)
    half_world = 0.5 * float(np.max(hi - lo)) * float(k)
    centre = (lo + hi) / 2.0 - np.asarray(scene.norm.center, dtype=np.float64)
    reach = (half_world + float(np.max(np.abs(centre)))) * float(scene.norm.scale)
    return max(CONTRACT_MIN_EXTENT, reach)


def warp_spec(scene) -> dict | None:
    """The warp a scene's kind needs (a JSON-able spec for the field config), or None for bounded scenes
    and for scenes whose dataset gives a box (`aabb`) around all content: the field cube already holds it
    (unless `aabb_scale` says the content reaches beyond that box)."""
    if scene.extra.get("aabb") is not None and scene.extra.get("unit_box") is None:
        return None
    kind = SCENE_WARPS.get(getattr(scene, "kind", "bounded"))
    if kind == "contract":
        return {"kind": "contract", "extent": contract_extent(scene), "cone": CONE}
    if kind == "ndc":
        cams = scene.field_cameras("train")
        s = scene.norm.scale
        near = max(float(scene.near) * s if scene.near > 0 else 0.05, 1e-3)
        far = float(scene.far) * s if 0 < scene.far < 1e9 else 4.0
        return ndc_spec(cams, near, max(far, 2.0 * near))
    return None


def warp_summary(scene) -> tuple[str, str]:
    """(the warp `warp_spec` chooses, in words; why), for `info`."""
    if scene.extra.get("aabb") is not None and scene.extra.get("unit_box") is None:
        return "none", "the dataset's aabb bounds all content"
    kind = SCENE_WARPS.get(getattr(scene, "kind", "bounded"))
    if kind == "contract":
        e = contract_extent(scene)
        k = scene.extra.get("aabb_scale", 1)
        src = f"the reach aabb_scale {k:g} gives" if k > 1 else "the default reach"
        return (f"mip-NeRF 360 contraction beyond the field cube, rays marched to {e:.4g}x its half-size",
                f"an {scene.kind} scene: far content keeps a place in the field; {src}")
    if kind == "ndc":
        return "NDC of a reference camera", "forward-facing scene: depth reaches to infinity in one direction"
    return "none", "bounded scene: the field cube holds the content"
