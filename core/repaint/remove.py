"""Remove the selection (offline edit, issue 5 item 1): inpainted per-view targets and the 3D region cleared."""
from __future__ import annotations

import math

import torch
from torch import Tensor

from repaint_nerf.core.repaint.inpaint import inpaint
from repaint_nerf.core.repaint.region import region_points
from repaint_nerf.core.repaint.target_guidance import TargetGuidance


class RemoveGuidance(TargetGuidance):
    """Targets: each training view inpainted over the mask; plus the region's density trained to zero."""

    grow_region = False

    def __init__(self, images: list[Tensor], masks: list[Tensor], region: Tensor | None = None,
                 bound: float = 1.0, weight: float = 1.0, clear_weight: float = 10.0,
                 clear_points: int = 8192, step_size: float | None = None, inpaint_radius: int = 5,
                 seed: int = 0, reduction: str = "sum"):
        """images (H, W, 3), masks (H, W) (dilate them first to cover the object's edges), region from
        `selection_region` (None: no 3D clearing); `reduction` as the trainer reduces Eq. unmask."""
        targets = [inpaint(im, m, inpaint_radius).permute(2, 0, 1)[None] for im, m in zip(images, masks)]
        super().__init__(targets, weight, reduction)
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
