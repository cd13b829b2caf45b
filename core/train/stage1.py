"""Stage-1 trainer: fits the field to the training images (paper Eq. color), and to teacher features
and depth priors when given (paper Eq. s1), with random-pixel batches, Adam and an LR schedule.

Pixels of all training images sit on the device as one flat uint8 tensor, so a batch is one random
gather. RGBA targets are composited over a random colour per ray and rendered over the same colour,
which teaches the field transparent empty space; their feature targets are scaled by alpha for the
same reason. Outputs that neither the losses nor the grid's reopening need are never asked from the
renderer.
"""
from __future__ import annotations

import dataclasses
import math
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from repaint_nerf.core.device import get_device, synchronize, threads
from repaint_nerf.core.render.occupancy import grid_for_field
from repaint_nerf.core.render.renderer import RenderOptions, render_camera, render_rays
from repaint_nerf.core.train import losses
from repaint_nerf.core.train.adan import grads_finite
from repaint_nerf.core.train.checkpoint import Checkpoint, load_optimizer_state, optimizer_state, split_state
from repaint_nerf.core.train.header import STAGE1, CheckpointHeader, GridFacts, SceneFacts
from repaint_nerf.core.train.health import SpikeDetector
from repaint_nerf.core.train.history import TrainingHistory
from repaint_nerf.core.train.metrics import mse_to_psnr, psnr, ssim
from repaint_nerf.core.train.schedule import LRSchedule, training_progress

CHECKPOINT_NAME = "stage1.safetensors"
# the bounded evaluation (Stage1Trainer.evaluate): its cost is the same at any image size. 8 x 48^2 = 18k rays,
# about 4.5 training batches of rays (forward only): measured on the 128-px demo (untrained, contended), 8 crops
# of 128 px (131k rays) took 189 s, 22x a training step (8.4 s)
EVAL_VIEWS = 8
# pixels per side of each view's evaluation grid: EVAL_GRID x EVAL_GRID pixels spread evenly over the whole view
# (SSIM's 11-px window fits). A 48-px crop instead covered 14% of a 128-px view but 3.5% of a 256-px one, often
# only the transparent background there (bench scale on the 256-px demo: 'inf' dB), so sizes did not compare
EVAL_GRID = 48
EVAL_GRID_MIN = 16  # the smallest grid an evaluation with a time limit shrinks to (SSIM's 11-px window fits)
EVAL_SAMPLE_CAP = 128  # samples per ray; see RenderOptions.sample_cap


@dataclass
class TrainConfig:
    """Stage-1 training settings (JSON-serialisable; saved with checkpoints)."""

    rays_per_batch: int = 4096  # paper: 4096
    # instant-ngp's fixed sample batch: with samples_per_batch > 0 a step takes samples_per_batch / (the last
    # steps' samples per ray) rays, between rays_per_batch / min_rays_divisor and rays_per_batch, so a scene that
    # marches many samples per ray (a capture's room, contracted) takes more, cheaper steps (0 = always
    # rays_per_batch). 16 per ray of the full batch: a scene marching fewer keeps 4096 rays (the demo, 4-15).
    # Measured 60 s from scratch on one core, held-out PSNR (bounded evaluation): room360 128 px 19.98 -> 23.06 dB
    # (245 steps of ~1000 rays against 119 of 4096), the fox capture 15.73 -> 19.35 dB; the 128-px demo at 90 s
    # 33.30 -> 33.41 dB (4096 rays either way once the fog clears)
    samples_per_batch: int = 65536
    min_rays_divisor: int = 8
    lr: float = 1e-2  # paper: Adam, 1e-2
    grid_lr_factor: float = 0.0  # the hash grid's rate is lr x this; 0 = auto (grid_lr_factor_for)
    betas: tuple[float, float] = (0.9, 0.99)  # official code
    eps: float = 1e-15
    weight_decay_mlp: float = 1e-6  # instant-ngp's L2 on the MLP weights (not on the hash table)
    schedule: str = "exp"  # see LRSchedule
    lr_final_factor: float = 0.1
    warmup: float = 0.0
    horizon_steps: int = 20000  # schedule length in steps when a run has no step budget
    # the LR decay follows the step count; a time budget's last `lr_anneal` share brings it to its end
    # (schedule.training_progress; 1.0 = decay by the seconds throughout)
    lr_anneal: float = 0.25
    color_loss: str = "mse"  # or "huber"
    huber_delta: float = 0.1
    lambda_feature: float = 1.0  # paper Eq. s1
    lambda_depth: float = 0.1  # paper Eq. s1
    # mip-NeRF 360's distortion loss (core.render.composite.distortion), with distances in steps over the field
    # cube's diagonal budget: pulls each ray's weights together into one surface instead of a fog. None = auto:
    # FORWARD_DISTORTION for forward-facing scenes, else off (0 = off)
    lambda_distortion: float | None = None
    depth_rays_fraction: float = 0.125  # extra rays on pixels with sparse depth priors
    random_background: bool = True
    perturb: bool = True
    t_threshold: float = 1e-4
    max_samples: int = 0  # steps across the cube's diagonal; 0 = auto (see sample_budget)
    # coarse-to-fine marching (see Stage1Trainer.march_samples): training marches this many steps across the
    # diagonal while the field is fog, then grows to max_samples over grid_warmup_steps (0 = max_samples throughout;
    # None = auto: EARLY_SAMPLES for a field in its own cube, EARLY_SAMPLES_FINE for a contracted or NDC one or
    # one trained on depth priors)
    early_max_samples: int | None = None
    grid_resolution: int = 0  # occupancy cells per axis; 0 = auto (see grid_resolution_for)
    grid_cascades: int = 1
    grid_update_every: int = 16  # instant-ngp: 16
    grid_warmup_steps: int = 256  # instant-ngp: 256 (every cell evaluated per update until then: costly on CPU)
    # skip the density-only filter pass (RenderOptions.one_pass) while it keeps at least this share of its
    # candidates: a foggy field, where every sample is kept and the pass is pure cost. Measured again at each grid
    # update; > 1 = never skip. The first filtered step below it ends the fog for the march ramp (march_budget)
    one_pass_kept: float = 0.99
    grid_update_spread: bool = False  # spread each grid update over its period's steps (the editor: even steps)
    # once per grid update the worst-rendered rays of the batch reopen the pruned cells in front of their
    # surface (a thin structure pruned before it was learned; OccupancyGrid.reopen)
    reopen_fraction: float = 0.01  # at most this fraction of the batch's rays
    reopen_error: float = 0.04  # only rays whose mean squared colour error is above this (0 = off)
    scene_warp: bool = True  # forward / unbounded scenes: NDC / contraction (core.field.contraction)
    # per-image appearance codes (core.field.appearance): auto = on for captures, off for rendered scenes; on; off
    appearance: str = "auto"
    appearance_dim: int = 0  # code size; 0 = APPEARANCE_DIM
    seed: int = 0
    checkpoint_every_s: float = 0.0  # periodic checkpoints during `train` (0 = only when asked)

    @staticmethod
    def from_dict(d: dict) -> "TrainConfig":
        names = {f.name for f in dataclasses.fields(TrainConfig)}
        kw = {k: v for k, v in d.items() if k in names}
        if "betas" in kw:
            kw["betas"] = tuple(kw["betas"])
        return TrainConfig(**kw)


