"""Monocular depth through a local transformers model (DPT, Depth Anything), aligned per image to the
sparse depth by core.teachers.depth_onnx.aligned_monocular_depth exactly as the ONNX teacher is."""
from __future__ import annotations

import os

import numpy as np
import torch

from repaint_nerf.core.models.depth import DepthModel, load_depth_model
from repaint_nerf.core.teachers._onnx import prepare_input, resize_map
from repaint_nerf.core.teachers.base import check_image
from repaint_nerf.core.teachers.feature_hf import input_hw

MAX_SIDE = 518  # default input short side cap (Depth Anything's own size)


class HFDepthTeacher:
    """Relative depth (H, W) from a transformers depth model; `inverse` says it is inverse depth (larger =
    nearer), as DPT and relative Depth Anything predict. `input_size` (H, W) fixes the model input."""

    def __init__(self, path: str | os.PathLike, input_size: tuple[int, int] | None = None,
                 device: torch.device | str | None = None):
        self.net: DepthModel = load_depth_model(path, device)
        self.path = self.net.path
        self.input_size = None if input_size is None else (int(input_size[0]), int(input_size[1]))
        self.inverse = self.net.inverse
        self.name = f"hf-depth-{self.net.model_type}"

    def config(self) -> dict:
        weights = sorted(self.path.glob("*.safetensors")) + sorted(self.path.glob("*.bin"))
        return {"path": str(self.path.resolve()), "model_type": self.net.model_type,
                "weights": [(w.name, w.stat().st_size, int(w.stat().st_mtime)) for w in weights],
                "input_size": self.input_size, "inverse": self.inverse}

    def model_input(self, height: int, width: int) -> tuple[int, int]:
        """The (H, W) an image of this size is fed at: aspect kept, sides multiples of the model's multiple."""
        if self.input_size is not None:
            return self.input_size
        return input_hw(height, width, self.net.multiple, min(self.net.short_side, MAX_SIDE))

    @torch.no_grad()
    def __call__(self, image: np.ndarray) -> np.ndarray:
        """(H, W, 3) uint8 -> (H, W) float32 relative inverse depth (or depth for a metric model)."""
        rgb = check_image(image)
        x = prepare_input(rgb, self.model_input(*rgb.shape[:2]), self.net.mean, self.net.std)
        out = self.net.model(pixel_values=torch.from_numpy(x).to(self.net.device)).predicted_depth
        out = out.reshape(out.shape[-2:]).float().cpu().numpy()
        return resize_map(out, rgb.shape[0], rgb.shape[1])
