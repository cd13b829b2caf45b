"""Fill masked pixels of an image from their surroundings (the remove edit's per-view targets)."""
from __future__ import annotations

import cv2
import numpy as np
import torch
from torch import Tensor


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
