"""The one CLIP loader: transformers CLIPModel + tokenizer + preprocessing constants from a local folder.

Preprocessing is returned as numbers (image size, mean, std) so callers can resize and normalise in
torch and keep the image differentiable, instead of going through the PIL image processor.
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor

from repaint_nerf.core.device import get_device
from repaint_nerf.core.errors import ModelNotFoundError, UserError
from repaint_nerf.core.models.paths import how_to_set

# OpenAI CLIP's normalisation; used when the folder has no preprocessor_config.json.
CLIP_MEAN = (0.48145466, 0.4578275, 0.40821073)
CLIP_STD = (0.26862954, 0.26130258, 0.27577711)


@dataclass
class Clip:
    """A frozen CLIP model with its tokenizer and the image size / normalisation it expects."""

    model: torch.nn.Module
    tokenizer: object
    image_size: int
    mean: tuple[float, float, float]
    std: tuple[float, float, float]
    device: torch.device

    @torch.no_grad()
    def encode_text(self, prompts: list[str]) -> Tensor:
        """Projected text embeddings (B, D), fp32, not normalised."""
        if self.tokenizer is None:
            raise UserError("this CLIP folder has no tokenizer files, so it cannot encode text",
                            hint="copy the tokenizer files (vocab.json, merges.txt) of the model into the folder")
        tok = self.tokenizer(prompts, padding=True, truncation=True, return_tensors="pt").to(self.device)
        return _pooled(self.model.get_text_features(input_ids=tok.input_ids,
                                                    attention_mask=tok.attention_mask)).float()

    def encode_image(self, pixel_values: Tensor) -> Tensor:
        """Projected image embeddings (B, D) of already resized and normalised images, with gradient."""
        return _pooled(self.model.get_image_features(pixel_values=pixel_values)).float()


def _pooled(out) -> Tensor:
    # transformers < 5 returns the embedding tensor; 5.x returns an output whose pooler_output is projected
    return out if isinstance(out, Tensor) else out.pooler_output


def _preprocessing(path: Path, model) -> tuple[int, tuple, tuple]:
    size = int(model.config.vision_config.image_size)
    mean, std = CLIP_MEAN, CLIP_STD
    cfg_file = path / "preprocessor_config.json"
    if cfg_file.exists():
        try:
            cfg = json.loads(cfg_file.read_text())
        except json.JSONDecodeError as exc:
            raise ModelNotFoundError(f"unreadable preprocessor_config.json: {exc}", path=cfg_file,
                                     hint="fix or delete the file (CLIP defaults are used without it)") from exc
        mean = tuple(cfg.get("image_mean", mean))
        std = tuple(cfg.get("image_std", std))
    return size, mean, std


def _tokenizer(cls, path: Path, required: bool):
    """The folder's tokenizer; None when it has none and none is `required`."""
    try:
        return cls.from_pretrained(path, local_files_only=True)
    except (OSError, ValueError, TypeError):
        if required:
            raise
        return None


def load_clip(path: str | os.PathLike, device: torch.device | str | None = None, need_tokenizer: bool = True) -> Clip:
    """Load a CLIP model folder (config.json, weights, tokenizer files) with `local_files_only=True`.
    `need_tokenizer=False` (image features only) loads a folder without tokenizer files (tokenizer None)."""
    from transformers import CLIPModel, CLIPTokenizer

    path = Path(path).expanduser()
    if not path.is_dir():
        raise ModelNotFoundError("the CLIP model folder does not exist", path=path, hint=how_to_set("clip"))
    if not (path / "config.json").exists():
        raise ModelNotFoundError("not a transformers CLIP folder: config.json is missing", path=path,
                                 hint="point at a folder saved by CLIPModel.save_pretrained, with its tokenizer")
    dev = get_device(str(device)) if device is not None else get_device()
    try:
        model = CLIPModel.from_pretrained(path, local_files_only=True, torch_dtype=torch.float32)
        tokenizer = _tokenizer(CLIPTokenizer, path, need_tokenizer)
    except (OSError, ValueError) as exc:
        raise ModelNotFoundError(f"could not load the CLIP model: {exc}", path=path,
                                 hint="the folder needs config.json, the weights and the tokenizer files "
                                      "(vocab.json, merges.txt)") from exc
    model.eval().requires_grad_(False).to(dev)
    size, mean, std = _preprocessing(path, model)
    return Clip(model=model, tokenizer=tokenizer, image_size=size, mean=mean, std=std, device=dev)
