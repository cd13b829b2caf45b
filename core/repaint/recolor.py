"""Recolour the selection (offline edit, issue 5 item 1): per-view targets with the masked pixels recoloured.

The targets keep each pixel's shading (see `recolor`), so the field learns a new albedo under the same light.
"""
from __future__ import annotations

import torch
from torch import Tensor

from repaint_nerf.core.repaint.color_space import lab_to_rgb, linear_to_srgb, luminance, rgb_to_lab, srgb_to_linear
from repaint_nerf.core.repaint.target_guidance import TargetGuidance


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


class RecolorGuidance(TargetGuidance):
    """Targets: each training view with the masked pixels recoloured to `color` (shading kept)."""

    # A recolour adds no geometry: opening the selection's 3D cells would let faint density there (kept out
    # of the render by the occupancy grid until now) show in front of what the mask leaves out.
    grow_region = False

    def __init__(self, images: list[Tensor], masks: list[Tensor], color, mode: str = "shading",
                 weight: float = 1.0, reduction: str = "sum"):
        """images (H, W, 3) and masks (H, W) per training view, at the render resolution; `reduction` as
        the trainer reduces Eq. unmask (TargetGuidance)."""
        self.color = tuple(float(c) for c in color)
        self.mode = mode
        y_ref = reference_luminance(images, masks)
        targets = [recolor(im, self.color, m, mode, y_ref).permute(2, 0, 1)[None]
                   for im, m in zip(images, masks)]
        super().__init__(targets, weight, reduction)
