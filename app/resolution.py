"""Dynamic render resolution for the viewport: instant-ngp's controller.

Before any frame has been measured the cost of a ray is unknown, and on a CPU it spans three orders of magnitude
(an opaque trained field stops rays early; a foggy one, e.g. a real capture a few minutes into training, marches every
ray to the far bound of its contracted space): the first frame renders at most FIRST_FRAME_RAYS rays, so a scene opens
with a picture in seconds, and the controller takes over from its measured time. While the camera moves, the render
scale follows the square root of the ratio between the target and
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
FIRST_FRAME_RAYS = 4096  # 64 x 64: on the 70-step fox capture, ~1.5 ms a ray on one shared core


@dataclass
class DynamicResolution:
    """Holds the render scale that keeps a frame near `target_ms`."""

    target_ms: float = 50.0
    scale: float = 0.25
    min_scale: float = MIN_SCALE
    max_scale: float = MAX_SCALE
    band: float = BAND
    measured: bool = False  # a frame's time has been fed to `update`

    def for_view(self, pixels: int | None) -> float:
        """The scale to render a new view of `pixels` pixels at: the current scale, capped to FIRST_FRAME_RAYS rays
        until a frame has been measured (None: the size is not known, no cap)."""
        if not self.measured and pixels:
            cap = math.sqrt(FIRST_FRAME_RAYS / max(int(pixels), 1))
            self.scale = max(self.min_scale, min(self.scale, cap))
        return self.scale

    def update(self, measured_ms: float, at_scale: float | None = None) -> float:
        """Feed the time a frame took (rendered at `at_scale`, default the current scale); return the new scale."""
        if not math.isfinite(measured_ms) or measured_ms <= 0.0:
            return self.scale
        self.measured = True
        base = self.scale if at_scale is None else at_scale
        if abs(measured_ms - self.target_ms) <= self.band * self.target_ms:
            return self.scale
        self.scale = min(self.max_scale, max(self.min_scale, base * math.sqrt(self.target_ms / measured_ms)))
        return self.scale