# TrainConfig.early_max_samples's auto values. Measured from 256 (first 50 steps 0.79 s each) down: 64 gave demo 26.3 dB
# in 63 s against 25.7 dB in 141 s with 256. Side by side at 90 s on 2 cores (docs/ARCHITECTURE.md, "The fog phase"):
# 32 against 64 in the field's own cube halves the first 50 steps (demo 36 / 71 ms a step, toys 39 / 77; later steps
# 31-32 / 26-31) and gains 1.8-3.2 dB at 10 s, the same at 30-90 s (demo 34.23 / 34.21, toys 34.32 / 34.19 dB, the
# ethiopian_head capture 25.79 / 25.80 with its first 50 steps at 40 / 62 ms); in a
# warped space a step across its cube spans more of the scene, and 32 lost 0.2-0.7 dB there (fern 21.71 / 21.86,
# fox 25.83 / 26.49 dB at 90 s) where the first 50 steps already cost 1.0-1.2x a later one. Depth priors supervise
# the rendered depth, which a coarse march resolves no finer than its step: on a 32-px demo with priors the depth
# loss after 100-120 steps was 0.08-0.11 at 32 against 0.034-0.038 at 64, so a field with priors keeps 64 as well
EARLY_SAMPLES = 32
EARLY_SAMPLES_FINE = 64

# the distortion weight of forward-facing scenes (TrainConfig.lambda_distortion), mip-NeRF 360's. Side by side on 2
# cores (docs/ARCHITECTURE.md): fern (NDC) at 120 s +0.37 dB, 128-px renders 2.0x faster (49 samples per ray against
# 90); the forward preset (a bounded field) at 90 s -0.1 dB with 1.34x the steps. Off elsewhere: the contracted fox
# lost 2.6 dB at 60 s and 0.4 at 120 s, room360 0.13 dB at 90 s with 1.37x the samples per ray
FORWARD_DISTORTION = 0.01


def check_distortion_weight(value: float, flag: str = "--distortion") -> float:
    """A distortion weight the user gave, or a clear error: it must be finite and 0 or more (an infinite one
    would make every step's loss non-finite, and each step would be skipped)."""
    if not (math.isfinite(value) and value >= 0):
        from repaint_nerf.core.errors import UserError

        raise UserError(f"{flag} must be a finite number, 0 or more, got {value}", hint=f"e.g. {flag} 0.01 (0 = off)")
    return float(value)


def default_config(device: torch.device | None = None, image_size: int | None = None):
    """The field package's default config for this device and image size."""
    from repaint_nerf.core.field import field as fieldmod

    return fieldmod.default_field_config(device, image_size or 800)


def make_field(field_cfg=None, device: torch.device | None = None, image_size: int | None = None):
    """The field for a config (the default for this device when None)."""
    from repaint_nerf.core.field import field as fieldmod

    field_cfg = field_cfg if field_cfg is not None else default_config(device, image_size)
    return fieldmod.NGPField(field_cfg).to(device), field_cfg


def warped_config(scene, device: torch.device | None, image_size: int):
    """The default field config with the space warp the scene's kind needs; None for bounded scenes."""
    from repaint_nerf.core.field.contraction import warp_spec

    spec = warp_spec(scene)
    return None if spec is None else dataclasses.replace(default_config(device, image_size), warp=spec)


def with_appearance(field_cfg, scene, cfg: TrainConfig, device: torch.device | None, image_size: int):
    """A fresh field's config with the appearance codes `cfg` asks for on this scene (one per training image);
    `field_cfg` itself (None: the default) when it asks for none."""
    from repaint_nerf.core.field.appearance import APPEARANCE_DIM, appearance_default

    if not appearance_default(scene, cfg.appearance)[0]:
        return field_cfg
    base = field_cfg if field_cfg is not None else default_config(device, image_size)
    return dataclasses.replace(base, appearance_dim=cfg.appearance_dim or APPEARANCE_DIM,
                               appearance_count=len(scene.train))


def grid_resolution_for(device: torch.device) -> int:
    """Occupancy grid resolution: instant-ngp's 128 on CUDA; 64 on a CPU, where every update sweep and
    dilation costs 8x less. Measured on the 128-px demo (4096 rays, 2-core CPU, test PSNR at 60/90/120/150 s):
    128 cells 17.3/19.8/21.5/23.0 dB (304 steps), 64 cells 20.2/23.2/26.6/28.9 dB (648 steps)."""
    return 128 if device.type == "cuda" else 64


def grid_lr_factor_for(device: torch.device, image_side: int) -> float:
    """The hash grid's learning rate over the MLP's: 1 up to 256 px, growing to 3 at 512 px and above on a CPU;
    1 on CUDA (instant-ngp's one rate for both).

    Why: a large image's run waits on its step count (570-860 steps to 25 dB at 512 px whatever the rays or table:
    docs/ARCHITECTURE.md), and a CPU run has only ~1000 steps in its first minutes. What the higher rate moves is the
    coarse levels (at most 128 cells a side): at 512 px, x3 on those alone reached 25 dB at 43.0 s, on the finer
    ones alone at 63.7 s, on all at 42.8 s (one run each, the same hour). Measured on 2 cores, one run
    each, x3 against x1: ethiopian_head at 512 px 25 dB at 43.1 / 64.3 s (and 38.0 / 62.3 s), fox (288x512)
    +0.25 / +0.47 / +0.71 dB at 30 / 60 / 90 s (side by side over 300 s: +0.48 / +0.78 / +0.94 dB at 60 / 120 /
    300 s), fern (504x378) +0.36 / +0.52 / +0.42 dB. At 128 px x3 came to 25 dB later (11.2 against 8.4 s): the
    early coarse fit wants the paper's rate, so small images keep it."""
    if device.type != "cpu":
        return 1.0
    return 1.0 + 2.0 * min(max(math.log2(max(image_side, 1) / GRID_LR_FROM_PX), 0.0), 1.0)


