"""The guidance backends, listed once: what each is called, how it is built, what it needs and what it offers.

The CLI's --guidance choices and help, the editor's Guidance list and model fields, the engine's and the
trainer's checks, and the CLIP weight's default all read `GUIDANCES`; a new backend is one record here.
Light to import (no torch): factories import their backend when called.
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable

from repaint_nerf.core.errors import UserError

if TYPE_CHECKING:
    from repaint_nerf.core.repaint.config import RepaintConfig
    from repaint_nerf.core.repaint.guidance import Guidance
    from repaint_nerf.core.repaint.trainer import RepaintTrainer

REMOVE_WORDS = re.compile(r"\b(remove|delete|erase|get rid of|take away|without)\b", re.I)
OFFICIAL_CLIP_WEIGHT = 0.01  # lambda_clip of the official code, which runs the CLIP loss with Stable Diffusion only


@dataclass(frozen=True)
class GuidanceInputs:
    """What a user gives a backend beyond the prompts and the selection."""

    sd_path: Any = None  # Stable Diffusion folder / file / cached id (flag > env > workspace settings)
    color: Any = None  # recolour target, 'R,G,B' or '#rrggbb' (else a colour named in the prompt)
    negative_prompt: str = ""


@dataclass(frozen=True)
class GuidanceSpec:
    """One guidance backend: its name, factory, needs, default CLIP weight and help text."""

    name: str
    help: str
    # Builds the backend for a trainer whose views, masks and config are prepared; None for `offline`, which
    # `pick` resolves to another record first.
    factory: Callable[[RepaintTrainer, GuidanceInputs], Guidance] | None
    needs_prompt: bool  # the prompt is required (sd: the text condition; offline: it picks the edit)
    model: str | None = None  # the model kind it loads ('sd'; core.models.paths names its flag and env var)
    clip_weight: float = 0.0  # lambda_clip when the config leaves it None (paper Eq. clip)
    needs_edited: bool = False  # the scene must have an edited/ variant (synthetic scenes only)
    extras: tuple[str, ...] = ()  # the optional Guidance members it overrides (core.repaint.guidance.EXTRAS)
    pick: Callable[[str], str] | None = None  # prompt -> the record that does the work (offline only)


def offline_kind(prompt: str) -> str:
    """'remove' when the prompt asks to remove (remove, delete, erase, ...), else 'recolor'."""
    return "remove" if REMOVE_WORDS.search(prompt or "") else "recolor"


def _recolor(t: RepaintTrainer, inputs: GuidanceInputs) -> Guidance:
    from repaint_nerf.core.repaint.colors import resolve_color
    from repaint_nerf.core.repaint.recolor import RecolorGuidance

    rgb = resolve_color(t.prompt, inputs.color)
    return RecolorGuidance(t.images, t.masks, rgb, t.cfg.recolor_mode, reduction=t.cfg.unmask_reduction)


def _remove(t: RepaintTrainer, inputs: GuidanceInputs) -> Guidance:
    from repaint_nerf.core.repaint.region import selection_region
    from repaint_nerf.core.repaint.remove import RemoveGuidance

    region = selection_region(t.cameras, t.masks, t.bound, t.cfg.region_resolution)
    # Inpaint (and leave free of the unmask loss) a rim around the object's soft edges too.
    t.widen_masks(max(1, round(max(t.size) / 64)))
    return RemoveGuidance(t.images, t.masks, region, t.bound, clear_weight=t.cfg.remove_clear_weight, seed=t.cfg.seed,
                          reduction=t.cfg.unmask_reduction)


def _analytic(t: RepaintTrainer, inputs: GuidanceInputs) -> Guidance:
    from repaint_nerf.core.repaint.analytic import AnalyticGuidance

    return AnalyticGuidance(t.edited_targets(), seed=t.cfg.seed)


def _sd(t: RepaintTrainer, inputs: GuidanceInputs) -> Guidance:
    from repaint_nerf.core.repaint import build_guidance

    settings = t.workspace.settings if t.workspace is not None else None
    return build_guidance("sd", prompt=t.prompt, negative_prompt=inputs.negative_prompt, sd_path=inputs.sd_path,
                          settings=settings, device=t.device, seed=t.cfg.seed,
                          unet_precision=t.cfg.sd_unet_precision, tiny_autoencoder=t.cfg.sd_tiny_autoencoder,
                          channels_last=t.cfg.sd_channels_last, token_merging=t.cfg.sd_token_merging,
                          sds_resolution=t.cfg.sds_resolution,
                          t_schedule=t.cfg.t_schedule, total_steps=t.cfg.steps, sd_config=t.cfg.sd_config,
                          sd_family=t.cfg.sd_family, prediction_type=t.cfg.sd_prediction_type)


GUIDANCES: dict[str, GuidanceSpec] = {s.name: s for s in (
    GuidanceSpec("offline", "recolor or remove, read from the prompt (no model)", None, needs_prompt=True,
                 pick=offline_kind),
    GuidanceSpec("recolor", "recolour the selection to a colour named in the prompt or given as --color, "
                            "keeping its shading (no model)", _recolor, needs_prompt=False,
                 extras=("grow_region",)),
    GuidanceSpec("remove", "remove the object and fill in behind it (no model)", _remove, needs_prompt=False,
                 extras=("grow_region", "field_loss")),
    GuidanceSpec("sd", "Stable Diffusion score distillation (a local model), with the CLIP background loss",
                 _sd, needs_prompt=True, model="sd", clip_weight=OFFICIAL_CLIP_WEIGHT),
    GuidanceSpec("analytic", "exact denoiser of a synthetic scene's edited/ variant (measurement)", _analytic,
                 needs_prompt=False, needs_edited=True),
)}


def get(name: str) -> GuidanceSpec:
    """The record of backend `name`; a UserError naming the known ones otherwise."""
    try:
        return GUIDANCES[name]
    except (KeyError, TypeError):
        raise UserError(f"unknown guidance {name!r}", hint=f"use one of: {', '.join(GUIDANCES)}") from None


def resolve(name: str, prompt: str = "") -> GuidanceSpec:
    """The record that does the work for `name` and `prompt` (offline -> recolor or remove)."""
    spec = get(name)
    return get(spec.pick(prompt)) if spec.pick is not None else spec


def clip_weight(name: str | None, cfg: RepaintConfig) -> float:
    """lambda_clip for an edit: the config's when set, else the backend's default (0 for unknown objects)."""
    if cfg.lambda_clip is not None:
        return float(cfg.lambda_clip)
    spec = GUIDANCES.get(name) if isinstance(name, str) else None
    return spec.clip_weight if spec is not None else 0.0


def models_needed(name: str, cfg: RepaintConfig) -> tuple[str, ...]:
    """The model kinds an edit loads: the backend's own, and CLIP when the background loss is on."""
    spec = get(name)
    return ((spec.model,) if spec.model else ()) + (("clip",) if clip_weight(name, cfg) > 0 else ())


def help_text() -> str:
    """'name: help; ...' for every backend (the CLI's --guidance help)."""
    return "; ".join(f"{s.name}: {s.help}" for s in GUIDANCES.values())
