"""How long a repaint will take before it starts, and how long is left while it runs.

A step costs the field's render and backward at the edit resolution plus the guidance's step. Before the
start: the field part is a first timed render+backward on this device when the caller has one (the CLI
times one, see RepaintTrainer.time_field_step), else a stored per-pixel figure; the Stable Diffusion part
is `bench sdcost`'s stored figure for the device kind and speed options at 512 px, scaled to the SDS
resolution as a fixed part plus a part per pixel (the UNet reads all its weights whatever the latent size:
256 px measured at 0.30-0.48 of 512 px, not 0.25). Offline guidances cost next to
nothing beyond the render. While running, the time left is the mean of the recent measured steps times
the steps left (the first, warm-up step is left out once there are others).
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import torch

from repaint_nerf.core.repaint.config import RepaintConfig

# Seconds per SDS step at 512 px by (UNet precision, tiny autoencoder, token merging), and the fixed fraction f
# of it that does not shrink with the SDS resolution: s(r) = s512 * (f + (1 - f) * (r / 512)^2). CPU: 2-core
# AMD EPYC (avx512_bf16), SD 1.5 architecture, channels-last UNet and tiny autoencoder, `bench sdcost` on an
# idle machine, one step each: fp32 + VAE 26.9 s, bf16 + tiny 5.78 s, + token merging 4.74 s; bf16 + tiny at
# 256 px 1.28 s -> f 0.02 (token merging is off at 256 px, sd_tome.MIN_TOKENS, so its f makes 256 px cost what
# bf16 + tiny costs there). bf16 + VAE and fp32 + tiny are earlier shared-machine ratios scaled to the idle 26.9 s
# baseline; the f of the VAE rows are the earlier session's.
SD_STEP_SECONDS_512 = {
    "cpu": {("fp32", False, False): (26.9, 0.23), ("bf16", False, False): (19.9, 0.23),
            ("fp32", True, False): (16.1, 0.31), ("bf16", True, False): (5.78, 0.02), ("bf16", True, True): (4.74, 0.03)},
}
SD_REFERENCE_RESOLUTION = 512
# Field step (render + backward + update) per megapixel of rays on a CPU: the README's stage-1 figure on this
# 2-core CPU (17 steps/s at 4096 rays, idle machine) -> 1 / (17 * 4096e-6) = 14.4 s/Mpx. Used only where no
# step was timed on the device (the editor before Repaint); the CLI times one.
FIELD_SECONDS_PER_MPIX = {"cpu": 14.4}


@dataclass
class Estimate:
    """A repaint's expected duration and how each part was derived."""

    steps: int
    field_seconds: float | None     # per step
    guidance_seconds: float | None  # per step
    how: str

    @property
    def step_seconds(self) -> float | None:
        if self.field_seconds is None or self.guidance_seconds is None:
            return None
        return self.field_seconds + self.guidance_seconds

    @property
    def total_seconds(self) -> float | None:
        s = self.step_seconds
        return None if s is None else s * self.steps

    def describe(self) -> str:
        """One line: total, per step and where the figures come from."""
        if self.total_seconds is None:
            return f"estimated time: unknown before the first steps ({self.how})"
        return (f"estimated time: {format_duration(self.total_seconds)} ({self.steps} steps x "
                f"{self.step_seconds:.2g} s; {self.how})")


def format_duration(seconds: float | None) -> str:
    """'45 s', '12 min', '3 h 20 min', '2 d 5 h'; '?' for None."""
    if seconds is None or seconds != seconds:
        return "?"
    s = max(0.0, float(seconds))
    if s < 90:
        return f"{s:.0f} s"
    if s < 90 * 60:
        return f"{s / 60:.0f} min"
    if s < 48 * 3600:
        return f"{int(s // 3600)} h {int(s % 3600 // 60)} min"
    return f"{int(s // 86400)} d {int(s % 86400 // 3600)} h"


def _device_kind(device: torch.device | str) -> str:
    return torch.device(device).type


