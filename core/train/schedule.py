"""Learning-rate schedules as a factor of the base rate, driven by training progress in [0, 1].

Progress follows the step count (see training_progress); a wall-clock budget only brings the decay to its end
within the budget's last part, so a run whose steps are slower (a larger image) gets the same rate per step.
"""
from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass
class LRSchedule:
    """kind: 'exp' (geometric decay to final_factor), 'step' (x0.33 at 50/75/90%), or 'const'."""

    kind: str = "exp"
    final_factor: float = 0.1
    warmup: float = 0.0  # fraction of training with a linear ramp from 0.1 to 1
    decay_start: float = 0.0  # fraction of training before the decay begins

    def factor(self, progress: float) -> float:
        """Multiplier of the base learning rate at `progress` in [0, 1] (clamped)."""
        p = min(max(progress, 0.0), 1.0)
        w = 1.0
        if self.warmup > 0 and p < self.warmup:
            w = 0.1 + 0.9 * p / self.warmup
        if self.kind == "const":
            return w
        if self.kind == "exp":
            if p <= self.decay_start:
                return w
            q = (p - self.decay_start) / max(1e-9, 1.0 - self.decay_start)
            return w * math.exp(q * math.log(self.final_factor))
        if self.kind == "step":
            return w * 0.33 ** sum(p >= m for m in (0.5, 0.75, 0.9))
        raise ValueError(f"unknown schedule '{self.kind}' (use exp, step or const)")


def training_progress(step: int, seconds: float, budget_steps: int | None, budget_seconds: float | None,
                      horizon_steps: int, anneal: float) -> float:
    """Progress in [0, 1] of the LR schedule: the step count over the step budget (else `horizon_steps`), brought
    forward in the last `anneal` share of a time budget so the decay ends with it (1.0 = by time throughout).

    Why: keyed to seconds, a size whose steps are slower, or whose early foggy steps last longer, has a lower rate
    at every step count (bench scale, 256 vs 128 px: 2.4x the steps to 25 dB); keyed to steps the time budget
    only caps the run, and its closing share still anneals the rate for the final quality.
    """
    p = step / max(1, budget_steps or horizon_steps)
    if budget_seconds:
        a = min(max(anneal, 1e-9), 1.0)
        p = max(p, (seconds / budget_seconds - (1.0 - a)) / a)
    return min(max(p, 0.0), 1.0)
