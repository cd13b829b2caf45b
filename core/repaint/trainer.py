"""The repaint trainer (paper stage 2, Eq. s2): loss = guidance + lambda_unmask * L_unmask + lambda_clip * L_clip.

Each step renders one whole training view (random, at a resolution that fits the device) with
gradients, asks the guidance for its loss on the render and mask, holds the pixels outside the mask to
the original training image (Eq. unmask) and optionally pulls the masked-out render toward the
background prompt (Eq. clip). Adan updates the field; the occupancy grid keeps updating, and the
selection's 3D region is marked occupied at the start so new content can grow there.

Only what the edit needs is computed: the renderer is asked for 'rgb' only (no feature head in the
backward pass), per-view rays, targets and masks are prepared once, CLIP is never loaded when
lambda_clip is 0. A non-finite guidance gradient or loss skips the step (counted in `skipped_steps`).
The trainer can pause, resume and cancel from another thread; a cancelled edit restores the field;
a finished one is saved as a new workspace version (undo goes back; the original is never overwritten).
"""
from __future__ import annotations

import dataclasses
import threading
import time
from pathlib import Path
from typing import Any, Callable

import cv2
import numpy as np
import torch
from torch import Tensor

from repaint_nerf.core.device import get_device, is_cuda, synchronize
from repaint_nerf.core.errors import UserError
from repaint_nerf.core.render.renderer import RenderOptions, render_camera, render_rays
from repaint_nerf.core.repaint import registry
from repaint_nerf.core.repaint.config import RepaintConfig  # noqa: F401  (defined in config.py; imported from here too)
from repaint_nerf.core.repaint.dilate import dilate
from repaint_nerf.core.repaint.guidance import as_guidance
from repaint_nerf.core.repaint.estimate import Estimate, Progress, estimate_repaint
from repaint_nerf.core.repaint.region import mark_region_occupied, selection_region
from repaint_nerf.core.repaint.objective import (UNMASK_REDUCTIONS, masked_mse, stage2_loss, unmask_loss,
                                                 unmask_weight)
from repaint_nerf.core.train.adan import OFFICIAL_LR, OFFICIAL_MULTIPLIERS, PAPER_LR, Adan, param_groups
from repaint_nerf.core.train.checkpoint import Checkpoint, split_state
from repaint_nerf.core.train.health import SpikeDetector
from repaint_nerf.core.train.metrics import mse_to_psnr
from repaint_nerf.core.train.schedule import LRSchedule
from repaint_nerf.core.train.stage1 import sample_budget, target_image

CPU_RESOLUTION, CUDA_RESOLUTION = 128, 400  # default caps of the render's long side


DRIFT_TINT = (0.55, 0.25, 0.75)  # where RepaintConfig.analytic_drift pulls what the edit leaves unchanged
UNCHANGED_TOL = 2.5 / 255  # an edited pixel this close to the original (every channel) is one the edit left alone


def unchanged(edited: Tensor, original: Tensor, tol: float = UNCHANGED_TOL) -> Tensor:
    """1 where the edited image (B, 3, H, W) matches the original within `tol` in every channel, else 0 (B, 1, H, W)."""
    return ((edited - original).abs().amax(1, keepdim=True) <= tol).float()


def default_resolution(width: int, height: int, device: torch.device) -> int:
    """The render's long side: the training image's, capped at 400 on CUDA and 128 on CPU."""
    return min(max(width, height), CUDA_RESOLUTION if is_cuda(device) else CPU_RESOLUTION)


def _resize(img: np.ndarray, w: int, h: int, interp=cv2.INTER_AREA) -> np.ndarray:
    return img if img.shape[1] == w and img.shape[0] == h else cv2.resize(img, (w, h), interpolation=interp)


def edited_images(scene) -> list[np.ndarray]:
    """The synthetic scene's edited/ variant of each training image (same names), for the analytic guidance."""
    root = Path(scene.root)
    folder = root / "edited"
    if not (folder / "transforms_train.json").is_file():
        raise UserError("this scene has no edited/ variant (edited/transforms_train.json)", root,
                        hint="the analytic guidance needs a synthetic scene from `repaint-nerf make-scene`; "
                             "use --guidance sd, recolor or remove")
    out = []
    for i, p in enumerate(scene.train.paths or []):
        rel = Path(p).relative_to(root) if Path(p).is_absolute() else Path(p)
        img = cv2.imread(str(folder / rel), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise UserError("an edited image is missing", folder / rel, hint="regenerate the scene")
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2RGBA if img.shape[-1] == 4 else cv2.COLOR_BGR2RGB)
        h, w = scene.train.images[i].shape[:2]
        out.append(_resize(img, w, h))
    if len(out) != len(scene.train):
        raise UserError("the scene's training images have no file paths to match edited/ against", root)
    return out