def sd_step_seconds(device: torch.device | str, unet_precision: str = "auto", tiny_autoencoder: bool = False,
                    sds_resolution: int | None = None,
                    token_merging: float = RepaintConfig.sd_token_merging) -> tuple[float | None, str]:
    """Stored seconds per SDS step for the device kind and options, scaled by (sds_resolution / 512)^2.

    Token merging was measured with the bf16 UNet and the tiny autoencoder; with other options the figure
    without it is used (an upper bound)."""
    from repaint_nerf.core.models.sd_speed import unet_dtype

    dev = torch.device(device)
    table = SD_STEP_SECONDS_512.get(_device_kind(dev))
    if table is None:
        return None, f"no stored Stable Diffusion figure for {dev.type}"
    precision = {torch.float32: "fp32", torch.bfloat16: "bf16", torch.float16: "fp16"}[unet_dtype(unet_precision, dev)]
    tome = token_merging > 0
    entry = table.get((precision, bool(tiny_autoencoder), tome)) or table.get((precision, bool(tiny_autoencoder), False))
    if entry is None:
        return None, f"no stored Stable Diffusion figure for {dev.type} {precision}"
    tome_note = "" if not tome else (", token merging" if (precision, bool(tiny_autoencoder), True) in table
                                     else ", token merging not measured with these options: the figure without it")
    base, fixed = entry
    res = sds_resolution or SD_REFERENCE_RESOLUTION
    scale = fixed + (1.0 - fixed) * (res / SD_REFERENCE_RESOLUTION) ** 2
    enc = "tiny autoencoder" if tiny_autoencoder else "VAE"
    return base * scale, (f"SD {base:.3g} s/step at 512 px from bench sdcost ({dev.type}, {precision} UNet, {enc}"
                          f"{tome_note}), x {scale:.2f} at {res} px")


def estimate_repaint(kind: str, steps: int, render_size: tuple[int, int], device: torch.device | str,
                     field_step_seconds: float | None = None, unet_precision: str = "auto",
                     tiny_autoencoder: bool = False, sds_resolution: int | None = None,
                     token_merging: float = RepaintConfig.sd_token_merging) -> Estimate:
    """Expected duration of `steps` repaint steps with guidance `kind` at a render of `render_size` (h, w).

    `field_step_seconds`: a measured render+backward on this device (else the stored per-pixel figure).
    """
    dev = torch.device(device)
    notes = []
    if field_step_seconds is not None:
        field = float(field_step_seconds)
        notes.append(f"field {field:.2g} s timed on this device")
    else:
        per_mpix = FIELD_SECONDS_PER_MPIX.get(dev.type)
        mpix = render_size[0] * render_size[1] / 1e6
        field = None if per_mpix is None else per_mpix * mpix
        notes.append(f"field {per_mpix} s/Mpx stored x {mpix:.3g} Mpx" if per_mpix is not None
                     else f"no stored field figure for {dev.type}")
    if kind != "sd":  # offline and analytic guidances: a few pixel operations beside the render
        guidance = 0.0
    else:
        guidance, note = sd_step_seconds(dev, unet_precision, tiny_autoencoder, sds_resolution, token_merging)
        notes.append(note)
    return Estimate(int(steps), field, guidance, "; ".join(notes))


class Progress:
    """Time left from measured step durations (recent mean x steps left), the prior estimate until then."""

    def __init__(self, total_steps: int, prior_step_seconds: float | None = None, window: int = 20):
        self.total = int(total_steps)
        self.prior = prior_step_seconds
        self.recent: deque[float] = deque(maxlen=window)
        self.first: float | None = None

    def update(self, seconds: float) -> None:
        """Record one step's duration (the first one is kept apart: it includes warm-up)."""
        if self.first is None:
            self.first = float(seconds)
        else:
            self.recent.append(float(seconds))

    def step_seconds(self) -> float | None:
        if self.recent:
            return sum(self.recent) / len(self.recent)
        return self.first if self.first is not None else self.prior

    def seconds_left(self, step: int) -> float | None:
        """Seconds until `total_steps` after `step` steps are done."""
        s = self.step_seconds()
        return None if s is None else s * max(0, self.total - int(step))


def estimate_before_start(kind: str, steps: int, width: int, height: int, device: torch.device | str,
                          resolution: int | None = None, **sd_options) -> Estimate:
    """The estimate for a scene's training image size, at the edit resolution the trainer would pick (stored
    figures only: nothing is timed). `sd_options`: unet_precision, tiny_autoencoder, sds_resolution,
    token_merging."""
    from repaint_nerf.core.repaint.trainer import default_resolution

    dev = torch.device(device)
    res = resolution or default_resolution(width, height, dev)
    scale = min(1.0, res / max(width, height))
    size = (max(1, round(height * scale)), max(1, round(width * scale)))
    return estimate_repaint(kind, steps, size, dev, **sd_options)
