"""Learning-rate schedules as a factor of the base rate, driven by training progress in [0, 1].

Progress is steps/total_steps or seconds/total_seconds (whichever is further along), so a run bounded
by wall-clock time decays its learning rate too.
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
