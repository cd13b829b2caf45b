"""Offline edits that need no model: recolour the selection and remove it (issue 5, item 1).

Both are Guidance backends with per-view image targets, so they run through the same repaint trainer
loop as score distillation (live preview, pause, cancel, undo). Recolour builds its targets by
recolouring the training images inside the mask, keeping their shading; remove inpaints the training
images over the mask (cv2.inpaint) and also trains the density of the selection's 3D region down
(`field_loss`), so the object is gone from every angle, not just painted over.

Why targets and not editing the colour MLP for points in a 3D region: the colour MLP is shared by the
whole scene through the hash grid, so an output-space edit needs a 3D mask at render time forever after
(a wrapper around the saved field), while fitting targets leaves a plain field that saves, loads and
renders like any other; with lambda_unmask holding the rest it converges in a few hundred steps.
"""
from __future__ import annotations

import math

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from core.repaint.guidance import GuidanceResult

# --- colour math (sRGB in [0, 1], D65) ---------------------------------------------------------------

_RGB2XYZ = torch.tensor([[0.4124564, 0.3575761, 0.1804375],
                         [0.2126729, 0.7151522, 0.0721750],
                         [0.0193339, 0.1191920, 0.9503041]])
_WHITE = torch.tensor([0.95047, 1.0, 1.08883])


def srgb_to_linear(x: Tensor) -> Tensor:
    """sRGB transfer function inverse (elementwise, [0, 1])."""
    x = x.clamp(0, 1)
    return torch.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(x: Tensor) -> Tensor:
    """sRGB transfer function (elementwise, clamped to [0, 1])."""
    x = x.clamp(0, 1)
    return torch.where(x <= 0.0031308, x * 12.92, 1.055 * x.clamp_min(1e-12) ** (1 / 2.4) - 0.055)


def luminance(rgb: Tensor) -> Tensor:
    """Relative luminance Y of sRGB colours (..., 3) -> (...)."""
    return srgb_to_linear(rgb) @ _RGB2XYZ[1].to(rgb)


def rgb_to_lab(rgb: Tensor) -> Tensor:
    """sRGB (..., 3) in [0, 1] -> CIELAB (..., 3) (L in [0, 100])."""
    xyz = srgb_to_linear(rgb) @ _RGB2XYZ.T.to(rgb) / _WHITE.to(rgb)
    d = 6 / 29
    f = torch.where(xyz > d ** 3, xyz.clamp_min(1e-12) ** (1 / 3), xyz / (3 * d * d) + 4 / 29)
    return torch.stack([116 * f[..., 1] - 16, 500 * (f[..., 0] - f[..., 1]), 200 * (f[..., 1] - f[..., 2])], -1)


def lab_to_rgb(lab: Tensor) -> Tensor:
    """CIELAB (..., 3) -> sRGB (..., 3), clamped into the gamut."""
    fy = (lab[..., 0] + 16) / 116
    f = torch.stack([fy + lab[..., 1] / 500, fy, fy - lab[..., 2] / 200], -1)
    d = 6 / 29
    xyz = torch.where(f > d, f ** 3, 3 * d * d * (f - 4 / 29)) * _WHITE.to(lab)
    lin = xyz @ torch.linalg.inv(_RGB2XYZ).T.to(lab)
    return linear_to_srgb(lin)


def reference_luminance(images: list[Tensor], masks: list[Tensor], q: float = 0.95) -> float:
    """The lit luminance of the selection: the q-quantile of Y over its pixels in all views (0.5 if empty)."""
    ys = [luminance(im[m > 0.5]) for im, m in zip(images, masks) if bool((m > 0.5).any())]
    if not ys:
        return 0.5
    y = torch.cat(ys)
    if y.numel() > 1 << 20:
        y = y[torch.randperm(y.numel())[: 1 << 20]]
    return max(float(torch.quantile(y.float(), q)), 1e-4)


