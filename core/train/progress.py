"""A terminal progress bar for training: fraction done, steps/s, ETA and the current PSNR.

Redraws in place on a terminal (at most ~8 times a second); on a pipe it prints a line every few
seconds instead, so logs stay readable.
"""
from __future__ import annotations

import sys
import time
from typing import TextIO


def _fmt_time(s: float) -> str:
    s = max(0, int(round(s)))
    return f"{s // 3600}:{s % 3600 // 60:02d}:{s % 60:02d}" if s >= 3600 else f"{s // 60}:{s % 60:02d}"


class ProgressBar:
    """Progress towards `total_steps` and/or `total_seconds` (None = open-ended)."""

    def __init__(self, total_steps: int | None = None, total_seconds: float | None = None,
                 stream: TextIO | None = None, width: int = 24, label: str = "train"):
        self.total_steps, self.total_seconds = total_steps, total_seconds
        self.stream = stream or sys.stderr
        self.width, self.label = width, label
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.start = time.perf_counter()
        self._last_draw = -1e9
        self._start_step: int | None = None
        self.last_line = ""

    def fraction(self, step: int, elapsed: float) -> float | None:
        parts = []
        if self.total_steps:
            parts.append(step / self.total_steps)
        if self.total_seconds:
            parts.append(elapsed / self.total_seconds)
        return min(1.0, max(parts)) if parts else None

    def format(self, step: int, elapsed: float, psnr: float | None = None, loss: float | None = None) -> str:
        """The bar's text for the given state (used by `update`; handy in tests)."""
        if self._start_step is None:
            self._start_step = step
        frac = self.fraction(step, elapsed)
        rate = (step - self._start_step) / elapsed if elapsed > 0 else 0.0
        if frac is None:
            bar, pct, eta = "", "", ""
        else:
            fill = int(round(frac * self.width))
            bar = "[" + "#" * fill + "." * (self.width - fill) + "] "
            pct = f"{100 * frac:3.0f}% "
            eta = f" ETA {_fmt_time(elapsed * (1 - frac) / frac)}" if frac > 0 else " ETA ?"
        total = f"/{self.total_steps}" if self.total_steps else ""
        text = f"{self.label} {bar}{pct}{step}{total} {rate:.1f} it/s {_fmt_time(elapsed)}{eta}"
        if psnr is not None:
            text += f" psnr {psnr:.2f} dB"
        if loss is not None:
            text += f" loss {loss:.4g}"
        return text

    def update(self, step: int, psnr: float | None = None, loss: float | None = None, force: bool = False) -> None:
        """Redraw if enough time has passed (or `force`)."""
        now = time.perf_counter()
        interval = 0.125 if self.tty else 5.0
        if not force and now - self._last_draw < interval:
            return
        self._last_draw = now
        self.last_line = self.format(step, now - self.start, psnr, loss)
        if self.tty:
            self.stream.write("\r" + self.last_line.ljust(100)[:160])
        else:
            self.stream.write(self.last_line + "\n")
        self.stream.flush()

    def close(self, step: int | None = None, psnr: float | None = None) -> None:
        """Draw the final state and end the line."""
        if step is not None:
            self._last_draw = -1e9
            self.update(step, psnr, force=True)
        if self.tty:
            self.stream.write("\n")
            self.stream.flush()
