"""The wall-clock budget of a whole command (`train --seconds S`): loading, training, saving and evaluation.

Training gets what is left after loading, less a reserve for the closing work (checkpoint, version and
the bounded evaluation); the closing evaluation stops at the deadline, and work that would not fit is
skipped and named rather than run past it.
"""
from __future__ import annotations

import math
import time
from collections.abc import Callable

CLOSING_RESERVE = 0.1  # fraction of the budget kept for saving and the closing evaluation
EVAL_SHARE = 0.1  # the closing evaluation's most seconds, as a share of the command's training seconds (issue 18)


class CommandBudget:
    """Seconds since the command started against an optional limit (None = unbounded)."""

    def __init__(self, seconds: float | None, reserve: float = CLOSING_RESERVE,
                 clock: Callable[[], float] = time.perf_counter):
        self.seconds, self.reserve, self.clock = seconds, reserve, clock
        self.start = clock()
        self.skipped: list[str] = []

    @property
    def bounded(self) -> bool:
        return self.seconds is not None

    def elapsed(self) -> float:
        return self.clock() - self.start

    def left(self) -> float:
        """Seconds left (inf when unbounded; never negative)."""
        return math.inf if self.seconds is None else max(0.0, self.seconds - self.elapsed())

    def deadline(self) -> float | None:
        """The clock value at which the budget ends (None when unbounded)."""
        return None if self.seconds is None else self.start + self.seconds

    def training_seconds(self) -> float | None:
        """Seconds training may take now: what is left less the closing reserve (None when unbounded)."""
        if self.seconds is None:
            return None
        return max(0.0, self.left() - self.reserve * self.seconds)

    def evaluation_seconds(self, trained_s: float, share: float = EVAL_SHARE) -> float:
        """Seconds the closing evaluation may take: `share` of the seconds this command trained, within what is
        left of the budget (any budget, or none: the evaluation never outweighs the training it reports on)."""
        return min(self.left(), share * max(0.0, trained_s))

    def fits(self, estimate_s: float) -> bool:
        """Whether work estimated at `estimate_s` seconds ends before the deadline."""
        return estimate_s <= self.left()

    def skip(self, what: str) -> str:
        """Record (and return) a message saying what the budget made the command skip."""
        msg = f"skipped {what}: the --seconds budget ({self.seconds:g} s) has {self.left():.1f} s left"
        self.skipped.append(msg)
        return msg
