"""The Guidance protocol (docs/CONTRACTS.md) and the score-distillation pieces its backends share.

A backend turns a render into a loss whose gradient is w(t) (eps_hat - eps) (paper Eq. SDS). The loss
is built in the AMP-safe form, 0.5 * ||z - stopgrad(z - g)||^2, so that d loss / d z == g exactly and
the gradient flows through a grad scaler like any other loss.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, TypedDict, runtime_checkable

import torch
import torch.nn.functional as F
from torch import Tensor


class GuidanceResult(TypedDict):
    loss: Tensor        # fp32 scalar; a constant 0 without gradient when skipped
    skipped: bool       # the guidance gradient was non-finite: the trainer must not step
    t: int              # the sampled timestep
    grad_norm: float    # norm of the guidance gradient after clipping (0 when skipped)


@runtime_checkable
class Guidance(Protocol):
    """What the repaint trainer calls once per step.

    `loss` is required. `grow_region` and `field_loss` are optional extras with the defaults below: a backend
    that subclasses Guidance inherits them, and the trainer wraps any other object with `loss` in
    `as_guidance`, so it never has to ask which extras an object has.
    """

    # Mark the selection's 3D cells occupied at the start, so new content can grow there (remove: False).
    grow_region: bool = True

    def loss(self, rgb: Tensor, mask: Tensor, view: int, step: int) -> GuidanceResult:
        """rgb (1,3,H,W) in [0,1] with grad, mask (1,1,H,W); returns the guidance loss and its stats."""
        ...

    def field_loss(self, field, step: int) -> Tensor | None:
        """An extra loss on the field itself (remove: the region's density), or None (the default: none)."""
        return None


EXTRAS = ("grow_region", "field_loss")  # the optional members of Guidance, with the defaults above


class _LossOnly(Guidance):
    """A duck-typed guidance with only `loss`, given the protocol's defaults for the extras."""

    def __init__(self, inner) -> None:
        self.inner = inner
        self.loss = inner.loss


def as_guidance(obj) -> Guidance:
    """`obj` itself when it has every Guidance member, else wrapped so the optional extras take their defaults."""
    if isinstance(obj, Guidance):
        return obj
    if not callable(getattr(obj, "loss", None)):
        raise TypeError("guidance must have loss(rgb, mask, view, step)")
    return _LossOnly(obj)


T_SCHEDULES = ("uniform", "annealed")
ANNEAL_TO = 0.5  # the annealed upper bound's end, as a fraction of T (threestudio's max_step_percent 0.98 -> 0.5)


@dataclass
class TimestepSampler:
    """t ~ U{floor(lo*T) .. floor(hi*T)} (official: 20..980 of 1000) and w(t) = 1 - alpha_bar_t.

    schedule 'annealed': the upper bound falls linearly from hi to max(lo, ANNEAL_TO) over the run (progress
    0 -> 1), so late steps refine detail at low noise instead of redrawing coarse shapes at high noise.
    """

    alphas_cumprod: Tensor
    t_range: tuple[float, float] = (0.02, 0.98)
    generator: torch.Generator | None = None
    schedule: str = "uniform"

    def __post_init__(self) -> None:
        n = len(self.alphas_cumprod)
        lo, hi = self.t_range
        if not 0.0 <= lo <= hi <= 1.0:
            raise ValueError(f"t_range must satisfy 0 <= lo <= hi <= 1, got {self.t_range}")
        self.max_step = min(int(n * hi), n - 1)
        self.min_step = min(int(n * lo), self.max_step)  # lo = 1.0 would start past the last timestep
        if self.schedule not in T_SCHEDULES:
            raise ValueError(f"unknown timestep schedule {self.schedule!r}; use one of {T_SCHEDULES}")
        self.anneal_end = max(self.min_step, min(int(n * ANNEAL_TO), self.max_step))

    def upper(self, progress: float = 0.0) -> int:
        """The largest timestep drawn at `progress` (0..1) of the run."""
        if self.schedule == "uniform":
            return self.max_step
        p = min(max(float(progress), 0.0), 1.0)
        return int(round(self.max_step + p * (self.anneal_end - self.max_step)))

    def sample(self, progress: float = 0.0) -> int:
        return int(torch.randint(self.min_step, self.upper(progress) + 1, (1,), generator=self.generator).item())

    def weight(self, t: int) -> float:
        return float(1.0 - self.alphas_cumprod[t])


def clip_gradient(grad: Tensor, clip_value: float | None = None, clip_norm: float | None = None) -> Tensor:
    """nan_to_num, then an optional element-wise clip and an optional global-norm clip."""
    grad = torch.nan_to_num(grad, nan=0.0, posinf=0.0, neginf=0.0)
    if clip_value is not None:
        grad = grad.clamp(-clip_value, clip_value)
    if clip_norm is not None:
        norm = grad.norm()
        if norm > clip_norm:
            grad = grad * (clip_norm / (norm + 1e-12))
    return grad


def distillation_loss(z: Tensor, grad: Tensor, t: int, clip_value: float | None = None,
                      clip_norm: float | None = None) -> GuidanceResult:
    """The SDS loss on `z` (latents or pixels, with graph) for a guidance gradient `grad` (no graph).

    A non-finite `grad` gives skipped=True and a constant zero loss; otherwise the loss is
    0.5 * sum((z - stopgrad(z - g))^2) in fp32, whose gradient with respect to z is g.
    """
    grad = grad.detach().float()
    if not bool(torch.isfinite(grad).all()):
        return GuidanceResult(loss=torch.zeros((), device=z.device, dtype=torch.float32), skipped=True,
                              t=t, grad_norm=0.0)
    grad = clip_gradient(grad, clip_value, clip_norm)
    z32 = z.float()
    target = (z32 - grad).detach()
    loss = 0.5 * F.mse_loss(z32, target, reduction="sum")
    if not bool(torch.isfinite(loss)):  # a non-finite render: nothing sane to apply
        return GuidanceResult(loss=torch.zeros((), device=z.device, dtype=torch.float32), skipped=True,
                              t=t, grad_norm=0.0)
    return GuidanceResult(loss=loss, skipped=False, t=t, grad_norm=float(grad.norm()))
