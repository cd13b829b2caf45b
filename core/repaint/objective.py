"""The stage-2 objective of the paper: the unmask loss (Eq. unmask) and the repaint loss (Eq. s2).

The guidance term (Eq. SDS) comes from a Guidance backend and the CLIP term (Eq. clip) from
core.repaint.clip_loss; this module weighs them together. Plain functions on tensors, so each is
tested against its written formula.
"""
from __future__ import annotations

from torch import Tensor

from repaint_nerf.core.repaint.config import UNMASK_REDUCTIONS


def unmask_loss(rgb: Tensor, target: Tensor, keep: Tensor, reduction: str = "sum") -> Tensor:
    """Paper Eq. unmask: squared error between render and original image on the kept (unmasked) pixels.

    rgb, target (B, 3, H, W); keep (B|1, 1, H, W) is 1(mask < 0.5), less any margin the caller frees.
    'sum' adds over rays and channels as the paper writes it; 'mean' averages over every value of the
    image with the masked pixels zeroed, as the official code does (so it is the sum / (B * 3 * H * W)).
    """
    sq = ((rgb.float() - target.float()) * keep) ** 2
    if reduction == "sum":
        return sq.sum()
    if reduction == "mean":
        return sq.mean()
    raise ValueError(f"unknown unmask reduction {reduction!r}; use one of {', '.join(UNMASK_REDUCTIONS)}")


def masked_mse(rgb: Tensor, target: Tensor, weight: Tensor) -> Tensor | None:
    """Mean squared error per channel over the pixels where `weight` (B|1, 1, H, W) is 1; None when there are none.

    The per-pixel figure behind Eq. unmask (weight = keep) and the offline targets (weight = mask), without a
    graph: what a status line or a PSNR reads, at any image size and reduction."""
    n = 3 * float(weight.float().sum()) * (rgb.shape[0] if weight.shape[0] == 1 else 1)
    if n <= 0:
        return None
    return (((rgb.detach().float() - target.float()) * weight.float()) ** 2).sum() / n


def unmask_weight(lambda_unmask: float, progress: float, ramp: float = 0.0, start: float = 1.0) -> float:
    """Eq. s2's lambda_unmask at `progress` (step / steps, 0..1) of the edit: it rises linearly from
    start x lambda_unmask to lambda_unmask over the first `ramp` of the steps, then stays there (ramp 0: constant).

    lambda(p) = lambda_unmask * (start + (1 - start) * min(1, p / ramp)).
    """
    if ramp <= 0:
        return float(lambda_unmask)
    return float(lambda_unmask) * (start + (1.0 - start) * min(1.0, max(0.0, progress) / ramp))


def stage2_loss(guidance: Tensor, unmask: Tensor, lambda_unmask: float, clip: Tensor | None = None,
                lambda_clip: float = 0.0) -> Tensor:
    """Paper Eq. s2 added to the guidance: L = L_SDS + lambda_unmask * L_unmask + lambda_clip * L_clip.

    `guidance` is the backend's loss (its gradient is the SDS gradient); `clip` is None when not used.
    """
    total = guidance.float() + lambda_unmask * unmask.float().to(guidance.device)
    if clip is not None:
        total = total + lambda_clip * clip.float().to(guidance.device)
    return total