GRID_LR_FROM_PX = 256  # grid_lr_factor_for: the paper's rate up to this long side


SAMPLE_BUDGET_MAX = 256  # steps across the diagonal at any image size (TrainConfig.max_samples sets more)


def sample_budget(image_side: int) -> int:
    """Steps across the field cube's diagonal for images `image_side` pixels wide: two per pixel, in [128, 256].

    The step follows the content, not the image: rays march only the occupied cells near surfaces, and a finer
    step there multiplies every step's samples. The same trained field rendered at 128 and at 256 px marches
    7.8 samples per ray at 256 steps and 15.0 at 512, whatever the image size (demo, 600 steps). Measured from
    scratch on one core, 240 s per run: toys at 256 px reaches 30 dB in 115 s at 256 steps against 153 s at 512
    (final 32.6 vs 32.8 dB); bread at 512 px in 183 s at 256 steps and never at 1024 (final 31.2 vs 28.8 dB,
    1.9 steps/s at 27 samples per ray). At 128 px, 384 steps gave the test PSNR of 1024 (28.5 vs 28.7 dB at 600
    steps) in 44% of the time. instant-ngp's 1024 is for a GPU; a long run that wants it sets max_samples.
    """
    return int(min(SAMPLE_BUDGET_MAX, max(128, 2 * image_side)))


def march_budget(step: int, full: int, early: int, ramp_steps: int, fog_cleared: int | None = 0) -> int:
    """Steps across the diagonal for training step `step`: `early` until the ramp's start, then growing
    geometrically to `full` over `ramp_steps` steps (coarse to fine; never above `full`; `early` <= 0 = `full`
    throughout). The ramp starts at step `fog_cleared` (None = not yet), at the latest at step `ramp_steps`.

    Why: an untrained field is fog, nothing reaches the transmittance threshold, so every sample of every ray
    up to the far bound is kept and differentiated; their count is the step count (sample_budget). While the
    field is fog it holds no detail a finer step would resolve, so it marches at the early budget
    (TrainConfig.early_max_samples) whatever the image size; the ramp starts when the fog clears (the first
    training step whose filter pass dropped candidates: Stage1Trainer.fog_cleared_step), so a size whose fog
    lasts more steps does not pay for a finer march in it; at the latest at the end of the grid's warm-up.
    """
    start = ramp_steps if fog_cleared is None else min(fog_cleared, ramp_steps)
    if early <= 0 or early >= full or step >= start + ramp_steps:
        return full
    if step <= start:
        return early
    return int(round(early * (full / early) ** ((step - start) / max(1, ramp_steps))))


def field_config_from_dict(d: dict):
    """Rebuild the FieldConfig saved with a checkpoint (unknown keys from newer versions ignored)."""
    from repaint_nerf.core.field.field import FieldConfig

    return FieldConfig.from_dict(d)


def _flat_images(images: list[np.ndarray]) -> tuple[torch.Tensor, np.ndarray, np.ndarray, np.ndarray]:
    """All images as one (P, C) uint8 tensor plus per-image offsets, widths and heights."""
    chans = 4 if any(im.ndim == 3 and im.shape[2] == 4 for im in images) else 3
    parts = []
    for im in images:
        im = np.asarray(im)
        if im.ndim == 2:
            im = np.repeat(im[..., None], 3, axis=2)
        if im.dtype != np.uint8:
            im = np.clip(np.asarray(im, np.float32) * 255.0 + 0.5, 0, 255).astype(np.uint8)
        if im.shape[2] < chans:
            im = np.concatenate([im, np.full(im.shape[:2] + (1,), 255, np.uint8)], axis=2)
        parts.append(torch.from_numpy(np.ascontiguousarray(im[..., :chans])).reshape(-1, chans))
    hs = np.array([im.shape[0] for im in images], np.int64)
    ws = np.array([im.shape[1] for im in images], np.int64)
    offsets = np.concatenate([[0], np.cumsum(hs * ws)])
    return torch.cat(parts), offsets, ws, hs


def _resample_index(u, v, w_img, h_img, w_t, h_t):
    """Nearest pixel of a (h_t, w_t) map for pixel (u, v) of a (h_img, w_img) image."""
    fu = torch.div(u * w_t, w_img, rounding_mode="floor")
    fv = torch.div(v * h_t, h_img, rounding_mode="floor")
    return fv * w_t + fu


def _get(obj, key):
    if isinstance(obj, dict):
        return obj.get(key)
    return getattr(obj, key, None)


