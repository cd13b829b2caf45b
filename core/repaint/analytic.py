"""Analytic guidance for measurement: score distillation with the exact denoiser of a known target.

For target x* the ideal noise prediction is eps_hat = (x_t - sqrt(ab) x*) / sqrt(1 - ab), so the SDS
gradient (paper Eq. SDS) is w(t) (eps_hat - eps) = w(t) sqrt(ab) / sqrt(1 - ab) (x - x*), with the
same t sampling, w(t) and loss form as the Stable Diffusion backend, in pixel space (no VAE).
"""
from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from repaint_nerf.core.repaint.guidance import Guidance, GuidanceResult, TimestepSampler, distillation_loss


def sd_alphas_cumprod(num_train_timesteps: int = 1000, beta_start: float = 0.00085,
                      beta_end: float = 0.012) -> Tensor:
    """alpha_bar_t of Stable Diffusion's 'scaled_linear' beta schedule (betas linear in sqrt), fp32."""
    betas = torch.linspace(beta_start ** 0.5, beta_end ** 0.5, num_train_timesteps, dtype=torch.float64) ** 2
    return torch.cumprod(1.0 - betas, dim=0).float()


def as_image_tensor(image: Tensor | np.ndarray) -> Tensor:
    """An image as float (1,3,H,W) in [0,1]: accepts uint8/float (H,W,3|4) arrays or (3,H,W)/(1,3,H,W) tensors."""
    if isinstance(image, np.ndarray):
        arr = image[..., :3]
        t = torch.from_numpy(np.ascontiguousarray(arr))
        t = t.float() / 255.0 if arr.dtype == np.uint8 else t.float()
        return t.permute(2, 0, 1)[None]
    t = image.float()
    if t.dim() == 3 and t.shape[0] not in (3, 4) and t.shape[-1] in (3, 4):
        t = t.permute(2, 0, 1)
    if t.dim() == 3:
        t = t[None]
    return t[:, :3]


class AnalyticGuidance(Guidance):
    """SDS toward known per-view targets (the synthetic scene's edited/ renders of the same cameras)."""

    def __init__(self, targets: Sequence[Tensor | np.ndarray] | Tensor | Callable[[int], Tensor | np.ndarray],
                 t_range: tuple[float, float] = (0.02, 0.98), clip_value: float | None = None,
                 clip_norm: float | None = None, seed: int | None = None, num_train_timesteps: int = 1000):
        self.targets = targets
        self.clip_value, self.clip_norm = clip_value, clip_norm
        self.generator = torch.Generator().manual_seed(seed) if seed is not None else None
        self.alphas_cumprod = sd_alphas_cumprod(num_train_timesteps)
        self.sampler = TimestepSampler(self.alphas_cumprod, t_range, self.generator)
        self._cache: dict[tuple, Tensor] = {}

    def target(self, view: int, size: tuple[int, int], device: torch.device) -> Tensor:
        """The target of `view` as (1,3,H,W) in [0,1] at `size` on `device` (cached)."""
        key = (view, tuple(size), str(device))
        if key not in self._cache:
            raw = self.targets(view) if callable(self.targets) else self.targets[view]
            x = as_image_tensor(raw)
            if tuple(x.shape[-2:]) != tuple(size):
                x = F.interpolate(x, size=size, mode="area")
            self._cache[key] = x.to(device)
        return self._cache[key]

    def loss(self, rgb: Tensor, mask: Tensor | None = None, view: int = 0, step: int = 0) -> GuidanceResult:
        """SDS loss of a render (1,3,H,W) in [0,1] against the exact denoiser of this view's target."""
        x = rgb.float() * 2 - 1  # the [-1, 1] range a diffusion model sees
        target = self.target(view, tuple(rgb.shape[-2:]), rgb.device) * 2 - 1
        t = self.sampler.sample()
        ab = float(self.alphas_cumprod[t])
        with torch.no_grad():
            noise = torch.randn(x.shape, generator=self.generator).to(x.device)
            x_t = ab ** 0.5 * x + (1 - ab) ** 0.5 * noise
            eps_hat = (x_t - ab ** 0.5 * target) / (1 - ab) ** 0.5
            grad = self.sampler.weight(t) * (eps_hat - noise)
        return distillation_loss(x, grad, t, self.clip_value, self.clip_norm)
