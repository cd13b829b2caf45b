"""The one camera model: pinhole intrinsics per image and OpenGL camera-to-world poses.

Convention (NeRF-synthetic / OpenGL): the camera looks down its -z axis, +x is right, +y is up.
Pixel (u, v) has its centre at (u + 0.5, v + 0.5); v grows downwards in the image. Loaders convert
other conventions once, at load time, with `opencv_to_opengl`.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

# Flips y and z: OpenCV/COLMAP camera axes (x right, y down, z forward) <-> OpenGL (x right, y up, z back).
_FLIP_YZ = np.diag([1.0, -1.0, -1.0, 1.0])


def opencv_to_opengl(c2w: np.ndarray) -> np.ndarray:
    """Convert (..., 4, 4) OpenCV camera-to-world poses to the OpenGL convention (and back: it is an involution)."""
    return c2w @ _FLIP_YZ


@dataclass
class Cameras:
    """N pinhole cameras. Poses are camera-to-world (N, 4, 4) in the OpenGL convention."""

    c2w: torch.Tensor  # (N, 4, 4) float32
    fx: torch.Tensor  # (N,) float32, pixels
    fy: torch.Tensor
    cx: torch.Tensor
    cy: torch.Tensor
    width: torch.Tensor  # (N,) int64
    height: torch.Tensor

    @staticmethod
    def create(c2w, fx, fy, cx, cy, width, height) -> "Cameras":
        """Build from array-likes; scalars broadcast to every camera."""
        c2w_t = torch.as_tensor(np.asarray(c2w, dtype=np.float32))
        if c2w_t.ndim == 2:
            c2w_t = c2w_t[None]
        if c2w_t.shape[-2:] == (3, 4):
            bottom = torch.tensor([0, 0, 0, 1], dtype=torch.float32).expand(c2w_t.shape[0], 1, 4)
            c2w_t = torch.cat([c2w_t, bottom], dim=1)
        n = c2w_t.shape[0]

        def vec(x, dtype):
            return torch.as_tensor(np.broadcast_to(np.asarray(x, dtype=np.float64), (n,)).copy()).to(dtype)

        return Cameras(c2w_t, vec(fx, torch.float32), vec(fy, torch.float32), vec(cx, torch.float32),
                       vec(cy, torch.float32), vec(width, torch.int64), vec(height, torch.int64))

    @staticmethod
    def cat(parts: list["Cameras"]) -> "Cameras":
        """The cameras of `parts`, in order, as one set (on the first part's device)."""
        dev = parts[0].device
        return Cameras(*(torch.cat([getattr(c, k).to(dev) for c in parts]) for k in
                         ("c2w", "fx", "fy", "cx", "cy", "width", "height")))

    def __len__(self) -> int:
        return int(self.c2w.shape[0])

    def sizes(self) -> list[tuple[int, int]]:
        """(H, W) of each view, in pixels."""
        return [(int(h), int(w)) for h, w in zip(self.height.tolist(), self.width.tolist())]

    def __getitem__(self, idx) -> "Cameras":
        if isinstance(idx, int):
            idx = [idx]
        return Cameras(self.c2w[idx], self.fx[idx], self.fy[idx], self.cx[idx], self.cy[idx],
                       self.width[idx], self.height[idx])

    def to(self, device) -> "Cameras":
        return Cameras(*(t.to(device) for t in (self.c2w, self.fx, self.fy, self.cx, self.cy,
                                                 self.width, self.height)))

    @property
    def device(self) -> torch.device:
        return self.c2w.device

    def scaled(self, factor: float) -> "Cameras":
        """Cameras for images resized by `factor` (e.g. 0.5 halves width and height)."""
        w = torch.round(self.width.double() * factor).long()
        h = torch.round(self.height.double() * factor).long()
        sx, sy = w.float() / self.width.float(), h.float() / self.height.float()
        return Cameras(self.c2w.clone(), self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy, w, h)

    def with_poses(self, c2w: torch.Tensor) -> "Cameras":
        return Cameras(c2w.to(self.c2w), self.fx, self.fy, self.cx, self.cy, self.width, self.height)

    def centers(self) -> torch.Tensor:
        return self.c2w[:, :3, 3]

    def rays(self, index: torch.Tensor, u: torch.Tensor, v: torch.Tensor):
        """Rays through pixel centres (u + 0.5, v + 0.5) of cameras `index` (all (R,) tensors).

        Returns (origins (R,3), unit directions (R,3), dz (R,)) where dz is the cosine between the ray
        and the optical axis, so depth along the camera axis = distance along the ray * dz.
        """
        index = index.to(self.c2w.device).long()
        x = (u.to(self.fx) + 0.5 - self.cx[index]) / self.fx[index]
        y = -(v.to(self.fy) + 0.5 - self.cy[index]) / self.fy[index]
        d_cam = torch.stack([x, y, -torch.ones_like(x)], dim=-1)
        norm = d_cam.norm(dim=-1, keepdim=True)
        rot = self.c2w[index, :3, :3]
        dirs = torch.einsum("rij,rj->ri", rot, d_cam / norm)
        origins = self.c2w[index, :3, 3]
        return origins, dirs, (1.0 / norm[:, 0])

    def image_rays(self, i: int):
        """All rays of camera i in row-major pixel order: (H*W, 3), (H*W, 3), (H*W,)."""
        h, w = int(self.height[i]), int(self.width[i])
        vv, uu = torch.meshgrid(torch.arange(h, device=self.device), torch.arange(w, device=self.device),
                                indexing="ij")
        idx = torch.full((h * w,), i, dtype=torch.long, device=self.device)
        return self.rays(idx, uu.reshape(-1), vv.reshape(-1))

    def project(self, points: torch.Tensor, i: int):
        """Project world points (P,3) into camera i: (pixel coords (P,2) with centres at +0.5, depth (P,))."""
        uv, z = self.project_views(points, torch.tensor([int(i)]))
        return uv[0], z[0]

    def project_views(self, points: torch.Tensor, views: torch.Tensor):
        """Project world points (P,3) into each camera of `views` (V,) at once: ((V,P,2) pixels, (V,P) depth)."""
        views = views.to(self.c2w.device).long()
        w2c = torch.linalg.inv(self.c2w[views])
        pc = torch.matmul(points.to(w2c)[None], w2c[:, :3, :3].transpose(1, 2)) + w2c[:, None, :3, 3]
        z = -pc[..., 2]
        u = self.fx[views, None] * pc[..., 0] / z + self.cx[views, None]
        v = -self.fy[views, None] * pc[..., 1] / z + self.cy[views, None]
        return torch.stack([u, v], dim=-1), z

    def in_image(self, uv: torch.Tensor, z: torch.Tensor, views: torch.Tensor) -> torch.Tensor:
        """Whether points that `project_views` put at pixels `uv` (V,P,2) and depths `z` (V,P) in `views` (V,) lie in
        front of each camera and inside its image [0, W) x [0, H): (V,P) bool."""
        views = views.to(self.c2w.device).long()
        w, h = self.width[views, None].to(uv), self.height[views, None].to(uv)
        return (z > 0) & (uv[..., 0] >= 0) & (uv[..., 0] < w) & (uv[..., 1] >= 0) & (uv[..., 1] < h)


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """OpenGL camera-to-world pose at `eye` looking at `target` (4x4 float64)."""
    eye, target, up = (np.asarray(a, dtype=np.float64) for a in (eye, target, up))
    back = eye - target
    back /= np.linalg.norm(back)
    right = np.cross(up, back)
    if np.linalg.norm(right) < 1e-8:
        right = np.cross(np.array([0.0, 1.0, 0.0]), back)
    right /= np.linalg.norm(right)
    true_up = np.cross(back, right)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, true_up, back, eye
    return m
