"""Dynamic render resolution for the viewport: instant-ngp's controller.

While the camera moves, the render scale follows the square root of the ratio between the target and
the measured frame time (render cost grows with pixel count, i.e. with scale squared), clamped to
[1/16, 1], and it changes only when the measured time leaves a 20% band around the target, so it does
not oscillate. While the camera rests the worker refines to full resolution regardless.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

MIN_SCALE = 1.0 / 16.0
MAX_SCALE = 1.0
BAND = 0.2


@dataclass
class DynamicResolution:
    """Holds the render scale that keeps a frame near `target_ms`."""

    target_ms: float = 50.0
    scale: float = 0.25
    min_scale: float = MIN_SCALE
    max_scale: float = MAX_SCALE
    band: float = BAND

    def update(self, measured_ms: float, at_scale: float | None = None) -> float:
        """Feed the time a frame took (rendered at `at_scale`, default the current scale); return the new scale."""
        if not math.isfinite(measured_ms) or measured_ms <= 0.0:
            return self.scale
        base = self.scale if at_scale is None else at_scale
        if abs(measured_ms - self.target_ms) <= self.band * self.target_ms:
            return self.scale
        self.scale = min(self.max_scale, max(self.min_scale, base * math.sqrt(self.target_ms / measured_ms)))
        return self.scale
