"""Density activations that cannot overflow: a truncated exp with clamped gradient, and softplus."""
from __future__ import annotations

import torch

TRUNC = 15.0  # exp(15) ~ 3.3e6: denser than any scene needs, far from float32 overflow


class _TruncExp(torch.autograd.Function):
    """exp(min(x, 15)) forward; backward g * exp(clamp(x, -15, 15)) (instant-ngp's trunc_exp, also capped forward)."""

    @staticmethod
    def forward(ctx, x):
        ctx.save_for_backward(x)
        return torch.exp(x.clamp(max=TRUNC))

    @staticmethod
    def backward(ctx, g):
        (x,) = ctx.saved_tensors
        return g * torch.exp(x.clamp(-TRUNC, TRUNC))


def trunc_exp(x: torch.Tensor) -> torch.Tensor:
    """Truncated exponential: finite value and gradient for any finite input."""
    return _TruncExp.apply(x)


def softplus_density(x: torch.Tensor) -> torch.Tensor:
    """softplus(x - 1) (the shift makes a zero-initialised field start nearly transparent); never overflows."""
    return torch.nn.functional.softplus(x - 1.0)


ACTIVATIONS = {"trunc_exp": trunc_exp, "softplus": softplus_density}


def density_activation(name: str):
    """The activation called `name` (trunc_exp or softplus)."""
    from repaint_nerf.core.errors import UserError

    if name not in ACTIVATIONS:
        raise UserError(f"unknown density activation '{name}'", hint=f"use one of {sorted(ACTIVATIONS)}")
    return ACTIVATIONS[name]
