"""Dense feature teacher from a transformers vision backbone (DINOv2, CLIP, SigLIP): the patch tokens of
the last layer as a (h, w, D) grid, upsampled bilinearly to the image and L2-normalised per pixel
(docs/CONTRACTS.md, feature teacher).

A full CLIP model gives MaskCLIP features instead (Zhou et al. 2022, "Extract Free Dense Labels from
CLIP"): the value embeddings of the last attention layer, through its output projection, the final layer
norm and the visual projection, so every patch feature lives in CLIP's joint text-image space and a text
prompt's embedding can be compared with it; the teacher then also `encode_text`s (through `clip`).
"""
from __future__ import annotations

import os

import numpy as np
import torch
from torch import Tensor

from repaint_nerf.core.models.vision import VisionBackbone, load_vision_backbone
from repaint_nerf.core.teachers._onnx import prepare_input, resize_map
from repaint_nerf.core.teachers.base import check_image, l2_normalize

MAX_SIDE = 448  # default input short side cap: DINOv2 configs say 518, which costs ~5x a 224 pass on a CPU
MIN_GRID = 16   # default input short side floor in patches: a ViT-B/32 CLIP at its 224 px would give 7 only


def input_hw(height: int, width: int, patch: int, short_side: int) -> tuple[int, int]:
    """The model input (H, W) of an image: its aspect kept, the short side near `short_side`, both sides
    multiples of the patch size (at least one patch)."""
    scale = short_side / min(height, width)
    return (max(patch, int(round(height * scale / patch)) * patch),
            max(patch, int(round(width * scale / patch)) * patch))


class HFFeatureTeacher:
    """Dense unit features (H, W, D) of a local transformers backbone folder. `input_size` (H, W) fixes the
    model input; by default the short side is the model's image size, raised to MIN_GRID patches and capped
    at MAX_SIDE, aspect kept."""

    def __init__(self, path: str | os.PathLike, input_size: tuple[int, int] | None = None,
                 device: torch.device | str | None = None, label: str | None = None):
        self.backbone: VisionBackbone = load_vision_backbone(path, device)
        self.path = self.backbone.path
        p = self.backbone.patch_size
        if input_size is not None and (input_size[0] % p or input_size[1] % p):
            input_size = (max(p, round(input_size[0] / p) * p), max(p, round(input_size[1] / p) * p))
        self.input_size = None if input_size is None else (int(input_size[0]), int(input_size[1]))
        self.maskclip = self.backbone.family == "clip"
        self.clip = self.backbone.clip if self.maskclip else None
        cfg = self.backbone.model.config
        self.dim = int(cfg.projection_dim if self.maskclip else getattr(cfg, "vision_config", cfg).hidden_size)
        self.name = f"hf-{self.backbone.model_type}" + ("-maskclip" if self.maskclip else "")
        self.label = label or self.path.name

    def config(self) -> dict:
        weights = sorted(self.path.glob("*.safetensors")) + sorted(self.path.glob("*.bin"))
        return {"path": str(self.path.resolve()), "model_type": self.backbone.model_type,
                "weights": [(w.name, w.stat().st_size, int(w.stat().st_mtime)) for w in weights],
                "input_size": self.input_size, "maskclip": self.maskclip, "sides": (MIN_GRID, MAX_SIDE)}

    def model_input(self, height: int, width: int) -> tuple[int, int]:
        """The (H, W) an image of this size is fed at."""
        if self.input_size is not None:
            return self.input_size
        b = self.backbone
        return input_hw(height, width, b.patch_size, min(max(b.image_size, MIN_GRID * b.patch_size), MAX_SIDE))

    @torch.no_grad()
    def __call__(self, image: np.ndarray) -> np.ndarray:
        """(H, W, 3) uint8 -> (H, W, D) float32 unit vectors."""
        rgb = check_image(image)
        size = self.model_input(*rgb.shape[:2])
        x = torch.from_numpy(prepare_input(rgb, size, self.backbone.mean, self.backbone.std)).to(self.backbone.device)
        grid = self.patch_grid(x)
        fmap = resize_map(grid.float().cpu().numpy(), rgb.shape[0], rgb.shape[1])
        return l2_normalize(fmap)

    def patch_grid(self, x: Tensor) -> Tensor:
        """(1, 3, H, W) normalised input -> (H/p, W/p, D) patch features."""
        b = self.backbone
        h, w = x.shape[2] // b.patch_size, x.shape[3] // b.patch_size
        if b.family == "dinov2":
            tokens = b.model(pixel_values=x).last_hidden_state
        elif b.family == "clip":
            tokens = maskclip_tokens(b.model, x)
        elif b.family == "clip_vision":
            vm = b.model.vision_model
            tokens = vm.post_layernorm(b.model(pixel_values=x, interpolate_pos_encoding=True).last_hidden_state)
        else:  # siglip: no class token; last_hidden_state is already layer-normed
            tokens = b.model(pixel_values=x, interpolate_pos_encoding=True).last_hidden_state
        tokens = tokens[0, b.prefix_tokens:]
        return tokens.reshape(h, w, tokens.shape[-1])


def maskclip_tokens(model, x: Tensor) -> Tensor:
    """MaskCLIP dense tokens (1, 1 + N, projection_dim) of a transformers CLIPModel: the last encoder
    layer's value path (v_proj, out_proj; no query-key attention, residual or MLP) of that layer's input,
    then the vision tower's post layer norm and the visual projection (the ones the pooled token goes through)."""
    vm = model.vision_model
    last = vm.encoder.layers[-1]
    seen: dict[str, Tensor] = {}

    def grab(module, args, kwargs):
        seen["h"] = args[0] if args else kwargs["hidden_states"]

    handle = last.register_forward_pre_hook(grab, with_kwargs=True)
    try:
        vm(pixel_values=x, interpolate_pos_encoding=True)
    finally:
        handle.remove()
    attn = last.self_attn
    v = attn.out_proj(attn.v_proj(last.layer_norm1(seen["h"])))
    return model.visual_projection(vm.post_layernorm(v))
