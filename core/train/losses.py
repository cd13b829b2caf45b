"""Stage-1 losses of the paper: colour (Eq. color), feature, depth and their sum (Eq. s1).

Each loss is a mean over rays (the paper's sums up to a constant, which keeps the lambdas independent
of the batch size).
"""
from __future__ import annotations

import torch
import torch.nn.functional as F


def color_loss(pred: torch.Tensor, target: torch.Tensor, kind: str = "mse", delta: float = 0.1) -> torch.Tensor:
    """Paper Eq. color: squared error between rendered and true pixel colours (or Huber with `delta`)."""
    if kind == "mse":
        return F.mse_loss(pred, target)
    if kind == "huber":
        return F.huber_loss(pred, target, delta=delta)
    raise ValueError(f"unknown colour loss '{kind}' (use 'mse' or 'huber')")


def feature_loss(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Paper Eq. feature: squared L2 distance of rendered features (R, D) to the teacher's (R, D), per element."""
    return F.mse_loss(pred.float(), target.float())


def depth_loss(pred_z: torch.Tensor, target_z: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """Paper Eq. depth: squared error of rendered z-depth to the prior where `valid` (field units)."""
    n = valid.sum()
    diff = torch.where(valid, pred_z - target_z.nan_to_num(0.0), torch.zeros_like(pred_z))
    return (diff ** 2).sum() / n.clamp(min=1)


def stage1_loss(color: torch.Tensor, feature: torch.Tensor | None = None, depth: torch.Tensor | None = None,
                lambda_feature: float = 0.0, lambda_depth: float = 0.0) -> torch.Tensor:
    """Paper Eq. s1: L = L_color + lambda_feature * L_feature + lambda_depth * L_depth (absent parts skipped)."""
    total = color
    if feature is not None and lambda_feature:
        total = total + lambda_feature * feature
    if depth is not None and lambda_depth:
        total = total + lambda_depth * depth
    return total
