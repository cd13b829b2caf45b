"""Tiny random-weight transformers teachers (DINOv2, CLIP, SigLIP, DPT, Depth Anything, SAM), built from
configs and saved with save_pretrained, plus a local Hugging Face cache layout to load them by model id.
Used by the teacher tests and never downloaded."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import torch

IMAGENET = {"image_mean": [0.485, 0.456, 0.406], "image_std": [0.229, 0.224, 0.225]}
_VIT = dict(hidden_size=16, num_hidden_layers=2, num_attention_heads=2, intermediate_size=32)


def _save(model, out: Path, preprocessor: dict | None = None) -> Path:
    model.save_pretrained(out)
    if preprocessor is not None:
        (out / "preprocessor_config.json").write_text(json.dumps(preprocessor))
    return out


def make_tiny_dinov2(root: Path, seed: int = 0, registers: int = 0) -> Path:
    """A Dinov2Model folder: patch 8, 32 px, 16-dim tokens (Dinov2WithRegisters when `registers` > 0)."""
    torch.manual_seed(seed)
    if registers:
        from transformers import Dinov2WithRegistersConfig, Dinov2WithRegistersModel

        model = Dinov2WithRegistersModel(Dinov2WithRegistersConfig(image_size=32, patch_size=8,
                                                                   num_register_tokens=registers, **_VIT))
    else:
        from transformers import Dinov2Config, Dinov2Model

        model = Dinov2Model(Dinov2Config(image_size=32, patch_size=8, **_VIT))
    return _save(model, root / "tiny-dinov2", IMAGENET)


def make_tiny_clip_model(root: Path, seed: int = 0, projection_dim: int = 8) -> Path:
    """A full CLIPModel folder with tokenizer (tests/tiny_diffusion.make_tiny_clip): MaskCLIP and text."""
    from tiny_diffusion import make_tiny_clip

    return make_tiny_clip(root, seed=seed, projection_dim=projection_dim)


def make_tiny_siglip(root: Path, seed: int = 0) -> Path:
    """A SiglipModel folder (vision + text towers); the teacher reads its vision tower's patch tokens."""
    from transformers import SiglipConfig, SiglipModel

    torch.manual_seed(seed)
    cfg = SiglipConfig(vision_config=dict(image_size=32, patch_size=8, **_VIT),
                       text_config=dict(vocab_size=64, max_position_embeddings=16, **_VIT))
    return _save(SiglipModel(cfg), root / "tiny-siglip", {"image_mean": [0.5] * 3, "image_std": [0.5] * 3})


def _lively_head(model) -> None:
    """Re-draw the depth head's weights larger, with a positive last bias, so the random model's output
    varies across the image instead of sitting near the ReLU's zero (as a trained head's does)."""
    convs = [m for m in model.head.modules() if isinstance(m, torch.nn.Conv2d)]
    with torch.no_grad():
        for c in convs:
            c.weight.normal_(0.0, 0.6)
            c.bias.normal_(0.0, 0.1)
        convs[-1].bias.fill_(1.0)


def make_tiny_dpt(root: Path, seed: int = 0) -> Path:
    """A DPTForDepthEstimation folder: ViT patch 8, 32 px, four reassembled stages."""
    from transformers import DPTConfig, DPTForDepthEstimation

    torch.manual_seed(seed)
    cfg = DPTConfig(image_size=32, patch_size=8, hidden_size=16, num_hidden_layers=4, num_attention_heads=2,
                    intermediate_size=32, backbone_out_indices=[0, 1, 2, 3], neck_hidden_sizes=[8, 8, 16, 16],
                    fusion_hidden_size=16, head_in_index=-1)
    model = DPTForDepthEstimation(cfg)
    _lively_head(model)
    return _save(model, root / "tiny-dpt",
                 {"image_mean": [0.5] * 3, "image_std": [0.5] * 3, "ensure_multiple_of": 32})


def make_tiny_depth_anything(root: Path, seed: int = 0) -> Path:
    """A DepthAnythingForDepthEstimation folder with a tiny DINOv2 backbone (patch 14)."""
    from transformers import DepthAnythingConfig, DepthAnythingForDepthEstimation, Dinov2Config

    torch.manual_seed(seed)
    backbone = Dinov2Config(image_size=28, patch_size=14, out_features=["stage1", "stage2", "stage3", "stage4"],
                            reshape_hidden_states=False, num_hidden_layers=4, hidden_size=16, num_attention_heads=2,
                            intermediate_size=32)
    cfg = DepthAnythingConfig(backbone_config=backbone, patch_size=14, reassemble_hidden_size=16,
                              neck_hidden_sizes=[8, 8, 16, 16], fusion_hidden_size=16, head_hidden_size=8)
    model = DepthAnythingForDepthEstimation(cfg)
    _lively_head(model)
    return _save(model, root / "tiny-depth-anything",
                 {**IMAGENET, "ensure_multiple_of": 14})


def make_tiny_sam(root: Path, seed: int = 0) -> Path:
    """A SamModel folder with its SamProcessor: 64 px input, patch 8 (an 8x8 image embedding)."""
    from transformers import SamConfig, SamImageProcessor, SamModel, SamProcessor

    torch.manual_seed(seed)
    cfg = SamConfig(vision_config=dict(image_size=64, patch_size=8, hidden_size=16, num_hidden_layers=2,
                                       num_attention_heads=2, mlp_dim=32, output_channels=16,
                                       window_size=4, global_attn_indexes=[1], num_pos_feats=8),
                    prompt_encoder_config=dict(image_size=64, patch_size=8, hidden_size=16, image_embedding_size=8,
                                               mask_input_channels=4),
                    mask_decoder_config=dict(hidden_size=16, mlp_dim=32, num_hidden_layers=2, num_attention_heads=2,
                                             iou_head_hidden_dim=16))
    out = _save(SamModel(cfg), root / "tiny-sam")
    proc = SamProcessor(SamImageProcessor(size={"longest_edge": 64}, pad_size={"height": 64, "width": 64},
                                          mask_size={"longest_edge": 16}, mask_pad_size={"height": 16, "width": 16}))
    proc.save_pretrained(out)
    return out


def install_in_hf_cache(folder: Path, hf_home: Path, model_id: str, revision: str = "0123abcd") -> Path:
    """Lay `folder` out as the local hub cache does ($HF_HOME/hub/models--ORG--NAME/snapshots/REV + refs/main);
    returns the snapshot folder."""
    repo = hf_home / "hub" / ("models--" + model_id.replace("/", "--"))
    snap = repo / "snapshots" / revision
    shutil.copytree(folder, snap)
    (repo / "refs").mkdir(parents=True, exist_ok=True)
    (repo / "refs" / "main").write_text(revision)
    return snap


BUILDERS = {"dinov2": make_tiny_dinov2, "clip": make_tiny_clip_model, "siglip": make_tiny_siglip,
            "dpt": make_tiny_dpt, "depth_anything": make_tiny_depth_anything, "sam": make_tiny_sam}
