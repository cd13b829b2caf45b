"""Bounded parametrisations of unbounded space, so one hash grid over [-1, 1]^3 holds any scene.

- unbounded 360 captures: the mip-NeRF 360 scene contraction (paper ref. [mipnerf360], its Eq. 10)
  contract(x) = x for |x| <= 1, (2 - 1/|x|) x/|x| otherwise, which maps R^3 into the radius-2 ball
  (L2 norm) or the [-2, 2]^3 cube (L-inf norm, which fills a cubic grid); we halve it into [-1, 1]^3.
- forward-facing captures: NeRF's normalised device coordinates of a reference camera (NeRF appendix C),
  x' = -fx/(W/2) * x/z, y' = -fy/(H/2) * y/z, z' = 1 + 2 near/z, mapping the frustum from the near plane
  to infinity onto [-1, 1]^3 (camera looks down -z, OpenGL).

Both act point-wise, so the renderer keeps marching straight rays in field space: `WarpedField` wraps
any field (density/forward/parameter_groups as in docs/CONTRACTS.md) and evaluates it at warped points.
"""
from __future__ import annotations

from dataclasses import replace as dc_replace

import numpy as np
import torch
from torch import Tensor

SCENE_WARPS = {"bounded": None, "unbounded": "contract", "forward": "ndc"}


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


class NDCWarp:
    """Forward-facing warp: world (field-space) points -> NDC of a reference camera, in [-1, 1]^3."""

    def __init__(self, ref_c2w: np.ndarray | Tensor, fx: float, fy: float, width: float, height: float,
                 near: float):
        c2w = torch.as_tensor(np.asarray(ref_c2w, dtype=np.float64))
        self.w2c = torch.linalg.inv(c2w).float()
        self.ax, self.ay = float(2.0 * fx / width), float(2.0 * fy / height)
        self.near = float(near)

    def __call__(self, x: Tensor) -> Tensor:
        w2c = self.w2c.to(x.device)
        p = x @ w2c[:3, :3].T + w2c[:3, 3]
        z = torch.minimum(p[:, 2:3], torch.full_like(p[:, 2:3], -self.near))  # in front of the near plane
        return torch.cat([-self.ax * p[:, 0:1] / z, -self.ay * p[:, 1:2] / z, 1.0 + 2.0 * self.near / z], dim=-1)

    def to_dict(self) -> dict:
        return {"w2c": self.w2c.tolist(), "ax": self.ax, "ay": self.ay, "near": self.near}


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


def scene_warp(scene) -> "callable | None":
    """The warp a scene's kind needs (in field space), or None for bounded scenes."""
    kind = SCENE_WARPS.get(getattr(scene, "kind", "bounded"))
    if kind == "contract":
        return contract
    if kind == "ndc":
        cams = scene.field_cameras("train")
        ref = mean_pose(cams.c2w.double().numpy())
        centres = cams.c2w[:, :3, 3].double().numpy()
        near_world = float(scene.near) if scene.near > 0 else 1.0
        near = max(near_world * scene.norm.scale, 1e-3)
        # move the reference camera back behind every camera, so the whole frustum is in front of it
        back = ref[:3, 2]
        ref[:3, 3] += back * max(0.0, float(((centres - ref[:3, 3]) @ back).max()))
        return NDCWarp(ref, float(cams.fx[0]), float(cams.fy[0]), float(cams.width[0]), float(cams.height[0]),
                       near)
    return None


class WarpedField(torch.nn.Module):
    """A field evaluated at warped points: the renderer and occupancy grid march in field space,
    the wrapped field (its hash grid) only ever sees [-1, 1]^3. `bound` is the marching extent."""

    def __init__(self, inner: torch.nn.Module, warp, bound: float):
        super().__init__()
        self.inner, self.warp = inner, warp
        cfg = getattr(inner, "cfg", None)
        self.cfg = dc_replace(cfg, bound=float(bound)) if cfg is not None and hasattr(cfg, "bound") else cfg
        self.bound = float(bound)

    def density(self, x: Tensor) -> Tensor:
        return self.inner.density(self.warp(x))

    def forward(self, x: Tensor, d: Tensor, outputs=("rgb",)) -> dict:
        return self.inner(self.warp(x), d, outputs=outputs)

    def parameter_groups(self) -> dict:
        return self.inner.parameter_groups()