class Stage1Trainer:
    """Trains a field (and its occupancy grid) on a scene; see the module docstring."""

    def __init__(self, scene, workspace=None, train_cfg: TrainConfig | None = None, field_cfg=None,
                 device: torch.device | str | None = None, feature_targets=None, depth_priors=None):
        self.scene = scene
        self.workspace = workspace
        self.cfg = train_cfg or TrainConfig()
        self.device = device if isinstance(device, torch.device) else get_device(device)
        torch.manual_seed(self.cfg.seed)
        self.gen = torch.Generator(device=self.device)
        self.gen.manual_seed(self.cfg.seed)

        split = scene.train
        pixels, offsets, ws, hs = _flat_images(split.images)
        self.pixels = pixels.to(self.device)
        self.n_pixels = int(offsets[-1])
        self.offsets = torch.as_tensor(offsets, device=self.device)
        self.widths = torch.as_tensor(ws, device=self.device)
        self.heights = torch.as_tensor(hs, device=self.device)
        self.uniform_size = bool((ws == ws[0]).all() and (hs == hs[0]).all())
        self.has_alpha = self.pixels.shape[1] == 4
        self.cameras = scene.field_cameras("train").to(self.device)
        side = int(max(ws.max(), hs.max()))  # the longest image side: the budgets and the field's defaults follow it
        if self.cfg.max_samples <= 0:
            self.cfg = dataclasses.replace(self.cfg, max_samples=sample_budget(side))
        if self.cfg.grid_resolution <= 0:
            self.cfg = dataclasses.replace(self.cfg, grid_resolution=grid_resolution_for(self.device))
        if self.cfg.grid_lr_factor <= 0:
            self.cfg = dataclasses.replace(self.cfg, grid_lr_factor=grid_lr_factor_for(self.device, side))

        self.feature_stream = None  # codes still arriving (core.teachers.feature_stream)
        self.feature_ready: torch.Tensor | None = None  # per image: its codes are in self.features
        self.features = self._prepare_features(feature_targets) if feature_targets is not None else None
        if field_cfg is None:  # a fresh field (a resumed one keeps its saved config)
            field_cfg = with_appearance(warped_config(scene, self.device, side) if self.cfg.scene_warp else None,
                                        scene, self.cfg, self.device, side)
        if self.features is not None and field_cfg is not None and getattr(field_cfg, "feature_dim", 0) != self.feature_dim:
            field_cfg = dataclasses.replace(field_cfg, feature_dim=self.feature_dim)
        self.field, self.field_cfg = make_field(field_cfg, self.device, side)
        if self.features is not None and getattr(self.field_cfg, "feature_dim", 0) != self.feature_dim:
            self.field_cfg = dataclasses.replace(self.field_cfg, feature_dim=self.feature_dim)
            self.field = type(self.field)(self.field_cfg).to(self.device)
        self.depth, self.depth_pixels = (self._prepare_depth(depth_priors) if depth_priors is not None
                                         else (None, None))
        if not self.cfg.lambda_depth:  # weight 0: checked above, never rendered
            self.depth = self.depth_pixels = None
        if self.cfg.lambda_distortion is None:
            forward = getattr(scene, "kind", "bounded") == "forward"
            self.cfg = dataclasses.replace(self.cfg, lambda_distortion=FORWARD_DISTORTION if forward else 0.0)

        self.grid = grid_for_field(self.field, self.cfg.grid_resolution, self.cfg.grid_cascades, device=self.device,
                                   update_every=self.cfg.grid_update_every, warmup_steps=self.cfg.grid_warmup_steps,
                                   spread=self.cfg.grid_update_spread)
        self.grid.restrict_to_views(self.cameras)  # content trains only where training rays pass
        if self.cfg.early_max_samples is None:
            fine = self.grid.warp is not None or self.depth is not None
            early = EARLY_SAMPLES_FINE if fine else EARLY_SAMPLES
            self.cfg = dataclasses.replace(self.cfg, early_max_samples=early)
        self.optimizer = self._make_optimizer()
        self.schedule = LRSchedule(self.cfg.schedule, self.cfg.lr_final_factor, self.cfg.warmup)
        self.budget_steps: int | None = None
        self.budget_seconds: float | None = None
        self.step_count = 0
        self.train_seconds = 0.0
        self.skipped_steps = 0
        self.spikes = SpikeDetector()
        self.history = TrainingHistory()  # loss/PSNR per step, saved with checkpoints (the editor's plot)
        self.profile = False
        self.last_times: dict = {}
        self.filter_kept = 0.0  # share of its candidates the last filtered step kept (see TrainConfig.one_pass_kept)
        self.recent_samples_per_ray: float | None = None  # moving mean of the steps' samples per ray (rays_now)
        self.fog_cleared_step: int | None = None  # the first step whose filter dropped candidates (march_samples)
        self.ray_seconds = 0.0  # the last step's seconds per ray: sizes a time-limited evaluation (evaluate)
        bg = scene.background
        self.fixed_background = None if bg is None else torch.tensor(bg, dtype=torch.float32, device=self.device)
        if not self.cfg.lambda_feature:
            self.close()
            self.features = self.feature_stream = self.feature_ready = None  # weight 0: never rendered
        self.outputs = ("rgb",) + (("feature",) if self.features is not None else ()) \
            + (("depth",) if self.depth is not None or self.cfg.reopen_error > 0 else ()) \
            + (("opacity",) if self.cfg.reopen_error > 0 else ()) \
            + (("distortion",) if self.cfg.lambda_distortion > 0 else ())  # depth, opacity: sums made anyway

    # -- set-up -----------------------------------------------------------------------------------
    def _make_optimizer(self) -> torch.optim.Optimizer:
        groups = []
        pg = self.field.parameter_groups() if hasattr(self.field, "parameter_groups") else {"all": list(self.field.parameters())}
        for name, params in pg.items():
            params = [p for p in params if p.requires_grad]
            if params:
                wd = self.cfg.weight_decay_mlp if name in ("mlp", "feature") else 0.0
                groups.append({"params": params, "lr": self._group_lr(name), "weight_decay": wd, "name": name})
        kw = dict(lr=self.cfg.lr, betas=tuple(self.cfg.betas), eps=self.cfg.eps)
        try:
            return torch.optim.Adam(groups, fused=True, **kw)
        except (RuntimeError, TypeError):
            return torch.optim.Adam(groups, foreach=True, **kw)

    def _group_lr(self, name: str) -> float:
        """Base learning rate of an optimiser group: lr, times grid_lr_factor for the hash grid."""
        return self.cfg.lr * (self.cfg.grid_lr_factor if name == "grid" else 1.0)

    def _prepare_features(self, targets) -> torch.Tensor:
        """Per-image (h, w, K) feature codes as one flat float16 tensor. A stream (core.teachers.feature_stream)
        gives zeros to start with and `_take_features` fills each image's rows as its codes arrive."""
        n = len(self.scene.train)
        if len(targets) != n:
            raise ValueError(f"{len(targets)} feature maps for {n} training images")
        if hasattr(targets, "poll"):
            self.feature_stream, sizes, self.feature_dim = targets, list(targets.sizes), int(targets.dims)
            self.feature_ready = torch.zeros(n, dtype=torch.bool, device=self.device)
        else:
            maps = [torch.as_tensor(np.asarray(targets[i])) for i in range(n)]
            sizes, self.feature_dim = [tuple(m.shape[:2]) for m in maps], int(maps[0].shape[-1])
        self.feat_h = torch.tensor([h for h, _ in sizes], device=self.device)
        self.feat_w = torch.tensor([w for _, w in sizes], device=self.device)
        offs = np.concatenate([[0], np.cumsum([h * w for h, w in sizes])])
        self.feat_offsets = torch.as_tensor(offs, device=self.device)
        if self.feature_stream is not None:
            return torch.zeros(int(offs[-1]), self.feature_dim, dtype=torch.float16, device=self.device)
        return torch.cat([m.reshape(-1, self.feature_dim).to(torch.float16) for m in maps]).to(self.device)

    def _take_features(self) -> None:
        """Copy the codes a feature stream made since the last step into the targets; once every image has
        them, the stream is dropped and every ray has a feature target again."""
        if self.feature_stream is None:
            return
        for i, codes in self.feature_stream.poll():
            a, b = int(self.feat_offsets[i]), int(self.feat_offsets[i + 1])
            self.features[a:b] = codes.reshape(-1, self.feature_dim).to(self.features.device, torch.float16)
            self.feature_ready[i] = True
        if self.feature_stream.complete:
            self.feature_stream = self.feature_ready = None

    def close(self) -> None:
        """Stop background work (a feature stream): the trainer is being replaced."""
        if self.feature_stream is not None:
            self.feature_stream.stop()

    def _prepare_depth(self, priors) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Depth priors as z-depth in field units per flat pixel (NaN = none), and the pixels that have one
        when they are sparse (those get extra rays every step)."""
        n = len(self.scene.train)
        if len(priors) != n:
            raise ValueError(f"{len(priors)} depth priors for {n} training images")
        scale = float(self.scene.norm.scale)
        flat = torch.full((self.n_pixels,), float("nan"))
        offs, ws, hs = self.offsets.cpu(), self.widths.cpu(), self.heights.cpu()
        for i in range(n):
            p = priors.for_image(i) if hasattr(priors, "for_image") else priors[i]
            if p is None:
                continue
            w, h, o = int(ws[i]), int(hs[i]), int(offs[i])
            if isinstance(p, (tuple, list)) and len(p) == 2:
                dense, valid = p
            elif _get(p, "z") is not None:
                u = torch.as_tensor(np.asarray(_get(p, "u")), dtype=torch.float64).floor().long()
                v = torch.as_tensor(np.asarray(_get(p, "v")), dtype=torch.float64).floor().long()
                z = torch.as_tensor(np.asarray(_get(p, "z")), dtype=torch.float32)
                keep = (u >= 0) & (u < w) & (v >= 0) & (v < h) & torch.isfinite(z) & (z > 0)
                flat[o + v[keep] * w + u[keep]] = z[keep] * scale
                continue
            elif _get(p, "depth") is not None:
                dense, valid = _get(p, "depth"), _get(p, "valid")
            else:
                dense, valid = p, None
            d = torch.as_tensor(np.asarray(dense, dtype=np.float32))
            ok = torch.isfinite(d) & (d > 0)
            if valid is not None:
                ok &= torch.as_tensor(np.asarray(valid)).bool()
            d = torch.where(ok, d * scale, torch.full_like(d, float("nan")))
            if d.shape != (h, w):
                vv, uu = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
                d = d.reshape(-1)[_resample_index(uu, vv, w, h, d.shape[1], d.shape[0])]
            flat[o:o + h * w] = d.reshape(-1)
        have = torch.isfinite(flat)
        sparse = None
        if have.float().mean() < 0.5:
            sparse = have.nonzero()[:, 0].to(self.device)
            if sparse.numel() == 0:
                sparse = None
        return flat.to(self.device), sparse

    # -- one step ---------------------------------------------------------------------------------
    def sample_pixels(self, n: int) -> torch.Tensor:
        """`n` flat pixel indices drawn uniformly over all training pixels (plus sparse-depth pixels)."""
        idx = torch.randint(0, self.n_pixels, (n,), generator=self.gen, device=self.device)
        if self.depth_pixels is not None:
            k = max(1, int(n * self.cfg.depth_rays_fraction))
            pick = torch.randint(0, self.depth_pixels.numel(), (k,), generator=self.gen, device=self.device)
            idx = torch.cat([idx, self.depth_pixels[pick]])
        return idx

    def pixel_coords(self, idx: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(image index, u, v) of flat pixel indices."""
        if self.uniform_size:
            hw = int(self.widths[0] * self.heights[0])
            img = torch.div(idx, hw, rounding_mode="floor")
            local = idx - img * hw
            w = self.widths[0]
        else:
            img = torch.searchsorted(self.offsets[1:], idx, right=True)
            local = idx - self.offsets[img]
            w = self.widths[img]
        v = torch.div(local, w, rounding_mode="floor")
        return img, local - v * w, v

    def make_batch(self) -> dict[str, torch.Tensor]:
        """Rays, targets and background colours for one step."""
        idx = self.sample_pixels(self.rays_now())
        img, u, v = self.pixel_coords(idx)
        origins, dirs, dz = self.cameras.rays(img, u, v)
        px = self.pixels[idx].float() * (1.0 / 255.0)
        n = idx.shape[0]
        if self.has_alpha and self.cfg.random_background and self.fixed_background is None:
            bg = torch.rand(n, 3, generator=self.gen, device=self.device)
        elif self.has_alpha:
            bg = (self.fixed_background if self.fixed_background is not None
                  else torch.ones(3, device=self.device)).expand(n, 3)
        elif self.cfg.random_background and self.fixed_background is None:
            bg = torch.rand(n, 3, generator=self.gen, device=self.device)  # opaque photos: forces opacity 1
        else:
            bg = None if self.fixed_background is None else self.fixed_background.expand(n, 3)
        rgb = px[:, :3]
        if self.has_alpha:
            a = px[:, 3:4]
            rgb = rgb * a + bg * (1.0 - a)
        batch = {"origins": origins, "dirs": dirs, "dz": dz, "rgb": rgb, "background": bg, "image": img}
        if self.features is not None:
            fidx = self.feat_offsets[img] + _resample_index(u, v, self.widths[img], self.heights[img],
                                                            self.feat_w[img], self.feat_h[img])
            feat = self.features[fidx]
            # empty space renders a zero feature (no background term), so a transparent pixel's target
            # is zero: the teacher saw it composited over white, and chasing that made floaters
            batch["feature"] = feat * px[:, 3:4].to(feat.dtype) if self.has_alpha else feat
            if self.feature_ready is not None:
                batch["feature_ready"] = self.feature_ready[img]
        if self.depth is not None:
            batch["depth"] = self.depth[idx]
        return batch

    def rays_now(self) -> int:
        """Rays for the next step: rays_per_batch, or with TrainConfig.samples_per_batch the rays whose samples
        fill that batch at the recent samples per ray (instant-ngp's fixed sample batch)."""
        full = self.cfg.rays_per_batch
        if self.cfg.samples_per_batch <= 0 or self.recent_samples_per_ray is None:
            return full
        n = int(self.cfg.samples_per_batch / max(self.recent_samples_per_ray, 1e-3))
        return max(full // max(1, self.cfg.min_rays_divisor), min(full, n))

    @property
    def march_samples(self) -> int:
        """Steps across the diagonal the field is trained and rendered at now (coarse to fine: march_budget)."""
        return march_budget(self.step_count, self.cfg.max_samples, self.cfg.early_max_samples,
                            self.cfg.grid_warmup_steps, self.fog_cleared_step)

    def progress(self) -> float:
        """Fraction of the planned training done (drives the LR schedule: schedule.training_progress)."""
        return training_progress(self.step_count, self.train_seconds, self.budget_steps, self.budget_seconds,
                                 self.cfg.horizon_steps, self.cfg.lr_anneal)

    def _set_lr(self) -> float:
        f = self.schedule.factor(self.progress())
        for g in self.optimizer.param_groups:
            g["lr"] = self._group_lr(g["name"]) * f
        return self.cfg.lr * f

    def step(self, interlude: Callable[[], None] | None = None) -> dict[str, Any]:
        """One optimisation step; returns the loss parts, the batch PSNR, the LR and the seconds it took.
        `interlude()`, when given, runs at each marching round's start, before the differentiable pass and between
        the forward and the backward pass (the editor's worker serves a new view there, so a camera move or a tool
        switch waits for a marching round or the differentiable pass, not for a whole step); its time is not the
        step's. It must leave the parameters, the occupancy grid and torch's random state as it found them.

        With `self.profile` set, `self.last_times` gets per-stage seconds (synchronising the device). While a
        feature stream's teacher runs on the CPU, the step leaves it its threads: both pools on the same cores
        made each wait on the other (fox, 2 cores: 1.06 steps/s beside the teacher, 6.3 after it).
        """
        stream = self.feature_stream
        if stream is None or self.device.type != "cpu":
            return self._step(interlude)
        with threads(torch.get_num_threads() - stream.threads):
            return self._step(interlude)

    def _step(self, interlude: Callable[[], None] | None = None) -> dict[str, Any]:
        prof = self.profile
        times: dict[str, float] = {}
        t0 = tick = time.perf_counter()

        def lap(key: str) -> None:
            nonlocal tick
            if prof:
                synchronize(self.device)
                now = time.perf_counter()
                times[key] = times.get(key, 0.0) + now - tick
                tick = now

        def pause() -> None:
            """The interlude, off the step's clock."""
            nonlocal t0, tick
            paused = time.perf_counter()
            interlude()
            held = time.perf_counter() - paused
            t0 += held
            tick += held

        self.field.train()
        self.grid.update(self.step_count, self.field.density)
        lap("grid_update")
        lr = self._set_lr()
        self._take_features()
        batch = self.make_batch()
        lap("batch")
        every = self.cfg.grid_update_every
        one_pass = self.filter_kept >= self.cfg.one_pass_kept and self.step_count % every != 0
        ready = batch.get("feature_ready")
        if ready is not None and not bool(ready.any()):  # no view has its codes yet: nothing to distil
            outputs = tuple(o for o in self.outputs if o != "feature")
        else:
            outputs = self.outputs
        opts = RenderOptions(outputs=outputs, background=batch["background"], t_threshold=self.cfg.t_threshold,
                             max_samples=self.march_samples, perturb=self.cfg.perturb, profile=prof,
                             one_pass=one_pass, appearance=batch["image"],
                             pause=None if interlude is None else pause)
        out = render_rays(self.field, self.grid, batch["origins"], batch["dirs"], opts)
        stats = out.get("stats") or {}
        if not one_pass and stats.get("density_samples"):
            self.filter_kept = stats["samples"] / stats["density_samples"]
            if self.fog_cleared_step is None and self.filter_kept < self.cfg.one_pass_kept:
                self.fog_cleared_step = self.step_count
        color = losses.color_loss(out["rgb"], batch["rgb"], self.cfg.color_loss, self.cfg.huber_delta)
        parts: dict[str, torch.Tensor] = {"color": color}
        if "feature" in outputs:
            pred, target = out["feature"], batch["feature"]
            if ready is not None:  # only the views whose codes have arrived
                pred, target = pred[ready], target[ready]
            parts["feature"] = losses.feature_loss(pred, target)
        if self.depth is not None:
            valid = torch.isfinite(batch["depth"])
            parts["depth"] = losses.depth_loss(out["depth"] * batch["dz"], batch["depth"], valid)
        total = losses.stage1_loss(color, parts.get("feature"), parts.get("depth"),
                                   self.cfg.lambda_feature, self.cfg.lambda_depth)
        if "distortion" in outputs:
            parts["distortion"] = out["distortion"].mean()
            total = total + self.cfg.lambda_distortion * parts["distortion"]
        if self.cfg.reopen_error > 0 and self.cfg.reopen_fraction > 0 and self.step_count % every == every - 1:
            self._reopen_worst(batch, out)  # the batch before an update: its cells open for the next period
        lap("forward")
        if interlude is not None:
            pause()
        self.optimizer.zero_grad(set_to_none=True)
        finite = bool(torch.isfinite(total))
        if finite:
            total.backward()
            finite = grads_finite(p for g in self.optimizer.param_groups for p in g["params"])
        lap("backward")
        if finite:
            self.optimizer.step()
        else:
            self.skipped_steps += 1  # DESIGN.md: a non-finite loss or gradient is skipped and counted, never applied
            self.optimizer.zero_grad(set_to_none=True)
        lap("optimizer")
        self.step_count += 1
        with torch.no_grad():
            mse = torch.mean((out["rgb"].detach() - batch["rgb"]) ** 2)
        info = {k: float(v.detach()) for k, v in parts.items()}
        synchronize(self.device)
        dt = time.perf_counter() - t0
        self.train_seconds += dt
        self.ray_seconds = dt / max(1, batch["rgb"].shape[0])
        info.update(step=self.step_count, loss=float(total.detach()), psnr=mse_to_psnr(mse), lr=lr, seconds=dt,
                    skipped=not finite, skipped_steps=self.skipped_steps,
                    spike=self.spikes.update(float(total.detach())), spikes=self.spikes.spikes)
        self.history.add(info)
        info["one_pass"] = one_pass
        for key in ("samples_per_ray", "candidates_per_ray"):
            if key in stats:
                info[key] = float(stats[key])
        if "samples_per_ray" in info:
            spr, prev = info["samples_per_ray"], self.recent_samples_per_ray
            self.recent_samples_per_ray = spr if prev is None else 0.8 * prev + 0.2 * spr
        info["rays"] = int(batch["rgb"].shape[0])
        if prof:
            times["render"] = dict(stats.get("time", {}))
            self.last_times = times
        return info

    @torch.no_grad()
    def _reopen_worst(self, batch: dict, out: dict) -> None:
        """Reopen the grid cells in front of the surface of the rays rendered worst (OccupancyGrid.reopen):
        a thin structure pruned before it was learned shows up as a large colour error on its pixels."""
        err = ((out["rgb"].detach() - batch["rgb"]) ** 2).mean(-1)
        k = max(1, int(err.shape[0] * self.cfg.reopen_fraction))
        vals, idx = err.topk(min(k, err.shape[0]))
        idx = idx[vals > self.cfg.reopen_error]
        if idx.numel():
            op, depth = out["opacity"].detach()[idx], out["depth"].detach()[idx]
            t_end = torch.where(op > 0.5, depth, torch.full_like(depth, math.inf))  # in front of the surface
            self.grid.reopen(batch["origins"][idx], batch["dirs"][idx], t_end)

    def train(self, steps: int | None = None, seconds: float | None = None,
              callback: Callable[[dict], Any] | None = None, stop=None,
              interlude: Callable[[], None] | None = None) -> dict | None:
        """Train until the total step count reaches `steps` or the total training time reaches `seconds`
        (both counted from the first step, so a resumed run finishes its plan), or until `stop` is set.

        `stop` is a threading.Event or a callable returning True; `callback(info)` runs after every step; `interlude`
        runs within each (`step`).
        The LR schedule spans the budget set by `plan` (else `horizon_steps`). Returns the last step's info.
        """
        should_stop = stop.is_set if isinstance(stop, threading.Event) else (stop or (lambda: False))
        last_save = time.perf_counter()
        info = None
        while True:
            if steps is not None and self.step_count >= steps:
                break
            if seconds is not None and self.train_seconds >= seconds:
                break
            if should_stop():
                break
            info = self.step(interlude)
            if callback is not None:
                callback(info)
            every = self.cfg.checkpoint_every_s
            if every and self.workspace is not None and time.perf_counter() - last_save > every:
                self.save_checkpoint()
                last_save = time.perf_counter()
        return info

    def plan(self, steps: int | None = None, seconds: float | None = None) -> None:
        """Set the training budget the LR schedule spans (total steps and/or seconds)."""
        self.budget_steps, self.budget_seconds = steps, seconds

    @property
    def done(self) -> bool:
        """Whether the planned budget is spent (never, for an open-ended run)."""
        return ((self.budget_steps is not None and self.step_count >= self.budget_steps)
                or (self.budget_seconds is not None and self.train_seconds >= self.budget_seconds))

    def train_for(self, seconds: float, stop: Callable[[], bool] | None = None,
                  interlude: Callable[[], None] | None = None) -> dict:
        """Train for about `seconds` more (at least one step), ending early once `stop()` turns true; the
        editor's worker calls this between renders and stops it when the user moves the camera, and serves a
        new view within a step through `interlude` (`step`)."""
        info = self.train(steps=self.step_count + 1, interlude=interlude) or {}
        if seconds > info.get("seconds", 0.0) and not (stop is not None and stop()):
            info = self.train(seconds=self.train_seconds + seconds - info.get("seconds", 0.0), stop=stop,
                              interlude=interlude) or info
        if self.feature_stream is not None:  # the editor says how far the teacher has got
            info = {**info, "features_ready": [self.feature_stream.received, len(self.feature_stream)]}
        return info

    # -- evaluation ---------------------------------------------------------------------------------
    def eval_split(self) -> str:
        """The split to evaluate on: test, else val, else train."""
        for name in ("test", "val", "train"):
            if name in self.scene.splits and len(self.scene.splits[name]):
                return name
        return "train"

    def eval_background(self) -> torch.Tensor:
        return self.fixed_background if self.fixed_background is not None else torch.ones(3, device=self.device)

    @torch.no_grad()
    def evaluate(self, split: str | None = None, max_views: int | None = None, with_ssim: bool = False,
                 full: bool = False, deadline: float | None = None, seconds: float | None = None,
                 scene=None) -> dict:
        """Mean PSNR (and SSIM) of renders of a split against its images composited over the eval background.
        `scene`: another load of the same capture to score against (the same poses at another image size: bench
        scale scores a 512-px field on the 128-px images); its poses go into field space by this scene's
        normalisation.

        By default a bounded evaluation, whose cost does not grow with the image size: `EVAL_VIEWS` views
        spread over the split (or `max_views`), an `EVAL_GRID` x `EVAL_GRID` grid of pixels spread evenly over
        each (the same scene content at every image size; see eval_pixels), and at most
        `EVAL_SAMPLE_CAP` samples per ray (an untrained, foggy field is never marched to the far bound).
        `full=True` renders every pixel of the first `max_views` views (all by default) without the cap.

        Time limits: `seconds` from the call and/or the clock value `deadline` (time.perf_counter()). A view starts
        only when the slowest view so far would end within them (at least one is evaluated); the others are
        counted in 'skipped_views'. The first view's time is estimated from the last training step's seconds per
        ray; when it would not fit, the bounded evaluation's grid shrinks (to EVAL_GRID_MIN at the least; 'grid'
        says the side used).
        """
        split = split or self.eval_split()
        data = (scene or self.scene).split(split)
        cams = self.scene.norm.cameras_to_field(data.cameras).to(self.device)
        bg = self.eval_background()
        opts = RenderOptions(outputs=("rgb",), background=bg, t_threshold=self.cfg.t_threshold,
                             max_samples=self.march_samples, perturb=False,
                             sample_cap=0 if full else EVAL_SAMPLE_CAP)
        self.field.eval()
        n = len(data)
        views = list(range(n if max_views is None else min(max_views, n))) if full \
            else spread_views(n, EVAL_VIEWS if max_views is None else max_views)
        t0 = time.perf_counter()
        limit = min(math.inf if seconds is None else seconds, math.inf if deadline is None else deadline - t0)
        side = None if full else eval_grid_side(limit, self.ray_seconds)
        ps, ss, pixels, samples, skipped, view_s = [], [], 0, 0.0, 0, 0.0
        for i in views:
            if ps and time.perf_counter() - t0 + view_s > limit:
                skipped += 1
                continue
            tv = time.perf_counter()
            if full:
                out = render_camera(self.field, self.grid, cams, i, opts)
                gt = target_image(data.images[i], bg)
                rgb = out["rgb"]
            else:
                us, vs = eval_pixels(int(cams.width[i]), int(cams.height[i]), side)
                vv, uu = torch.meshgrid(torch.as_tensor(vs, device=self.device),
                                        torch.as_tensor(us, device=self.device), indexing="ij")
                o, d, _ = cams.rays(torch.full_like(uu, i).reshape(-1), uu.reshape(-1), vv.reshape(-1))
                out = render_rays(self.field, self.grid, o, d, opts)
                rgb = out["rgb"].reshape(len(vs), len(us), 3)
                gt = target_image(np.asarray(data.images[i])[np.ix_(vs, us)], bg)
            pixels += gt.shape[0] * gt.shape[1]
            samples += float(out["stats"]["samples"])
            ps.append(psnr(rgb.clamp(0, 1), gt))
            if with_ssim:
                ss.append(ssim(rgb.clamp(0, 1), gt))
            view_s = max(view_s, time.perf_counter() - tv)
        self.field.train()
        res = {"split": split, "views": len(ps), "views_total": n, "full": full, "pixels": pixels, "grid": side,
               "skipped_views": skipped, "samples_per_ray": samples / max(1, pixels),
               "seconds": time.perf_counter() - t0, "psnr": float(np.mean(ps)) if ps else float("nan")}
        if with_ssim:
            res["ssim"] = float(np.mean(ss)) if ss else float("nan")
        return res

    # -- checkpoints ----------------------------------------------------------------------------------
    def checkpoint(self) -> Checkpoint:
        """The full training state: field, grid, optimiser, RNG, step, configs, scene facts."""
        tensors = {f"field.{k}": v for k, v in self.field.state_dict().items()}
        grid_t, grid_rest = split_state(self.grid.state_dict())
        tensors.update({f"grid.{k}": v for k, v in grid_t.items()})
        opt_t, opt_meta = optimizer_state(self.optimizer)
        tensors.update({f"optim.{k}": v for k, v in opt_t.items()})
        tensors["rng.sampler"] = self.gen.get_state()
        tensors["rng.torch"] = torch.get_rng_state()
        header = CheckpointHeader(
            kind=STAGE1, step=self.step_count, train_seconds=self.train_seconds,
            field_config=dataclasses.asdict(self.field_cfg), train_config=dataclasses.asdict(self.cfg),
            grid=GridFacts(self.cfg.grid_resolution, self.cfg.grid_cascades,
                           float(getattr(self.field_cfg, "bound", 1.0)), grid_rest),
            optim=opt_meta, budget_steps=self.budget_steps, budget_seconds=self.budget_seconds,
            scene=SceneFacts.of(self.scene), history=self.history, fog_cleared_step=self.fog_cleared_step)
        return Checkpoint.of(tensors, header)

    def load(self, ckpt: Checkpoint) -> None:
        """Restore a state written by `checkpoint` (same field config) to resume training."""
        h = ckpt.info
        self.field.load_state_dict(ckpt.section("field"))
        self.grid.load_state_dict({**ckpt.section("grid"), **h.grid.state})
        load_optimizer_state(self.optimizer, {k: v.to(self.device) for k, v in ckpt.section("optim").items()},
                             h.optim or {})
        self.gen.set_state(ckpt.tensors["rng.sampler"].cpu())
        torch.set_rng_state(ckpt.tensors["rng.torch"].cpu())
        self.step_count, self.train_seconds = h.step, h.train_seconds
        self.budget_steps, self.budget_seconds = h.budget_steps, h.budget_seconds
        self.history = h.history
        self.fog_cleared_step = h.march_start

    def checkpoint_path(self) -> Path:
        if self.workspace is None:
            raise ValueError("this trainer has no workspace to save into")
        return self.workspace.checkpoints_dir / CHECKPOINT_NAME

    def save_checkpoint(self) -> Path:
        """Write the training state to the workspace's checkpoint (atomically)."""
        path = self.checkpoint_path()
        self.checkpoint().save(path)
        return path

    def resume(self) -> bool:
        """Load the workspace's checkpoint if there is one; returns whether it did."""
        path = self.checkpoint_path()
        if not path.exists():
            return False
        self.load(Checkpoint.load(path, self.device))
        return True

    def load_version(self, path: str | Path) -> None:
        """Load the field and grid of a saved version (undo/redo); the optimiser starts afresh."""
        ck = Checkpoint.load(path, self.device)
        self.field.load_state_dict(ck.section("field"))
        self.grid.load_state_dict({**ck.section("grid"), **ck.info.grid.state})
        self.optimizer = self._make_optimizer()

    def save_version(self, name: str = "reconstruction"):
        """Save the current field as a new stage-1 version of the workspace (never overwritten by edits)."""
        return self.workspace.save_version(name, self.checkpoint(), kind="stage1")


def spread_views(n: int, k: int) -> list[int]:
    """`k` view indices spread evenly over `n` views (all of them when k >= n)."""
    if k >= n:
        return list(range(n))
    return sorted({int(round(x)) for x in np.linspace(0, n - 1, max(1, k))})


def eval_pixels(width: int, height: int, side: int) -> tuple[np.ndarray, np.ndarray]:
    """(columns, rows) of the bounded evaluation's pixels: at most `side` of each, the centres of a `side` x `side`
    split of the view (a nearest-pixel downscale), so every image size shows the same content at the same cost,
    and successive evaluations compare the same pixels."""
    def axis(n: int) -> np.ndarray:
        k = min(side, n)
        return ((np.arange(k) + 0.5) * n / k).astype(np.int64)
    return axis(width), axis(height)


def eval_grid_side(limit_s: float, ray_seconds: float, side: int | None = None) -> int:
    """The bounded evaluation's grid side for a view estimated at `ray_seconds` per pixel to fit in `limit_s`:
    `side` (EVAL_GRID) when it fits or nothing is known, else the largest that fits, at least EVAL_GRID_MIN."""
    side = EVAL_GRID if side is None else side
    if not math.isfinite(limit_s) or ray_seconds <= 0 or side * side * ray_seconds <= limit_s:
        return side
    return int(min(side, max(EVAL_GRID_MIN, math.isqrt(int(max(0.0, limit_s) / ray_seconds)))))


def target_image(image: np.ndarray, background: torch.Tensor) -> torch.Tensor:
    """A uint8 (H, W, 3|4) image as float (H, W, 3) on the background's device, alpha composited over it."""
    t = torch.as_tensor(np.ascontiguousarray(image), device=background.device).float() / 255.0
    if t.shape[-1] == 4:
        return t[..., :3] * t[..., 3:4] + background * (1.0 - t[..., 3:4])
    return t[..., :3]


def restore_field(ckpt: Checkpoint, device: torch.device | str | None = None):
    """(field, grid, header) from a checkpoint or version, ready to render (eval mode); the header is a
    `core.train.header.CheckpointHeader`."""
    device = device if isinstance(device, torch.device) else get_device(device)
    header = ckpt.info
    fld, _ = make_field(header.field_cfg(), device)
    fld.load_state_dict({k: v.to(device) for k, v in ckpt.section("field").items()})
    g = header.grid
    grid = grid_for_field(fld, g.resolution, g.cascades, device=device)
    grid.load_state_dict({**{k: v.to(device) for k, v in ckpt.section("grid").items()}, **g.state})
    fld.eval()
    return fld, grid, header
