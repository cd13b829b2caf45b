"""Grow binary masks by a square neighbourhood (mask dilation for the edits and the unmask loss's margin)."""
from __future__ import annotations

import torch.nn.functional as F
from torch import Tensor


def dilate(mask: Tensor, pixels: int) -> Tensor:
    """Binary dilation of (H, W) or (B, 1, H, W) masks by a square of radius `pixels` (0: unchanged)."""
    if pixels <= 0:
        return mask
    x = mask.float()
    shaped = x if x.dim() == 4 else x[None, None]
    out = F.max_pool2d(shaped, 2 * pixels + 1, stride=1, padding=pixels)
    return out if x.dim() == 4 else out[0, 0]