class RepaintTrainer:
    """Edits `field` in place under a guidance; see the module docstring.

    `guidance` is a Guidance object or the name of a backend in core.repaint.registry ('offline' picks recolor
    or remove from the prompt); `masks` are bool (H, W) per training view (default: the workspace's, from `select`).
    `on_snapshot(info)` gets {'step', 'rgb' (H, W, 3) numpy preview, 'view'} every `snapshot_every` steps.
    """

    def __init__(self, scene, field, grid, workspace=None, masks: list[np.ndarray] | None = None,
                 guidance: Any = None, prompt: str = "", bg_prompt: str = "", backend: str | None = None,
                 config: RepaintConfig | None = None, device: torch.device | str | None = None,
                 sd_path=None, clip_path=None, color=None, negative_prompt: str = "",
                 on_snapshot: Callable[[dict], Any] | None = None, trained_samples: int | None = None,
                 **overrides):
        self.scene, self.field, self.grid, self.workspace = scene, field, grid, workspace
        self.prompt, self.bg_prompt = prompt, bg_prompt
        cfg = config or RepaintConfig()
        unknown = set(overrides) - {f.name for f in dataclasses.fields(RepaintConfig)}
        if unknown:
            raise TypeError(f"unknown repaint options {sorted(unknown)}")
        self.cfg = dataclasses.replace(cfg, **overrides)
        if self.cfg.max_samples <= 0:  # the budget the field was trained with, else the one stage 1 would pick
            side = max(max(int(im.shape[0]), int(im.shape[1])) for im in scene.train.images)
            self.cfg.max_samples = int(trained_samples) if trained_samples else sample_budget(side)
        kind = backend if guidance is None else guidance
        spec = registry.resolve(kind, prompt) if isinstance(kind, str) else None
        self.kind = spec.name if spec is not None else type(kind).__name__
        self.cfg.lambda_clip = registry.clip_weight(self.kind, self.cfg)
        if self.cfg.steps < 1:
            raise UserError(f"steps must be at least 1, got {self.cfg.steps}")
        if self.cfg.lambda_unmask < 0 or self.cfg.lambda_clip < 0:
            raise UserError("lambda_unmask and lambda_clip must not be negative")
        if self.cfg.unmask_reduction not in UNMASK_REDUCTIONS:
            raise UserError(f"unknown unmask reduction {self.cfg.unmask_reduction!r}",
                            hint=f"use one of: {', '.join(UNMASK_REDUCTIONS)}")
        if not (0.0 <= self.cfg.unmask_ramp <= 1.0 and 0.0 <= self.cfg.unmask_ramp_start <= 1.0):
            raise UserError(f"unmask_ramp and unmask_ramp_start must lie in [0, 1], got {self.cfg.unmask_ramp} "
                            f"and {self.cfg.unmask_ramp_start}", hint="unmask_ramp 0 keeps lambda_unmask constant")
        if self.cfg.unmask_margin < 0:
            raise UserError(f"unmask_margin must not be negative, got {self.cfg.unmask_margin}")
        self.device = device if isinstance(device, torch.device) else (
            next(field.parameters()).device if device is None else get_device(device))
        self.on_snapshot = on_snapshot
        self.gen = torch.Generator().manual_seed(self.cfg.seed)

        bg = scene.background if scene.background is not None else (1.0, 1.0, 1.0)
        self.background = torch.tensor(bg, dtype=torch.float32, device=self.device)
        self._prepare_views(masks)
        self._initial = self._state_copy()
        self.guidance = as_guidance(kind) if spec is None else \
            spec.factory(self, registry.GuidanceInputs(sd_path, color, negative_prompt))
        self.clip = self._build_clip(clip_path)

        self.optimizer = self._make_optimizer()
        self.schedule = LRSchedule("exp", 0.1)  # both presets: lr x 0.1^(step / steps)
        self.step_count = 0
        self.train_seconds = 0.0
        self.skipped_steps = 0
        self.progress = Progress(self.cfg.steps)
        self.spikes = SpikeDetector()  # on the unmask loss: the guidance loss swings with t by design
        self.done = False
        self.cancelled = False
        self.version = None
        self.history: list[dict] = []
        self._paused = threading.Event()
        self._cancel = threading.Event()
        self._lock = threading.RLock()
        # Start the grid's step counter past its warm-up so updates sample (not sweep) the grid.
        self._grid_step0 = ((getattr(grid, "warmup_steps", 0) // 16) + 1) * 16 if grid is not None else 0
        self.region = None
        if self.cfg.grow_region and self.guidance.grow_region and grid is not None:
            self.region = self._region()
            mark_region_occupied(grid, self.region, self.bound)

    # -- set-up -------------------------------------------------------------------------------------
    @property
    def bound(self) -> float:
        cfg = getattr(self.field, "cfg", None)
        return float(getattr(cfg, "bound", getattr(self.field, "bound", 1.0)))

    def _prepare_views(self, masks) -> None:
        split = self.scene.train
        n = len(split)
        if masks is None:
            if self.workspace is None:
                raise UserError("no selection to repaint", hint="run `repaint-nerf select` first")
            from repaint_nerf.core.select.masks import load_masks

            masks = load_masks(self.workspace.masks_dir)
        if len(masks) != n:
            raise UserError(f"the selection has {len(masks)} masks for {n} training views",
                            getattr(self.workspace, "masks_dir", None),
                            hint="make the selection again: repaint-nerf select")
        if not any(np.asarray(m).any() for m in masks):
            raise UserError("the selection is empty in every view",
                            hint="select again with a lower threshold or another patch")
        w0, h0 = int(split.images[0].shape[1]), int(split.images[0].shape[0])
        res = self.cfg.resolution or default_resolution(w0, h0, self.device)
        self.scale = min(1.0, res / max(w0, h0))
        cams = self.scene.field_cameras("train").scaled(self.scale).to(self.device)
        self.cameras = cams
        self.rays, self.images, self.masks, self.keep = [], [], [], []
        for i in range(n):
            w, h = int(cams.width[i]), int(cams.height[i])
            img = target_image(_resize(np.asarray(split.images[i]), w, h), self.background)
            m = _resize(np.asarray(masks[i], np.float32), w, h) > 0.5
            m = torch.from_numpy(m).to(self.device).float()
            m = dilate(m, self.cfg.mask_dilation)
            o, d, _ = cams.image_rays(i)
            self.rays.append((o, d))
            self.images.append(img)
            self.masks.append(m)
            self.keep.append(1.0 - dilate(m, self.cfg.unmask_margin))
        self.size = (int(cams.height[0]), int(cams.width[0]))

    def _region(self) -> Tensor:
        return selection_region(self.cameras, self.masks, self.bound, self.cfg.region_resolution)

    def widen_masks(self, pixels: int) -> None:
        """Grow every view's mask by `pixels` (the unmask loss then holds only what is left outside)."""
        self.masks = [dilate(m, pixels) for m in self.masks]
        self.keep = [1.0 - dilate(m, self.cfg.unmask_margin) for m in self.masks]

    def edited_targets(self) -> list[Tensor]:
        """The scene's edited/ views at the edit resolution, (1, 3, H, W) each, moved `analytic_drift` toward
        DRIFT_TINT where the edit leaves the original view alone (the analytic guidance's targets).

        The drift stands in for a diffusion model repainting what the prompt does not ask for; like Stable
        Diffusion it never sees the selection, so it paints the whole edited object wherever the mask ends and
        drifts only what the edit leaves unchanged (within UNCHANGED_TOL of the original)."""
        targets = [target_image(_resize(im, self.size[1], self.size[0]), self.background).permute(2, 0, 1)[None]
                   for im in edited_images(self.scene)]
        if self.cfg.analytic_drift > 0:
            tint = torch.tensor(DRIFT_TINT, device=self.device).view(1, 3, 1, 1)
            targets = [t.to(self.device) for t in targets]
            origs = [im.permute(2, 0, 1)[None] for im in self.images]
            targets = [t + self.cfg.analytic_drift * unchanged(t, o) * (tint - t) for t, o in zip(targets, origs)]
        return targets

    def _build_clip(self, clip_path):
        if self.cfg.lambda_clip <= 0:
            return None
        from repaint_nerf.core.models.paths import resolve_model_path
        from repaint_nerf.core.repaint.clip_loss import build_clip_loss

        settings = self.workspace.settings if self.workspace is not None else None
        resolve_model_path("clip", clip_path, settings)  # a missing model fails now, not at step 1
        return build_clip_loss(self.cfg.lambda_clip, self.bg_prompt, clip_path, settings, device=self.device)

    def _make_optimizer(self) -> Adan:
        groups = (self.field.parameter_groups() if hasattr(self.field, "parameter_groups")
                  else {"all": list(self.field.parameters())})
        groups = {k: v for k, v in groups.items() if k != "feature"}  # never rendered, never decayed
        if self.cfg.optimizer == "paper":
            lr, mult = self.cfg.lr or PAPER_LR, {}
        elif self.cfg.optimizer == "official":
            lr, mult = self.cfg.lr or OFFICIAL_LR, OFFICIAL_MULTIPLIERS
        else:
            raise UserError(f"unknown optimizer preset {self.cfg.optimizer!r}", hint="use 'paper' or 'official'")
        return Adan(param_groups(groups, lr, mult))

    def _state_copy(self) -> dict:
        st = {"field": {k: v.detach().clone() for k, v in self.field.state_dict().items()}}
        if self.grid is not None:
            st["grid"] = {k: (v.clone() if isinstance(v, Tensor) else v) for k, v in self.grid.state_dict().items()}
        return st

    # -- one step -----------------------------------------------------------------------------------
    def render_view(self, view: int, grad: bool = True, pause: Callable[[], None] | None = None) -> Tensor:
        """Render training view `view` at the edit resolution as (1, 3, H, W) (rgb only); `pause` as
        RenderOptions.pause (the step's interlude)."""
        o, d = self.rays[view]
        opts = RenderOptions(outputs=("rgb",), background=self.background, t_threshold=self.cfg.t_threshold,
                             max_samples=self.cfg.max_samples, perturb=self.cfg.perturb and grad, pause=pause)
        with torch.set_grad_enabled(grad):
            out = render_rays(self.field, self.grid, o, d, opts)
        h, w = self.size
        return out["rgb"].reshape(h, w, 3).permute(2, 0, 1)[None]

    def unmask_loss(self, rgb: Tensor, view: int) -> Tensor:
        """Paper Eq. unmask on training view `view`, reduced per `unmask_reduction` (objective.unmask_loss)."""
        target = self.images[view].permute(2, 0, 1)[None]
        return unmask_loss(rgb, target, self.keep[view][None, None], self.cfg.unmask_reduction)

    def unmasked_psnr(self, rgb: Tensor, view: int) -> float | None:
        """PSNR (dB) of the pixels Eq. unmask holds in this render against the photo; None when it holds none or
        the render is not finite."""
        target = self.images[view].permute(2, 0, 1)[None]
        mse = masked_mse(rgb, target, self.keep[view][None, None])
        return None if mse is None or not bool(torch.isfinite(mse)) else mse_to_psnr(mse)

    def step(self, interlude: Callable[[], None] | None = None) -> dict:
        """One edit step on a random view; returns its losses, the unmasked PSNR ('psnr', when the step was not
        skipped) and whether it was skipped. `interlude()`, when given, runs at each marching round's start and
        before the differentiable pass of the view's render, and once the guidance has been computed, before the
        backward pass (the editor's worker renders a new view there); its time is not the step's."""

        def pause() -> None:
            nonlocal t0
            paused = time.perf_counter()
            interlude()
            t0 += time.perf_counter() - paused

        with self._lock:
            t0 = time.perf_counter()
            self.field.train()
            if self.grid is not None:
                self.grid.update(self._grid_step0 + self.step_count, self.field.density)
            progress = self.step_count / max(1, self.cfg.steps)
            self.optimizer.set_lr_factor(self.schedule.factor(progress))
            view = int(torch.randint(0, len(self.rays), (1,), generator=self.gen))
            rgb = self.render_view(view, pause=None if interlude is None else pause)
            mask = self.masks[view][None, None]
            g = self.guidance.loss(rgb, mask, view, self.step_count)
            info: dict[str, Any] = {"view": view, "t": int(g.get("t", 0)), "guidance": float(g["loss"].detach())}
            skipped = bool(g.get("skipped", False))
            self.optimizer.zero_grad(set_to_none=True)
            if not skipped:
                unmask = self.unmask_loss(rgb, view)
                info["unmask"] = float(unmask.detach())
                kept = self.unmasked_psnr(rgb, view)
                if kept is not None:
                    info["psnr"] = kept
                c = self.clip.loss(rgb, mask) if self.clip is not None else None
                if c is not None:
                    info["clip"] = float(c.detach())
                lam = unmask_weight(self.cfg.lambda_unmask, progress, self.cfg.unmask_ramp, self.cfg.unmask_ramp_start)
                info["lambda_unmask"] = lam
                total = stage2_loss(g["loss"], unmask, lam, c, self.cfg.lambda_clip)
                fl = self.guidance.field_loss(self.field, self.step_count)
                if fl is not None:
                    total = total + fl
                    info["field"] = float(fl.detach())
                if interlude is not None:
                    pause()
                if bool(torch.isfinite(total)):
                    total.backward()
                    before = self.optimizer.skipped_steps
                    self.optimizer.step()
                    skipped = self.optimizer.skipped_steps > before
                else:
                    skipped = True
                info["loss"] = float(total.detach())
            if skipped:
                self.skipped_steps += 1
                self.optimizer.zero_grad(set_to_none=True)
            self.step_count += 1
            synchronize(self.device)
            dt = time.perf_counter() - t0
            self.train_seconds += dt
            info.update(spike=self.spikes.update(info.get("unmask", float("nan"))), spikes=self.spikes.spikes)
            self.progress.update(dt)
            info.update(step=self.step_count, skipped=skipped, skipped_steps=self.skipped_steps, seconds=dt,
                        phase="repaint", lr=float(self.optimizer.param_groups[0]["lr"]), steps=self.cfg.steps,
                        eta_s=self.progress.seconds_left(self.step_count))
            self.history.append(info)
            if self.on_snapshot is not None and self.cfg.snapshot_every and \
                    self.step_count % self.cfg.snapshot_every == 0:
                self.on_snapshot(self.snapshot())
            if self.step_count >= self.cfg.steps:
                self.finish()
                info["done"] = True
            return info

    def time_field_step(self) -> float:
        """Seconds of one render + backward of view 0 at the edit resolution (no update: the field is unchanged)."""
        synchronize(self.device)
        t0 = time.perf_counter()
        rgb = self.render_view(0)
        rgb.float().sum().backward()
        synchronize(self.device)
        dt = time.perf_counter() - t0
        self.optimizer.zero_grad(set_to_none=True)
        return dt

    def estimate(self, time_field: bool = True) -> Estimate:
        """Expected duration of this edit (core.repaint.estimate), with a timed field step when `time_field`."""
        est = estimate_repaint(self.kind, self.cfg.steps, self.size, self.device,
                               field_step_seconds=self.time_field_step() if time_field else None,
                               unet_precision=self.cfg.sd_unet_precision,
                               tiny_autoencoder=bool(self.cfg.sd_tiny_autoencoder),
                               sds_resolution=self.cfg.sds_resolution, token_merging=self.cfg.sd_token_merging)
        self.progress.prior = est.step_seconds
        return est

    @torch.no_grad()
    def snapshot(self, view: int | None = None) -> dict:
        """A preview render of a training view at the edit resolution: {'step', 'view', 'rgb' (H, W, 3) numpy}."""
        v = self.cfg.snapshot_view if view is None else view
        rgb = self.render_view(min(v, len(self.rays) - 1), grad=False)[0].permute(1, 2, 0).clamp(0, 1)
        return {"step": self.step_count, "view": v, "rgb": rgb.cpu().numpy()}

    # -- running, pausing, cancelling ---------------------------------------------------------------
    def pause(self) -> None:
        """Stop stepping after the current step until `resume` (thread-safe)."""
        self._paused.set()

    def resume(self) -> None:
        self._paused.clear()

    @property
    def paused(self) -> bool:
        return self._paused.is_set()

    def cancel(self) -> None:
        """Stop the edit and restore the field and grid as they were before it (thread-safe)."""
        self._cancel.set()
        with self._lock:
            if not self.cancelled and not self.done:
                self.field.load_state_dict(self._initial["field"])
                if self.grid is not None and "grid" in self._initial:
                    self.grid.load_state_dict(self._initial["grid"])
                self.cancelled = True

    def run(self, callback: Callable[[dict], Any] | None = None, poll: float = 0.05) -> dict | None:
        """Step until done or cancelled (waiting while paused); `callback(info)` after each step."""
        info = None
        while not self.done and not self._cancel.is_set():
            if self._paused.is_set():
                time.sleep(poll)
                continue
            info = self.step()
            if callback is not None:
                callback(info)
        return info

    def train_for(self, seconds: float, stop: Callable[[], bool] | None = None,
                  interlude: Callable[[], None] | None = None) -> dict:
        """Step for about `seconds` (at least one step), ending early once `stop()` turns true; the editor's
        worker calls this between renders and stops it when the user moves the camera, and renders a new view
        within a step through `interlude` (`step`)."""
        info: dict = {"phase": "repaint", "step": self.step_count, "done": self.done}
        t_end = time.perf_counter() + seconds
        while not self.done and not self._cancel.is_set() and not self._paused.is_set():
            info = self.step(interlude)
            if time.perf_counter() >= t_end or (stop is not None and stop()):
                break
        info = dict(info)
        info["done"] = self.done
        return info

    # -- saving ---------------------------------------------------------------------------------------
    def checkpoint(self) -> Checkpoint:
        """The edited field and grid in the stage-1 checkpoint layout (loads with restore_field)."""
        from repaint_nerf.core.train.header import EDIT, CheckpointHeader, EditFacts, GridFacts, SceneFacts

        tensors = {f"field.{k}": v.detach().cpu() for k, v in self.field.state_dict().items()}
        grid_t, grid_rest = split_state(self.grid.state_dict())
        tensors.update({f"grid.{k}": v for k, v in grid_t.items()})
        header = CheckpointHeader(
            kind=EDIT, field_config=dataclasses.asdict(self.field.cfg),
            grid=GridFacts(self.grid.resolution, self.grid.cascades, self.grid.bound, grid_rest),
            scene=SceneFacts.of(self.scene),
            edit=EditFacts(guidance=self.kind, prompt=self.prompt, bg_prompt=self.bg_prompt, steps=self.step_count,
                           skipped_steps=self.skipped_steps, config=dataclasses.asdict(self.cfg)))
        return Checkpoint.of(tensors, header)

    def finish(self) -> None:
        """Mark the edit done and save it as a new workspace version (when there is a workspace)."""
        if self.done:
            return
        self.done = True
        self.field.eval()
        if self.workspace is not None:
            name = f"{self.kind}: {self.prompt}".strip().rstrip(":")
            self.version = self.workspace.save_version(name[:80], self.checkpoint(), kind="edit")

    def evaluate(self, split: str = "test", masks: list[np.ndarray] | None = None,
                 targets: list[np.ndarray] | None = None) -> dict:
        """Render a split: PSNR inside `masks` against `targets` and outside against the split's images."""
        cams = self.scene.field_cameras(split).to(self.device)
        data = self.scene.split(split)
        opts = RenderOptions(outputs=("rgb",), background=self.background, max_samples=self.cfg.max_samples,
                             t_threshold=self.cfg.t_threshold)
        self.field.eval()
        se_in = n_in = se_out = n_out = 0.0
        for i in range(len(data)):
            rgb = render_camera(self.field, self.grid, cams, i, opts)["rgb"].clamp(0, 1)
            m = torch.from_numpy(np.asarray(masks[i], bool)).to(self.device) if masks is not None else \
                torch.zeros(rgb.shape[:2], dtype=torch.bool, device=self.device)
            orig = target_image(np.asarray(data.images[i]), self.background)
            d_out = ((rgb - orig) ** 2).sum(-1)
            se_out += float(d_out[~m].sum())
            n_out += 3 * float((~m).sum())
            if targets is not None:
                tgt = target_image(np.asarray(targets[i]), self.background)
                se_in += float(((rgb - tgt) ** 2).sum(-1)[m].sum())
                n_in += 3 * float(m.sum())
        self.field.train()

        def ps(se, n):
            return float("nan") if n == 0 else (float("inf") if se == 0 else -10 * np.log10(se / n))

        return {"psnr_masked": ps(se_in, n_in), "psnr_unmasked": ps(se_out, n_out)}
