"""Stage 2 of the paper: guidance backends for repainting the selected region (Eq. SDS, Eq. clip).

`build_guidance(kind, ...)` returns a backend with `loss(rgb, mask, view, step) -> dict`.
"""
from __future__ import annotations

import os
from collections.abc import Mapping
from typing import Any

from core.repaint.guidance import Guidance, GuidanceResult

__all__ = ["Guidance", "GuidanceResult", "build_guidance"]


def build_guidance(kind: str, *, prompt: str = "", negative_prompt: str = "",
                   sd_path: str | os.PathLike | None = None, settings: Mapping[str, Any] | None = None,
                   targets=None, device=None, cpu_offload: bool = False,
                   sd_config: str | os.PathLike | None = None, sd_family: str | None = None,
                   prediction_type: str | None = None, **options) -> Guidance:
    """A guidance backend: 'sd' (Stable Diffusion from flag > env > settings) or 'analytic' (needs `targets`).

    `sd_config`, `sd_family`, `prediction_type` go to the SD loader (core.models.sd.load_stable_diffusion);
    `options` go to the backend (guidance_scale, t_range, clip_value, clip_norm, seed).
    """
    if kind == "sd":
        from core.models.paths import resolve_model_path
        from core.models.sd import load_stable_diffusion
        from core.repaint.sds import SDSGuidance

        sd = load_stable_diffusion(resolve_model_path("sd", sd_path, settings), device=device,
                                   cpu_offload=cpu_offload, config=sd_config, family=sd_family,
                                   prediction_type=prediction_type)
        return SDSGuidance(sd, prompt, negative_prompt, **options)
    if kind == "analytic":
        from core.repaint.analytic import AnalyticGuidance

        if targets is None:
            raise ValueError("analytic guidance needs `targets` (the edited renders of the training views)")
        return AnalyticGuidance(targets, **options)
    from core.errors import UserError

    raise UserError(f"unknown guidance backend {kind!r}", hint="use 'sd' or 'analytic'")
