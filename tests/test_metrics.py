"""Image metrics against independent references: SSIM against scikit-image's structural_similarity (Gaussian
window sigma 1.5, population covariance, as Wang et al. 2004 and the NeRF papers report it), PSNR by hand."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from skimage.metrics import structural_similarity

from repaint_nerf.core.train.metrics import psnr, ssim


@pytest.mark.parametrize("shape,noise", [((40, 56, 3), 0.05), ((24, 24, 3), 0.3), ((64, 48, 1), 0.1)])
def test_ssim_matches_scikit_image(shape, noise):
    rng = np.random.default_rng(0)
    x = rng.random(shape).astype(np.float32)
    x = 0.5 * x + 0.5 * np.roll(x, 1, axis=0)  # some structure
    y = np.clip(x + noise * rng.standard_normal(shape).astype(np.float32), 0, 1)
    ref = structural_similarity(x, y, data_range=1.0, channel_axis=-1, gaussian_weights=True, sigma=1.5,
                                use_sample_covariance=False)
    assert ssim(torch.from_numpy(y), torch.from_numpy(x)) == pytest.approx(ref, abs=1e-5)


def test_psnr_by_hand():
    a, b = torch.zeros(4, 4, 3), torch.full((4, 4, 3), 0.1)
    assert psnr(a, b) == pytest.approx(20.0)
