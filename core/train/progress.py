"""A terminal progress bar for training on tqdm: fraction done, steps/s, elapsed, ETA and the current PSNR / loss.

tqdm (maintained, handles terminal widths, in-place redraws and notebooks) formats and draws the bar; on a pipe a
plain line is printed every few seconds instead, so logs stay readable. Progress runs by steps (`total_steps`) or
by time (`total_seconds`, then the bar and ETA follow the clock and the step rate is shown beside them).
"""
from __future__ import annotations

import sys
import time
from typing import TextIO

from tqdm import tqdm

BAR = "{desc} {percentage:3.0f}%|{bar:24}| "


class ProgressBar:
    """Progress towards `total_steps` and/or `total_seconds` (None = open-ended)."""

    def __init__(self, total_steps: int | None = None, total_seconds: float | None = None,
                 stream: TextIO | None = None, width: int = 24, label: str = "train"):
        self.total_steps, self.total_seconds = total_steps, total_seconds
        self.stream = stream or sys.stderr
        self.label = label
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.start = time.perf_counter()
        self._last_draw = -1e9
        self._start_step: int | None = None
        self._bar: tqdm | None = None
        self.last_line = ""

    def fraction(self, step: int, elapsed: float) -> float | None:
        parts = []
        if self.total_steps:
            parts.append(step / self.total_steps)
        if self.total_seconds:
            parts.append(elapsed / self.total_seconds)
        return min(1.0, max(parts)) if parts else None

    def format(self, step: int, elapsed: float, psnr: float | None = None, loss: float | None = None) -> str:
        """The bar's text for the given state (tqdm's meter; used by `update`, handy in tests)."""
        if self._start_step is None:
            self._start_step = step
        frac = self.fraction(step, elapsed)
        rate = (step - self._start_step) / elapsed if elapsed > 0 else 0.0
        total = f"/{self.total_steps}" if self.total_steps else ""
        eta = "?" if not frac else tqdm.format_interval(elapsed * (1 - frac) / frac)
        post = f"{step}{total} {rate:.1f} it/s {tqdm.format_interval(elapsed)} ETA {eta}"
        if psnr is not None:
            post += f" psnr {psnr:.2f} dB"
        if loss is not None:
            post += f" loss {loss:.4g}"
        if frac is None:
            return f"{self.label} {post}"
        return tqdm.format_meter(int(round(1000 * frac)), 1000, elapsed, prefix=self.label, ascii=not self.tty,
                                 bar_format=BAR + post.replace("{", "{{").replace("}", "}}"))

    def update(self, step: int, psnr: float | None = None, loss: float | None = None, force: bool = False) -> None:
        """Redraw if enough time has passed (or `force`)."""
        now = time.perf_counter()
        interval = 0.125 if self.tty else 5.0
        if not force and now - self._last_draw < interval:
            return
        self._last_draw = now
        self.last_line = self.format(step, now - self.start, psnr, loss)
        if self.tty:  # tqdm redraws the line in place, fitted to the terminal
            if self._bar is None:
                self._bar = tqdm(file=self.stream, bar_format="{desc}", leave=True, dynamic_ncols=True)
            self._bar.set_description_str(self.last_line)
        else:
            self.stream.write(self.last_line + "\n")
            self.stream.flush()

    def close(self, step: int | None = None, psnr: float | None = None) -> None:
        """Draw the final state and end the line."""
        if step is not None:
            self._last_draw = -1e9
            self.update(step, psnr, force=True)
        if self._bar is not None:
            self._bar.close()
            self._bar = None
