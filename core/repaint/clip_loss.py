"""The CLIP background loss (paper Eq. clip): -cos(CLIP(render with the mask blacked out), CLIP(bg prompt)).

Resizing and normalisation are done in torch so the loss stays differentiable. The model loads lazily
on the first call, so a trainer with lambda_clip = 0 never touches it (use `build_clip_loss`).
"""
from __future__ import annotations

import os
from collections.abc import Mapping
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor

from repaint_nerf.core.models.clip import Clip


def clip_preprocess(img: Tensor, size: int, mean, std) -> Tensor:
    """CLIP's resize (short side to `size`, bicubic) + centre crop + normalise, differentiable; (B,3,H,W) in [0,1]."""
    h, w = img.shape[-2:]
    scale = size / min(h, w)
    nh, nw = max(size, round(h * scale)), max(size, round(w * scale))
    x = F.interpolate(img, size=(nh, nw), mode="bicubic", align_corners=False, antialias=scale < 1)
    top, left = (nh - size) // 2, (nw - size) // 2
    x = x[..., top:top + size, left:left + size]
    m = torch.tensor(mean, device=x.device, dtype=x.dtype).view(1, 3, 1, 1)
    s = torch.tensor(std, device=x.device, dtype=x.dtype).view(1, 3, 1, 1)
    return (x - m) / s


class ClipBackgroundLoss:
    """-cosine between the masked-out render and the background prompt; text embedding cached."""

    def __init__(self, prompt: str, path: str | os.PathLike | None = None,
                 settings: Mapping[str, Any] | None = None, clip: Clip | None = None,
                 device: torch.device | str | None = None, eps: float = 1e-8):
        self.prompt, self.path, self.settings, self.device, self.eps = prompt, path, settings, device, eps
        self._clip = clip
        self._text: Tensor | None = None

    @property
    def clip(self) -> Clip:
        """The CLIP model, loaded on first use from flag > env var > settings."""
        if self._clip is None:
            from repaint_nerf.core.models.clip import load_clip
            from repaint_nerf.core.models.paths import resolve_model_path

            self._clip = load_clip(resolve_model_path("clip", self.path, self.settings), device=self.device)
        return self._clip

    @property
    def loaded(self) -> bool:
        return self._clip is not None

    def text_embedding(self) -> Tensor:
        if self._text is None:
            self._text = self.clip.encode_text([self.prompt])
        return self._text

    def loss(self, rgb: Tensor, mask: Tensor) -> Tensor:
        """fp32 scalar -mean cos(Z_I, Z_BGT) for renders (B,3,H,W) in [0,1] and masks (B,1,H,W) (1 = edited)."""
        clip = self.clip
        keep = (mask < 0.5).to(rgb.dtype)
        img = (rgb * keep).float().to(clip.device)
        pixels = clip_preprocess(img, clip.image_size, clip.mean, clip.std)
        z_img = clip.encode_image(pixels)
        z_txt = self.text_embedding().to(z_img.device)
        cos = F.cosine_similarity(z_img, z_txt.expand_as(z_img), dim=-1, eps=self.eps)
        return -cos.mean()


def build_clip_loss(weight: float, prompt: str, path: str | os.PathLike | None = None,
                    settings: Mapping[str, Any] | None = None, **kwargs) -> ClipBackgroundLoss | None:
    """A ClipBackgroundLoss when `weight` > 0, else None (and nothing is loaded or even looked up)."""
    if weight <= 0:
        return None
    return ClipBackgroundLoss(prompt, path=path, settings=settings, **kwargs)
