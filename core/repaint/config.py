"""RepaintConfig: the one set of stage-2 defaults, used by the CLI, the editor and the benchmarks alike.

Light to import (no torch), so the CLI's flags and the editor's fields can default from it.
"""
from __future__ import annotations

from dataclasses import dataclass

UNMASK_REDUCTIONS = ("mean", "sum")
OPTIMIZERS = ("paper", "official")


@dataclass
class RepaintConfig:
    """Stage-2 settings. The paper runs 10000 steps at 400x400 on a GPU; our default of 300 steps at
    <= 128 px is what a CPU finishes in minutes (offline and analytic edits converge in that)."""

    steps: int = 300
    resolution: int | None = None  # render long side; None = training size capped at 128 (CPU) / 400 (CUDA)
    lambda_unmask: float = 100.0  # paper Eq. s2 (official code: 100)
    # Eq. unmask reduced as the official code does ("mean" over the kept pixels) or as the paper writes it
    # ("sum" over rays): at lambda 100 the mean is ~40x weaker per pixel than the guidance (bench edit).
    unmask_reduction: str = "mean"
    # Weight of the CLIP background loss (paper Eq. clip); None = the guidance's own default
    # (core.repaint.registry.clip_weight: the official 0.01 with Stable Diffusion, else 0). 0 loads no CLIP.
    lambda_clip: float | None = None
    optimizer: str = "paper"  # 'paper': Adan 1e-3 decaying to 1e-4; 'official': 5e-3, 10x on the grid, constant
    lr: float | None = None  # overrides the preset's base rate
    mask_dilation: int = 0  # pixels added around the mask (guidance and unmask loss both see the larger mask)
    unmask_margin: int = 1  # pixels around the mask the unmask loss leaves free (its soft edges may change)
    snapshot_every: int = 25  # steps between preview snapshots (0 = none)
    snapshot_view: int = 0
    seed: int = 0
    max_samples: int = 512
    t_threshold: float = 1e-3
    perturb: bool = True
    grow_region: bool = True  # mark the selection's 3D cells occupied at the start
    region_resolution: int = 64
    recolor_mode: str = "shading"
    remove_clear_weight: float = 10.0
    # Measurement only (bench edit's second ablation): the analytic target outside the mask moves this far
    # toward a flat tint, as a diffusion model also repaints surroundings it was not asked to change; the
    # unmask loss (paper Eq. unmask) is what holds them. 0 = the true edited views.
    analytic_drift: float = 0.0
    # Stable Diffusion step cost (bench sdcost figures in core.repaint.estimate):
    # the gradient-free UNet's precision: 'auto' = fp16 on CUDA, bf16 on a CPU with native bf16, else fp32.
    sd_unet_precision: str = "auto"
    # a TAESD-style tiny autoencoder (local folder or cached id, e.g. madebyollin/taesd) replacing the VAE
    # encoder and its backward; None keeps the VAE (exact latents, the costliest part of a CPU step).
    sd_tiny_autoencoder: str | None = None
    # UNet weights stored channels-last (NHWC): oneDNN convolutions skip layout reorders (bench sdcost: a
    # bf16 + tiny-autoencoder step 1.12x-1.17x faster on the CPU); False keeps PyTorch's default layout.
    sd_channels_last: bool = True
    # the side SD sees the render at; None = the model's own (512 for SD 1.5 / 2-base). 256 costs ~1/4 but
    # SD draws less well below its training resolution.
    sds_resolution: int | None = None
    # SD's timestep draw: 'uniform' on [0.02, 0.98] T (official), or 'annealed': the upper bound falls to
    # 0.5 T over the run (threestudio's schedule; meant to need fewer steps, not measured here: no real weights)
    t_schedule: str = "uniform"