def recolor(rgb: Tensor, color, mask: Tensor | None = None, mode: str = "shading",
            ref_luminance: float | None = None) -> Tensor:
    """Recolour sRGB pixels (..., 3) in [0, 1] to `color` inside `mask` (soft, (...)), keeping shading.

    mode 'shading' (default): a diffuse surface is albedo x shading, so the new pixel is the target
    colour (linear) times the pixel's shading Y / Y_ref, with Y_ref the selection's lit luminance; the
    target's own lightness shows through (a red ball turned dark blue looks dark blue).
    mode 'lightness': CIELAB with L kept and (a, b) taken from the target (hue and chroma replaced).
    """
    target = torch.as_tensor(color, dtype=rgb.dtype, device=rgb.device).reshape(3)
    if mode == "shading":
        y_ref = ref_luminance if ref_luminance is not None else max(float(luminance(rgb).max()), 1e-4)
        shade = (luminance(rgb) / y_ref)[..., None]
        out = linear_to_srgb(srgb_to_linear(target) * shade)
    elif mode == "lightness":
        lab = rgb_to_lab(rgb)
        t_lab = rgb_to_lab(target)
        out = lab_to_rgb(torch.cat([lab[..., :1], t_lab[1:].expand_as(lab[..., 1:])], -1))
    else:
        raise ValueError(f"unknown recolour mode {mode!r} (use 'shading' or 'lightness')")
    if mask is None:
        return out
    m = mask.to(rgb.dtype)[..., None]
    return rgb * (1 - m) + out * m


def inpaint(rgb: Tensor, mask: Tensor, radius: int = 5) -> Tensor:
    """Fill the pixels under `mask` (H, W) of an sRGB image (H, W, 3) from their surroundings (cv2 Telea)."""
    img = (rgb.detach().clamp(0, 1).cpu().numpy() * 255 + 0.5).astype(np.uint8)
    hole = ((mask.detach().cpu().numpy() > 0.5) * 255).astype(np.uint8)
    if not hole.any():
        return rgb.clone()
    filled = cv2.inpaint(np.ascontiguousarray(img), hole, float(radius), cv2.INPAINT_TELEA)
    out = torch.from_numpy(filled).to(rgb.device, rgb.dtype) / 255.0
    m = mask.to(rgb.dtype)[..., None] > 0.5
    return torch.where(m, out, rgb)


def dilate(mask: Tensor, pixels: int) -> Tensor:
    """Binary dilation of (H, W) or (B, 1, H, W) masks by a square of radius `pixels` (0: unchanged)."""
    if pixels <= 0:
        return mask
    x = mask.float()
    shaped = x if x.dim() == 4 else x[None, None]
    out = F.max_pool2d(shaped, 2 * pixels + 1, stride=1, padding=pixels)
    return out if x.dim() == 4 else out[0, 0]


# --- the selection's 3D region ------------------------------------------------------------------------

