"""The one loader of transformers vision backbones used as dense feature teachers (DINOv2, CLIP, SigLIP),
from a local folder with `local_files_only=True`, with the numbers their preprocessing needs.

CLIP folders are loaded through core.models.clip (the one CLIP loader), so the same model also encodes
text (MaskCLIP-style text selection, core/teachers/feature_hf.py).
"""
from __future__ import annotations

import contextlib
import json
import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import torch

from repaint_nerf.core.device import get_device
from repaint_nerf.core.errors import ModelNotFoundError
from repaint_nerf.core.models.frozen import FrozenNet
from repaint_nerf.core.models.paths import locate_model, model_type

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
HALF = (0.5, 0.5, 0.5)
# model_type -> (family, default mean/std when the folder has no preprocessor_config.json)
BACKBONES = {
    "dinov2": ("dinov2", IMAGENET_MEAN, IMAGENET_STD),
    "dinov2_with_registers": ("dinov2", IMAGENET_MEAN, IMAGENET_STD),
    "clip": ("clip", None, None),
    "clip_vision_model": ("clip_vision", None, None),
    "siglip": ("siglip", HALF, HALF),
    "siglip_vision_model": ("siglip", HALF, HALF),
}


@dataclass
class VisionBackbone(FrozenNet):
    """A frozen vision transformer: `family` says how its patch tokens are read (dinov2, clip, clip_vision,
    siglip); `clip` is the core.models.clip.Clip of a full CLIP folder (text encoder included), else None."""

    family: str
    patch_size: int
    image_size: int
    prefix_tokens: int
    clip: object | None = None


@contextlib.contextmanager
def quiet_transformers() -> Iterator[None]:
    """Silence transformers' load reports and progress bars (a tower loaded out of a two-tower checkpoint
    lists every unused weight) for the duration of a load; errors still raise."""
    from transformers.utils import logging as tlog

    level, bars = tlog.get_verbosity(), tlog.is_progress_bar_enabled()
    tlog.set_verbosity_error()
    tlog.disable_progress_bar()
    try:
        yield
    finally:
        tlog.set_verbosity(level)
        if bars:
            tlog.enable_progress_bar()


def preprocessor_stats(path: Path, mean, std) -> tuple[tuple, tuple, dict]:
    """(mean, std, the whole preprocessor_config.json or {}) of a model folder; defaults when it is absent."""
    cfg_file = Path(path) / "preprocessor_config.json"
    if not cfg_file.is_file():
        return tuple(mean), tuple(std), {}
    try:
        cfg = json.loads(cfg_file.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise ModelNotFoundError(f"unreadable preprocessor_config.json ({exc})", path=cfg_file,
                                 hint="fix or delete the file (the model's defaults are used without it)") from exc
    return tuple(cfg.get("image_mean", mean)), tuple(cfg.get("image_std", std)), cfg


def check_backbone(path: Path) -> str:
    """config.json's model_type of a supported backbone folder, else a ModelNotFoundError listing them."""
    kind = model_type(path)
    if kind not in BACKBONES:
        raise ModelNotFoundError(f"config.json's model_type '{kind}' is not a supported feature backbone",
                                 path=path, hint=f"use one of: {', '.join(sorted(BACKBONES))} (or an ONNX export)")
    return kind


def load_vision_backbone(path: str | os.PathLike, device: torch.device | str | None = None) -> VisionBackbone:
    """Load a DINOv2 / CLIP / SigLIP folder or cached model id (config.json + weights) frozen, in fp32, on `device`."""
    path = locate_model("feature", path)
    kind = check_backbone(path)
    family, mean, std = BACKBONES[kind]
    dev = get_device(str(device)) if device is not None else get_device()
    clip = None
    try:
        with quiet_transformers():
            if family == "clip":
                from repaint_nerf.core.models.clip import load_clip

                clip = load_clip(path, dev, need_tokenizer=False)
                model, mean, std = clip.model, clip.mean, clip.std
            else:
                model = _model_class(kind).from_pretrained(path, local_files_only=True, torch_dtype=torch.float32)
    except (OSError, ValueError) as exc:
        raise ModelNotFoundError(f"could not load the {kind} model: {str(exc).splitlines()[0][:300]}", path=path,
                                 hint="the folder needs config.json and the weights (model.safetensors)") from exc
    model.eval().requires_grad_(False).to(dev)
    if family in ("clip", "clip_vision"):
        from repaint_nerf.core.models.clip import CLIP_MEAN, CLIP_STD

        mean, std = mean or CLIP_MEAN, std or CLIP_STD
    mean, std, _ = preprocessor_stats(path, mean, std)
    vcfg = getattr(model.config, "vision_config", None) or model.config
    prefix = {"dinov2": 1 + int(getattr(vcfg, "num_register_tokens", 0) or 0), "siglip": 0}.get(family, 1)
    return VisionBackbone(model=model, family=family, model_type=kind, patch_size=int(vcfg.patch_size),
                          image_size=int(vcfg.image_size), mean=tuple(map(float, mean)), std=tuple(map(float, std)),
                          prefix_tokens=prefix, device=dev, path=path, clip=clip)


def _model_class(kind: str):
    import transformers

    return getattr(transformers, {"dinov2": "Dinov2Model", "dinov2_with_registers": "Dinov2WithRegistersModel",
                                  "clip_vision_model": "CLIPVisionModel", "siglip": "SiglipVisionModel",
                                  "siglip_vision_model": "SiglipVisionModel"}[kind])
