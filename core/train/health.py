"""Training health checks shared by both stages: loss-spike detection (reported, not acted on).

Non-finite steps are skipped where the optimiser steps (stage1.Stage1Trainer.step, train.adan.Adan);
this module only notices losses that are finite but far above their recent level, so a run's report
can say when and how often it was unstable.
"""
from __future__ import annotations

import math


class SpikeDetector:
    """Flags a loss more than `factor` times its running level (an EMA of log loss) after `warmup` steps."""

    def __init__(self, factor: float = 10.0, beta: float = 0.95, warmup: int = 10):
        self.log_factor = math.log(factor)
        self.beta, self.warmup = beta, warmup
        self.level: float | None = None
        self.seen = 0
        self.spikes = 0

    def update(self, loss: float) -> bool:
        """Record one step's loss; True when it is a spike. Non-finite or non-positive losses are ignored."""
        if not math.isfinite(loss) or loss <= 0:
            return False
        x = math.log(loss)
        spike = self.level is not None and self.seen >= self.warmup and x - self.level > self.log_factor
        if spike:
            self.spikes += 1
            x = self.level + self.log_factor  # a spike moves the level no more than a just-tolerated loss would
        self.level = x if self.level is None else self.beta * self.level + (1 - self.beta) * x
        self.seen += 1
        return spike
