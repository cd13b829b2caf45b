"""Image metrics on float images in [0, 1]: PSNR and SSIM (Gaussian window, Wang et al. 2004; equal to scikit-image's
structural_similarity with gaussian_weights, sigma 1.5, population covariance: tests/test_metrics.py)."""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F


def mse_to_psnr(mse: float | torch.Tensor) -> float:
    """PSNR in dB for a mean squared error of images in [0, 1]."""
    m = float(mse)
    return float("inf") if m <= 0 else -10.0 * math.log10(m)


def psnr(pred: torch.Tensor, target: torch.Tensor) -> float:
    """PSNR in dB between two images (any matching shape) with values in [0, 1]."""
    return mse_to_psnr(torch.mean((pred.float() - target.float()) ** 2))


def _gauss(size: int, sigma: float, device) -> torch.Tensor:
    x = torch.arange(size, dtype=torch.float32, device=device) - (size - 1) / 2
    g = torch.exp(-(x ** 2) / (2 * sigma ** 2))
    return g / g.sum()


def ssim(pred: torch.Tensor, target: torch.Tensor, window: int = 11, sigma: float = 1.5) -> float:
    """Mean SSIM of two (H, W, C) images in [0, 1] (valid-region Gaussian filtering, C1=0.01^2, C2=0.03^2)."""
    x = pred.float().permute(2, 0, 1)[None]
    y = target.float().permute(2, 0, 1)[None]
    c = x.shape[1]
    window = min(window, x.shape[-1], x.shape[-2])
    g = _gauss(window, sigma, x.device)
    kern = (g[:, None] * g[None, :]).expand(c, 1, window, window).contiguous()

    def filt(z):
        return F.conv2d(z, kern, groups=c)

    mu_x, mu_y = filt(x), filt(y)
    sxx = filt(x * x) - mu_x ** 2
    syy = filt(y * y) - mu_y ** 2
    sxy = filt(x * y) - mu_x * mu_y
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    num = (2 * mu_x * mu_y + c1) * (2 * sxy + c2)
    den = (mu_x ** 2 + mu_y ** 2 + c1) * (sxx + syy + c2)
    return float((num / den).mean())
