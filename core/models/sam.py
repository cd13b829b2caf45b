"""The one loader of Segment Anything models (transformers SamModel + SamProcessor) from a local folder
with `local_files_only=True`, used to refine selection masks per view (core/teachers/sam_refine.py)."""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import torch

from repaint_nerf.core.device import get_device
from repaint_nerf.core.errors import ModelNotFoundError
from repaint_nerf.core.models.paths import locate_model, model_type
from repaint_nerf.core.models.vision import quiet_transformers


@dataclass
class Sam:
    """A frozen SAM with the processor that resizes, pads and normalises its inputs and maps masks back."""

    model: torch.nn.Module
    processor: object
    device: torch.device
    path: Path


def load_sam(path: str | os.PathLike, device: torch.device | str | None = None) -> Sam:
    """Load a SAM folder or cached model id (config.json, weights, processor config) frozen, in fp32, on `device`."""
    from transformers import SamModel, SamProcessor

    path = locate_model("sam", path)
    kind = model_type(path)
    if kind != "sam":
        raise ModelNotFoundError(f"config.json's model_type is '{kind}', not 'sam'", path=path,
                                 hint="point --sam-path at a transformers SamModel folder (e.g. facebook/sam-vit-base)")
    dev = get_device(str(device)) if device is not None else get_device()
    try:
        with quiet_transformers():
            model = SamModel.from_pretrained(path, local_files_only=True, torch_dtype=torch.float32)
            processor = SamProcessor.from_pretrained(path, local_files_only=True)
    except (OSError, ValueError) as exc:
        raise ModelNotFoundError(f"could not load the SAM model: {str(exc).splitlines()[0][:300]}", path=path,
                                 hint="the folder needs config.json, the weights and preprocessor_config.json "
                                      "(as SamModel / SamProcessor.save_pretrained write them)") from exc
    model.eval().requires_grad_(False).to(dev)
    return Sam(model=model, processor=processor, device=dev, path=path)
