"""RepaintConfig: the one set of stage-2 defaults, used by the CLI, the editor and the benchmarks alike.

Light to import (no torch), so the CLI's flags and the editor's fields can default from it.
"""
from __future__ import annotations

from dataclasses import dataclass

UNMASK_REDUCTIONS = ("sum", "mean")  # paper Eq. unmask as written; as the official code reduces it
OPTIMIZERS = ("paper", "official")


@dataclass
class RepaintConfig:
    """Stage-2 settings. The paper runs 10000 steps at 400x400 on a GPU; our default of 600 steps at
    <= 128 px is what a small object's edit needs under the unmask weight (below); offline and analytic edits
    take minutes on a CPU, and the editor and `repaint` show the estimated time before they start."""

    steps: int = 600
    resolution: int | None = None  # render long side; None = training size capped at 128 (CPU) / 400 (CUDA)
    # Paper Eq. s2's weight on Eq. unmask, reduced as the paper writes it ("sum" over rays and channels) or as
    # the official code does ("mean" over every value of the image, masked pixels zeroed: the sum / 3HW, so
    # mean at 100 is sum at 100/3HW); objective.unmask_loss. The default holds the rest of the scene under a
    # guidance that repaints it and still lets the edit through in the default steps (the paper: a larger
    # weight slows the edit). bench edit "drift" (drifting guidance, patch selection, 300 steps), sum at 10 -> 5,
    # two edit seeds: demo 48 px (patch IoU 0.89) masked 21.3 / 22.4 -> 25.3 / 26.3 dB, unmasked drop
    # -0.49 / -0.57 -> -0.06 / +0.12 dB; bread 64 px (IoU 0.93) masked 31.0 -> 31.0 dB, drop -1.5 -> -0.7 dB.
    # At 3 demo's rest drops 0.77 dB; at 10 demo needs 600 steps for 25.3 dB. Lemon 64 px (IoU 0.79) is
    # slower: masked 18.5 -> 20.1 dB at 300 steps (drop -0.45 -> +0.40 dB). At 600 steps (constant weight) all
    # three met the goal: demo 26.6 dB (drop -0.20), bread 31.8 (-0.90), lemon 25.4 (+0.41).
    # The old default, a mean at 100, dropped the rest 8.4 dB (demo 32 px, 80 steps).
    lambda_unmask: float = 5.0
    # The weight rises linearly from unmask_ramp_start x lambda_unmask at the first step to lambda_unmask at
    # unmask_ramp x steps and stays there (objective.unmask_weight; unmask_ramp 0 = constant, the paper's).
    # Why: the weight is what slows the edit (the paper's Fig. lambda), and on a small object most of all: the
    # colour head and grid are shared with the rest, whose pixels outside the mask (98.6% of lemon 64 px's
    # image) carry the guidance-vs-unmask tug of war that sets Adan's per-parameter step, so the edit inside
    # gets a small share (lemon's masked error at 300 steps is a uniform hue bias, 20.3 -> 25.8 dB without it).
    # A weak weight first lets the edit move, the full weight after pulls the rest back. bench edit drift case,
    # 300 steps, current patch selection, constant 5 -> this ramp: demo 48 px (IoU 0.93) masked 26.13 -> 26.78
    # dB, drop 0.01 -> -0.01 dB; bread 64 px (IoU 0.94) 30.93 -> 31.20, drop -0.93 -> -0.78; lemon 64 px
    # (IoU 0.90) 20.42 -> 23.99, drop 0.46 -> 0.50 (seed 1: 22.81, 0.46), still short of 25 dB. Rejected on
    # lemon: lr x2 / x4 (20.6 dB, drop 0.52 / 22.3, 1.16), colour head lr x5 / x10 (23.5, 0.57 / 19.3, 0.69),
    # grid x4 (19.4, 1.35), a ramp over 0.3 of the steps (23.4, 0.33), to a weight of 10 (21.7, -0.36).
    # With this ramp at 600 steps all three meet the goal: lemon 27.09 dB, drop 0.47; bread 32.33, -0.81; demo
    # 27.35, -0.14. So the default steps are 600 (300 before): an SD step costs 5-20 s on this CPU
    # (core.repaint.estimate), 50 min an edit with the tiny autoencoder at 512 px, 15 min at 256 px, 3.4 h with
    # the VAE; on a GPU, minutes.
    unmask_ramp: float = 0.5
    unmask_ramp_start: float = 0.2
    unmask_reduction: str = "sum"
    lambda_clip: float | None = None
    # Adan decaying lr x 0.1^(step / steps); 'paper': base 1e-3 (to 1e-4); 'official': 5e-3 with 10x on the grid,
    # which converges within the few hundred steps a CPU affords (the paper runs 10000)
    optimizer: str = "official"
    lr: float | None = None  # overrides the preset's base rate
    mask_dilation: int = 0  # pixels added around the mask (guidance and unmask loss both see the larger mask)
    # Pixels around the (dilated) mask that Eq. unmask leaves free, so the object's soft, anti-aliased edge
    # may change with it; 0 is the paper's and official code's 1(mask < 0.5) exactly.
    unmask_margin: int = 1
    snapshot_every: int = 25  # steps between preview snapshots (0 = none)
    snapshot_view: int = 0
    seed: int = 0
    # steps across the cube's diagonal; 0 = the field's own budget (RepaintTrainer's `trained_samples`: what the
    # editor views it at and bench edit measures the edits at). 512 cost 1.9-2.2x a step of 256 (demo, toys, fox)
    # and kept the unmasked part 0.1-0.5 dB closer step for step; in the same time 256 did better (ARCHITECTURE).
    max_samples: int = 0
    t_threshold: float = 1e-3
    perturb: bool = True
    grow_region: bool = True  # mark the selection's 3D cells occupied at the start
    region_resolution: int = 64
    recolor_mode: str = "shading"
    remove_clear_weight: float = 10.0
    # Measurement only (bench edit's drift case and second ablation): the analytic target moves this far toward
    # a flat tint wherever the edit leaves the view unchanged, as a diffusion model also repaints surroundings it
    # was not asked to change (it never sees the mask); the unmask loss (paper Eq. unmask) is what holds them.
    # 0 = the true edited views.
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
    # ToMe for SD (core.models.sd_tome): this ratio of the tokens merged in the self-attention of the UNet's
    # highest-resolution blocks at 512-px SDS (0 = off, at most 0.75). bench sdcost, bf16 + tiny autoencoder,
    # 512 px, contended CPU: SD 1.5 1.1x-1.55x less CPU time per step (three pairs), SD 2-base inconclusive
    # (0.75x and 1.28x in two rounds); guidance-gradient cosine with the fp32 UNet 0.997 / 0.999.
    sd_token_merging: float = 0.5
    # the side SD sees the render at; None = the model's own (512 for SD 1.5 / 2-base). 256 costs ~1/4 but
    # SD draws less well below its training resolution.
    sds_resolution: int | None = None
    # SD's timestep draw: 'uniform' on [0.02, 0.98] T (official), or 'annealed': the upper bound falls to
    # 0.5 T over the run (threestudio's schedule; meant to need fewer steps, not measured here: no real weights)
    t_schedule: str = "uniform"
    # Stable Diffusion loading (core.models.sd): a diffusers config folder for a single-file checkpoint (default:
    # the shipped one of its detected family), the family (sd1 | sd2-base | sd2-768-v) and prediction type
    # (epsilon | v_prediction) when the file or folder says otherwise or nothing.
    sd_config: str | None = None
    sd_family: str | None = None
    sd_prediction_type: str | None = None
