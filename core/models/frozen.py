"""What every frozen pretrained network loaded from a local folder carries: the module, its kind, its input
normalisation and where it came from (core.models.vision and core.models.depth extend it)."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch


@dataclass
class FrozenNet:
    """A frozen (eval, no grad) network with the per-channel mean/std its inputs are normalised by."""

    model: torch.nn.Module
    model_type: str  # config.json's model_type
    mean: tuple[float, float, float]
    std: tuple[float, float, float]
    device: torch.device
    path: Path
