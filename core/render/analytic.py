"""Analytic stand-in fields with NGPField's interface (density, forward), for renderer and trainer tests.

Each is density = sigma * shape(x) with a learnable `sigma` and colour logits, so gradients through the
renderer can be checked without the hash grid. Shapes: an axis-aligned box (a slab when it spans two
axes), a ball, and a smooth Gaussian blob.
"""
from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn


class AnalyticField(nn.Module):
    """Base: subclasses define `shape(x) -> (N,) in [0, 1]`; colour = sigmoid(logits + slope * x)."""

    def __init__(self, sigma: float = 10.0, rgb: Sequence[float] = (0.8, 0.3, 0.1), color_slope: float = 0.0,
                 feature_dim: int = 0, bound: float = 1.0):
        super().__init__()
        self.bound = float(bound)
        self.sigma = nn.Parameter(torch.tensor(float(sigma)))
        rgb_t = torch.as_tensor(rgb, dtype=torch.float32).clamp(1e-4, 1 - 1e-4)
        self.rgb_logit = nn.Parameter(torch.log(rgb_t / (1 - rgb_t)))
        self.color_slope = float(color_slope)
        self.feature = nn.Parameter(torch.linspace(-1.0, 1.0, feature_dim)) if feature_dim else None

    def shape(self, x: Tensor) -> Tensor:
        raise NotImplementedError

    def density(self, x: Tensor) -> Tensor:
        """(N,3) -> (N,) sigma >= 0, zero outside the cube [-bound, bound]^3."""
        inside = (x.abs().amax(dim=-1) <= self.bound).to(x.dtype)
        return self.sigma * self.shape(x) * inside

    def color(self, x: Tensor) -> Tensor:
        """(N,3) -> (N,3) colour in [0, 1]."""
        return torch.sigmoid(self.rgb_logit + self.color_slope * x)

    def forward(self, x: Tensor, d: Tensor, outputs: Sequence[str] = ("rgb",)) -> dict:
        """'sigma' (N,), and 'rgb' (N,3) / 'feature' (N,F) when asked (like NGPField.forward)."""
        out = {"sigma": self.density(x)}
        if "rgb" in outputs:
            out["rgb"] = self.color(x)
        if "feature" in outputs:
            if self.feature is None:
                raise ValueError("this field has no feature head (feature_dim=0)")
            out["feature"] = self.feature[None, :] * (1.0 + 0.5 * x[:, :1])
        return out


class BoxField(AnalyticField):
    """Uniform density inside the box [lo, hi] (a slab when it spans the cube in two axes)."""

    def __init__(self, lo: Sequence[float], hi: Sequence[float], **kw):
        super().__init__(**kw)
        self.register_buffer("lo", torch.as_tensor(lo, dtype=torch.float32))
        self.register_buffer("hi", torch.as_tensor(hi, dtype=torch.float32))

    def shape(self, x: Tensor) -> Tensor:
        return ((x >= self.lo) & (x <= self.hi)).all(dim=-1).to(x.dtype)


class _CentredField(AnalyticField):
    """A density around a centre point (a buffer, so it moves with the field's device)."""

    def __init__(self, center: Sequence[float], **kw):
        super().__init__(**kw)
        self.register_buffer("center", torch.as_tensor(center, dtype=torch.float32))


class SphereField(_CentredField):
    """Uniform density inside a ball."""

    def __init__(self, center: Sequence[float] = (0.0, 0.0, 0.0), radius: float = 0.5, **kw):
        super().__init__(center, **kw)
        self.radius = float(radius)

    def shape(self, x: Tensor) -> Tensor:
        return ((x - self.center).norm(dim=-1) <= self.radius).to(x.dtype)


class GaussianField(_CentredField):
    """Smooth density sigma * exp(-|x - c|^2 / (2 s^2)), cut to zero below 1e-6 of the peak."""

    def __init__(self, center: Sequence[float] = (0.0, 0.0, 0.0), scale: float = 0.2, **kw):
        super().__init__(center, **kw)
        self.scale = float(scale)

    def shape(self, x: Tensor) -> Tensor:
        g = torch.exp(-((x - self.center) ** 2).sum(-1) / (2 * self.scale ** 2))
        return g * (g > 1e-6).to(x.dtype)
