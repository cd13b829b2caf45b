"""The Adan optimiser (Xie et al. 2022) as the paper's stage 2 uses it, with non-finite steps skipped.

The update itself is pytorch-optimizer's Adan (a maintained implementation), run per parameter
(no foreach/fused kernels); this module adds the project's rules: a step whose gradients are not all
finite is skipped and counted, per-group learning rates (official: 10x on the grid) scale with one
schedule factor, and the defaults of stable-dreamfusion (eps 1e-8, weight decay 2e-5, max grad norm 5).
"""
from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping

import torch
from pytorch_optimizer.optimizer.adan import Adan as _Adan

PAPER_LR = 1e-3             # the paper: 1e-3 decaying to 1e-4 (LRSchedule('exp', final_factor=0.1))
OFFICIAL_LR = 5e-3          # the official code: 5e-3 ...
OFFICIAL_MULTIPLIERS = {"grid": 10.0}   # ... with 10x on the hash grid


def grads_finite(params: Iterable[torch.Tensor]) -> bool:
    """True when every present gradient is finite (one device sync for all of them)."""
    flags = [torch.isfinite(p.grad).all() for p in params if p.grad is not None]
    return bool(torch.stack(flags).all()) if flags else True


def param_groups(groups: Mapping[str, Iterable[torch.nn.Parameter]], lr: float,
                 multipliers: Mapping[str, float] | None = None) -> list[dict]:
    """Optimiser groups from named parameter lists (e.g. NGPField.parameter_groups()), lr x multiplier each."""
    multipliers = multipliers or {}
    out = []
    for name, params in groups.items():
        params = [p for p in params if p.requires_grad]
        if params:
            out.append({"params": params, "lr": lr * multipliers.get(name, 1.0), "name": name})
    return out


class Adan(_Adan):
    """Adan with skipped non-finite steps (`skipped_steps` counts them) and a schedule factor on base rates.

    no_prox=True applies weight decay decoupled (p *= 1 - lr*wd before the update); False uses the
    proximal form (p /= 1 + lr*wd after it). They differ by O((lr*wd)^2).
    """

    def __init__(self, params, lr: float = PAPER_LR, betas: tuple[float, float, float] = (0.98, 0.92, 0.99),
                 eps: float = 1e-8, weight_decay: float = 2e-5, max_grad_norm: float = 5.0,
                 no_prox: bool = True):
        super().__init__(params, lr=lr, betas=betas, weight_decay=weight_decay, weight_decouple=no_prox,
                         max_grad_norm=max_grad_norm, foreach=False, eps=eps)
        for group in self.param_groups:
            group.setdefault("base_lr", group["lr"])
        self.skipped_steps = 0
        self.applied_steps = 0

    def _all_params(self) -> list[torch.Tensor]:
        return [p for g in self.param_groups for p in g["params"]]

    def grads_finite(self) -> bool:
        """True when the next step would be applied (every gradient finite)."""
        return grads_finite(self._all_params())

    def set_lr_factor(self, factor: float) -> None:
        """Set each group's lr to its base lr times `factor` (e.g. LRSchedule.factor(progress))."""
        for group in self.param_groups:
            group["lr"] = group["base_lr"] * factor

    @torch.no_grad()
    def step(self, closure: Callable[[], torch.Tensor] | None = None):
        """One Adan update, or none (counted in `skipped_steps`) when a gradient is NaN or infinite."""
        loss = None
        if closure is not None:
            with torch.enable_grad():
                loss = closure()
        if not self.grads_finite():
            self.skipped_steps += 1
            return loss
        super().step()
        self.applied_steps += 1
        return loss
