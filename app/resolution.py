"""Dynamic render resolution for the viewport: instant-ngp's controller.

Before any frame has been measured the cost of a ray is unknown, and on a CPU it spans three orders of magnitude
(an opaque trained field stops rays early; a foggy one, e.g. a real capture a few minutes into training, marches every
ray to the far bound of its contracted space): the first frame renders at most FIRST_FRAME_RAYS rays, so a scene opens
with a picture in seconds, and the controller takes over from its measured time. While the camera moves, the render
scale follows the square root of the ratio between the target and
the measured frame time (render cost grows with pixel count, i.e. with scale squared), clamped to
[1/16, 1], and it changes only when the measured time leaves a 20% band around the target, so it does
not oscillate. Below the floor it lengthens the marching step instead (`stride`, up to MAX_STRIDE), the one
other cost a moving view can shed: a foggy field's rays cost in proportion to their samples. While the camera
rests the worker refines to full resolution, at the normal step, regardless.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

MIN_SCALE = 1.0 / 16.0
MAX_SCALE = 1.0
BAND = 0.2
# At the 1/16 floor, renders of the fox capture 100 steps into training (17 orbit views of `bench viewport`): the
# step at 2x took 0.60 of the time and differed from the normal step's picture by 35 dB PSNR (median; 31 at worst),
# at 4x 0.38 and 30 dB (24 at worst)
MAX_STRIDE = 4.0
FIRST_FRAME_RAYS = 4096  # 64 x 64: on the 70-step fox capture, ~1.5 ms a ray on one shared core


@dataclass
class DynamicResolution:
    """Holds the render scale that keeps a frame near `target_ms`."""

    target_ms: float = 50.0
    scale: float = 0.25
    min_scale: float = MIN_SCALE
    max_scale: float = MAX_SCALE
    band: float = BAND
    stride: float = 1.0  # the marching step's multiple, over 1 only at the scale floor
    max_stride: float = MAX_STRIDE
    measured: bool = False  # a frame's time has been fed to `update`

    def for_view(self, pixels: int | None) -> float:
        """The scale to render a new view of `pixels` pixels at: the current scale, capped to FIRST_FRAME_RAYS rays
        until a frame has been measured (None: the size is not known, no cap)."""
        if not self.measured and pixels:
            cap = math.sqrt(FIRST_FRAME_RAYS / max(int(pixels), 1))
            self.scale = max(self.min_scale, min(self.scale, cap))
        return self.scale

    def update(self, measured_ms: float, at_scale: float | None = None, at_stride: float | None = None) -> float:
        """Feed the time a frame took (rendered at `at_scale` and `at_stride`, default the current ones); return the
        new scale. A frame's cost goes with its pixels over its step: scale^2 / stride."""
        if not math.isfinite(measured_ms) or measured_ms <= 0.0:
            return self.scale
        self.measured = True
        base = self.scale if at_scale is None else at_scale
        stride = self.stride if at_stride is None else at_stride
        if abs(measured_ms - self.target_ms) <= self.band * self.target_ms:
            return self.scale
        work = base * base / stride * self.target_ms / measured_ms
        self.scale = min(self.max_scale, max(self.min_scale, math.sqrt(work)))
        self.stride = 1.0 if self.scale > self.min_scale else min(self.max_stride, max(1.0, self.scale ** 2 / work))
        return self.scale
