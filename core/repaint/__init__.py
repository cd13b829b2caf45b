"""Stage 2 of the paper: guidance backends for repainting the selected region (Eq. SDS, Eq. clip).

`build_guidance(kind, ...)` returns a backend with `loss(rgb, mask, view, step) -> dict`; the backends are
listed in `core.repaint.registry`. The package imports no torch until a backend is used, so the CLI's flags
and the editor's fields can read `core.repaint.config` and the registry cheaply.
"""
from __future__ import annotations

import os
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from repaint_nerf.core.repaint.guidance import Guidance, GuidanceResult

__all__ = ["Guidance", "GuidanceResult", "build_guidance"]


def __getattr__(name: str):
    if name in ("Guidance", "GuidanceResult"):
        from repaint_nerf.core.repaint import guidance

        return getattr(guidance, name)
    raise AttributeError(f"module 'repaint_nerf.core.repaint' has no attribute {name!r}")


def build_guidance(kind: str, *, prompt: str = "", negative_prompt: str = "",
                   sd_path: str | os.PathLike | None = None, settings: Mapping[str, Any] | None = None,
                   targets=None, device=None, cpu_offload: bool = False,
                   unet_precision: str = "auto", tiny_autoencoder: str | os.PathLike | None = None,
                   channels_last: bool = False, token_merging: float = 0.0,
                   sd_config: str | os.PathLike | None = None,
                   sd_family: str | None = None, prediction_type: str | None = None, **options) -> Guidance:
    """A guidance backend: 'sd' (Stable Diffusion from flag > env > settings) or 'analytic' (needs `targets`).

    `sd_config`, `sd_family`, `prediction_type` go to the SD loader (core.models.sd.load_stable_diffusion);
    `unet_precision`, `tiny_autoencoder`, `channels_last` and `token_merging` are SD's speed options
    (core.models.sd_speed);
    `options` go to the backend (guidance_scale, t_range, clip_value, clip_norm, seed, sds_resolution).
    """
    if kind == "sd":
        from repaint_nerf.core.models.paths import resolve_model_path
        from repaint_nerf.core.models.sd import load_stable_diffusion
        from repaint_nerf.core.models.sd_speed import apply_speed_options
        from repaint_nerf.core.repaint.sds import SDSGuidance

        sd = load_stable_diffusion(resolve_model_path("sd", sd_path, settings), device=device,
                                   cpu_offload=cpu_offload, config=sd_config, family=sd_family,
                                   prediction_type=prediction_type)
        apply_speed_options(sd, unet_precision, tiny_autoencoder, channels_last, token_merging)
        return SDSGuidance(sd, prompt, negative_prompt, **options)
    if kind == "analytic":
        from repaint_nerf.core.repaint.analytic import AnalyticGuidance

        if targets is None:
            raise ValueError("analytic guidance needs `targets` (the edited renders of the training views)")
        return AnalyticGuidance(targets, **options)
    from repaint_nerf.core.errors import UserError
    from repaint_nerf.core.repaint.registry import get

    get(kind)  # an unknown name: the error lists the backends
    raise UserError(f"the {kind!r} guidance is built from the repaint trainer's views",
                    hint="use core.repaint.trainer.RepaintTrainer(..., guidance=kind)")
