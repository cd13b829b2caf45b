"""Colour math for the offline edits: sRGB <-> linear, relative luminance, CIELAB (sRGB in [0, 1], D65)."""
from __future__ import annotations

import torch
from torch import Tensor

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
