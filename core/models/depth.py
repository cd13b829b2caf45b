"""The one loader of transformers monocular depth models (DPT, Depth Anything: AutoModelForDepthEstimation)
from a local folder with `local_files_only=True`, with the numbers their preprocessing needs."""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import torch

from repaint_nerf.core.device import get_device
from repaint_nerf.core.errors import ModelNotFoundError
from repaint_nerf.core.models.frozen import FrozenNet
from repaint_nerf.core.models.paths import locate_model, model_type
from repaint_nerf.core.models.vision import HALF, IMAGENET_MEAN, IMAGENET_STD, preprocessor_stats, quiet_transformers

METRIC_TYPES = ("zoedepth",)  # model types that predict metric depth, not relative inverse depth


@dataclass
class DepthModel(FrozenNet):
    """A frozen depth network: input short side and size multiple, and whether it predicts relative inverse
    depth (DPT, Depth Anything relative) or depth (metric models)."""

    short_side: int
    multiple: int
    inverse: bool


def check_depth_model(path: Path) -> str:
    """config.json's model_type of a folder AutoModelForDepthEstimation can load, else a ModelNotFoundError."""
    from transformers.models.auto.modeling_auto import MODEL_FOR_DEPTH_ESTIMATION_MAPPING_NAMES as known

    kind = model_type(path)
    if kind not in known:
        raise ModelNotFoundError(f"could not load '{kind}' as a depth-estimation model (known: "
                                 f"{', '.join(sorted(known))})", path=path,
                                 hint="point --depth-model at a DPT or Depth Anything folder (or an ONNX export)")
    return kind


def load_depth_model(path: str | os.PathLike, device: torch.device | str | None = None) -> DepthModel:
    """Load a transformers depth-estimation folder or cached model id (config.json + weights) frozen, in fp32,
    on `device`."""
    from transformers import AutoModelForDepthEstimation

    path = locate_model("depth", path)
    kind = check_depth_model(path)
    dev = get_device(str(device)) if device is not None else get_device()
    try:
        with quiet_transformers():
            model = AutoModelForDepthEstimation.from_pretrained(path, local_files_only=True, torch_dtype=torch.float32)
    except (OSError, ValueError, KeyError) as exc:
        raise ModelNotFoundError(f"could not load '{kind}' as a depth-estimation model: "
                                 f"{str(exc).splitlines()[0][:300]}", path=path,
                                 hint="point --depth-model at a DPT or Depth Anything folder (or an ONNX "
                                      "export)") from exc
    model.eval().requires_grad_(False).to(dev)
    cfg = model.config
    backbone = getattr(cfg, "backbone_config", None) or cfg
    patch = int(getattr(cfg, "patch_size", None) or getattr(backbone, "patch_size", 16))
    default_mean, default_std = (HALF, HALF) if kind == "dpt" else (IMAGENET_MEAN, IMAGENET_STD)
    mean, std, pre = preprocessor_stats(path, default_mean, default_std)
    size = pre.get("size") or {}
    short = int(size.get("height") or size.get("shortest_edge") or getattr(backbone, "image_size", 384))
    multiple = int(pre.get("ensure_multiple_of") or 1)
    multiple = max(multiple, patch) if multiple % patch == 0 or patch % multiple == 0 else multiple * patch
    metric = getattr(cfg, "depth_estimation_type", "relative") == "metric" or kind in METRIC_TYPES
    return DepthModel(model=model, model_type=kind, short_side=short, multiple=multiple,
                      mean=tuple(map(float, mean)), std=tuple(map(float, std)), inverse=not metric,
                      device=dev, path=path)
