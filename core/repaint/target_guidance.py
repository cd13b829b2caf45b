"""Guidance toward fixed per-view image targets inside the mask: the base of the offline edits (recolour, remove).

Both offline edits are Guidance backends with per-view image targets, so they run through the same repaint
trainer loop as score distillation (live preview, pause, cancel, undo). Recolour builds its targets by
recolouring the training images inside the mask, keeping their shading; remove inpaints the training
images over the mask (cv2.inpaint) and also trains the density of the selection's 3D region down
(`field_loss`), so the object is gone from every angle, not just painted over.

Why targets and not editing the colour MLP for points in a 3D region: the colour MLP is shared by the
whole scene through the hash grid, so an output-space edit needs a 3D mask at render time forever after
(a wrapper around the saved field), while fitting targets leaves a plain field that saves, loads and
renders like any other; with lambda_unmask holding the rest it converges in a few hundred steps.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from repaint_nerf.core.repaint.config import UNMASK_REDUCTIONS
from repaint_nerf.core.repaint.guidance import Guidance, GuidanceResult
from repaint_nerf.core.repaint.objective import masked_mse, unmask_loss


class TargetGuidance(Guidance):
    """Guidance toward fixed per-view images inside the mask: Eq. unmask's squared error on the masked pixels.

    loss = weight * sum over masked rays of ||render - target||^2, reduced like Eq. unmask (`reduction`, the
    trainer's unmask_reduction), so each masked pixel is pulled to its target as hard as each unmasked one is
    held to the photo, and lambda_unmask weighs the two as Eq. s2 weighs the guidance against Eq. unmask, at any
    image size and mask area. (A mean over the masked pixels instead divides the pull by their count: 3000x
    weaker than a summed Eq. unmask on a 1000-pixel mask, so the edit never moved and the freed region drifted.)
    Targets and masks are (1, 3, H, W) / (1, 1, H, W) per view, at the render size."""

    grow_region = True  # mark the selection's cells occupied at the start (new content may appear)

    def __init__(self, targets: list[Tensor], weight: float = 1.0, reduction: str = "sum"):
        if reduction not in UNMASK_REDUCTIONS:
            raise ValueError(f"unknown reduction {reduction!r}; use one of {', '.join(UNMASK_REDUCTIONS)}")
        self.targets = targets
        self.weight = float(weight)
        self.reduction = reduction

    def target(self, view: int, size: tuple[int, int], device) -> Tensor:
        t = self.targets[view].to(device)
        if tuple(t.shape[-2:]) != tuple(size):
            t = F.interpolate(t, size=size, mode="area")
        return t

    def loss(self, rgb: Tensor, mask: Tensor, view: int, step: int) -> GuidanceResult:
        """Eq. unmask's form on the masked pixels against this view's target (fp32); skipped when not finite.

        grad_norm reports the masked pixels' mean squared error (0 for an empty mask)."""
        tgt = self.target(view, tuple(rgb.shape[-2:]), rgb.device)
        m = mask.float()
        loss = self.weight * unmask_loss(rgb, tgt, m, self.reduction)
        if not bool(torch.isfinite(loss)):
            return GuidanceResult(loss=torch.zeros((), device=rgb.device), skipped=True, t=0, grad_norm=0.0)
        mse = masked_mse(rgb, tgt, m)
        return GuidanceResult(loss=loss, skipped=False, t=0, grad_norm=0.0 if mse is None else float(mse))