@torch.no_grad()
def selection_region(cameras, masks: list[Tensor], bound: float = 1.0, resolution: int = 64,
                     min_views: int = 2) -> Tensor:
    """Voxels (resolution^3 bool over [-bound, bound]^3) of the selection's visual hull.

    A voxel belongs when every training view whose image holds its centre (in front of the camera)
    sees it inside the mask, and at least `min_views` views hold it. Masks are (H_i, W_i) at each
    camera's resolution (the cameras may be scaled to the masks' size).
    """
    dev = cameras.device
    r = resolution
    ax = (torch.arange(r, device=dev, dtype=torch.float32) + 0.5) * (2 * bound / r) - bound
    pts = torch.stack(torch.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
    seen = torch.zeros(pts.shape[0], dtype=torch.int32, device=dev)
    inside = torch.ones(pts.shape[0], dtype=torch.bool, device=dev)
    for i, m in enumerate(masks):
        uv, z = cameras.project(pts, i)
        h, w = m.shape[-2:]
        u, v = torch.floor(uv[:, 0]).long(), torch.floor(uv[:, 1]).long()
        ok = (z > 1e-6) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        hit = torch.zeros_like(ok)
        hit[ok] = m.to(dev)[v[ok], u[ok]] > 0.5
        seen += ok.int()
        inside &= ~ok | hit
    return (inside & (seen >= min_views)).reshape(r, r, r)


def region_points(region: Tensor, bound: float, n: int, generator: torch.Generator | None = None) -> Tensor:
    """`n` points drawn uniformly inside the region's voxels (jittered), (n, 3); empty when it is empty."""
    idx = region.reshape(-1).nonzero(as_tuple=True)[0]
    if idx.numel() == 0:
        return torch.zeros(0, 3, device=region.device)
    r = region.shape[0]
    pick = idx[torch.randint(0, idx.numel(), (n,), generator=generator, device="cpu").to(idx.device)]
    ijk = torch.stack([pick // (r * r), (pick // r) % r, pick % r], -1).float()
    jitter = torch.rand(n, 3, generator=generator, device="cpu").to(region.device)
    return (ijk + jitter) * (2 * bound / r) - bound


def mark_region_occupied(grid, region: Tensor, bound: float) -> int:
    """Mark the occupancy grid's cells that hold region voxels occupied (new content may grow there).

    Their density is raised to a little above the grid's threshold, so the normal decay frees them again
    after a few hundred steps if nothing grows. Returns the number of cells marked.
    """
    if grid is None or not bool(region.any()):
        return 0
    r = region.shape[0]
    idx = region.reshape(-1).nonzero(as_tuple=True)[0]
    ijk = torch.stack([idx // (r * r), (idx // r) % r, idx % r], -1).float()
    pts = (ijk + 0.5) * (2 * bound / r) - bound
    return grid.mark_occupied(pts)


# --- guidances with image targets ----------------------------------------------------------------

class TargetGuidance:
    """Guidance toward fixed per-view images inside the mask: loss = weight * mean over masked pixels of
    ||render - target||^2. Targets and masks are (1, 3, H, W) / (1, 1, H, W) per view, at the render size."""

    grow_region = True  # mark the selection's cells occupied at the start (new content may appear)

    def __init__(self, targets: list[Tensor], weight: float = 1.0):
        self.targets = targets
        self.weight = float(weight)

    def target(self, view: int, size: tuple[int, int], device) -> Tensor:
        t = self.targets[view].to(device)
        if tuple(t.shape[-2:]) != tuple(size):
            t = F.interpolate(t, size=size, mode="area")
        return t

    def loss(self, rgb: Tensor, mask: Tensor, view: int, step: int) -> GuidanceResult:
        """Masked MSE to this view's target (fp32); skipped when the render is not finite."""
        tgt = self.target(view, tuple(rgb.shape[-2:]), rgb.device)
        m = mask.float()
        err = ((rgb.float() - tgt) ** 2 * m).sum() / (3 * m.sum()).clamp_min(1.0)
        loss = self.weight * err
        if not bool(torch.isfinite(loss)):
            return GuidanceResult(loss=torch.zeros((), device=rgb.device), skipped=True, t=0, grad_norm=0.0)
        return GuidanceResult(loss=loss, skipped=False, t=0, grad_norm=float(err.detach()))


class RecolorGuidance(TargetGuidance):
    """Targets: each training view with the masked pixels recoloured to `color` (shading kept)."""

    # A recolour adds no geometry: opening the selection's 3D cells would let faint density there (kept out
    # of the render by the occupancy grid until now) show in front of what the mask leaves out.
    grow_region = False

    def __init__(self, images: list[Tensor], masks: list[Tensor], color, mode: str = "shading",
                 weight: float = 1.0):
        """images (H, W, 3) and masks (H, W) per training view, at the render resolution."""
        self.color = tuple(float(c) for c in color)
        self.mode = mode
        y_ref = reference_luminance(images, masks)
        targets = [recolor(im, self.color, m, mode, y_ref).permute(2, 0, 1)[None]
                   for im, m in zip(images, masks)]
        super().__init__(targets, weight)


class RemoveGuidance(TargetGuidance):
    """Targets: each training view inpainted over the mask; plus the region's density trained to zero."""

    grow_region = False

    def __init__(self, images: list[Tensor], masks: list[Tensor], region: Tensor | None = None,
                 bound: float = 1.0, weight: float = 1.0, clear_weight: float = 10.0,
                 clear_points: int = 8192, step_size: float | None = None, inpaint_radius: int = 5,
                 seed: int = 0):
        """images (H, W, 3), masks (H, W) (dilate them first to cover the object's edges), region from
        `selection_region` (None: no 3D clearing)."""
        targets = [inpaint(im, m, inpaint_radius).permute(2, 0, 1)[None] for im, m in zip(images, masks)]
        super().__init__(targets, weight)
        self.region, self.bound = region, float(bound)
        self.clear_weight, self.clear_points = float(clear_weight), int(clear_points)
        self.step_size = step_size or 2 * math.sqrt(3) * bound / 1024
        self.generator = torch.Generator().manual_seed(seed)

    def field_loss(self, field, step: int) -> Tensor | None:
        """clear_weight * mean opacity of one marching step at random points of the region (drives it empty)."""
        if self.region is None or self.clear_weight <= 0:
            return None
        x = region_points(self.region, self.bound, self.clear_points, self.generator)
        if x.numel() == 0:
            return None
        sigma = field.density(x).float()
        alpha = -torch.expm1(-sigma * (self.step_size * 16))  # opacity of a 16-step segment
        return self.clear_weight * alpha.mean()
