"""Tiny random-weight Stable Diffusion and CLIP folders, laid out like real ones, for the guidance tests.

Built in code and saved with save_pretrained so the tests load them through the same loaders a
user's model goes through (core.models.sd / core.models.clip).
"""
from __future__ import annotations

import json
import string
from pathlib import Path

import torch

MAX_LEN = 16


def write_tokenizer_files(folder: Path) -> tuple[Path, Path]:
    """A CLIP BPE vocabulary of single letters (no merges): every lower-case word is encodable."""
    folder.mkdir(parents=True, exist_ok=True)
    tokens = ["<|startoftext|>", "<|endoftext|>"]
    for c in string.ascii_lowercase:
        tokens += [c, c + "</w>"]
    vocab, merges = folder / "vocab.json", folder / "merges.txt"
    vocab.write_text(json.dumps({t: i for i, t in enumerate(tokens)}))
    merges.write_text("#version: 0.2\n")
    return vocab, merges


def tiny_tokenizer(folder: Path):
    from transformers import CLIPTokenizer

    vocab, merges = write_tokenizer_files(folder)
    return CLIPTokenizer(str(vocab), str(merges), model_max_length=MAX_LEN)


def _text_config_kwargs(vocab_size: int) -> dict:
    return dict(vocab_size=vocab_size, hidden_size=16, intermediate_size=32, num_hidden_layers=1,
                num_attention_heads=2, max_position_embeddings=MAX_LEN, bos_token_id=0, eos_token_id=1,
                pad_token_id=1, projection_dim=8)


def make_tiny_sd(root: Path, seed: int = 0) -> Path:
    """A diffusers SD folder (model_index.json, unet/, vae/, text_encoder/, tokenizer/, scheduler/); 64 px."""
    from diffusers import AutoencoderKL, DDPMScheduler, StableDiffusionPipeline, UNet2DConditionModel
    from transformers import CLIPTextConfig, CLIPTextModel

    torch.manual_seed(seed)
    unet = UNet2DConditionModel(
        sample_size=8, in_channels=4, out_channels=4, layers_per_block=1, block_out_channels=(8, 16),
        down_block_types=("CrossAttnDownBlock2D", "DownBlock2D"),
        up_block_types=("UpBlock2D", "CrossAttnUpBlock2D"), cross_attention_dim=16, attention_head_dim=2,
        norm_num_groups=4)
    vae = AutoencoderKL(
        in_channels=3, out_channels=3, latent_channels=4, layers_per_block=1, block_out_channels=(8, 8, 8, 8),
        down_block_types=("DownEncoderBlock2D",) * 4, up_block_types=("UpDecoderBlock2D",) * 4,
        norm_num_groups=4, sample_size=64)
    tokenizer = tiny_tokenizer(root / "_tok_src")
    text_encoder = CLIPTextModel(CLIPTextConfig(**_text_config_kwargs(len(tokenizer.get_vocab()))))
    scheduler = DDPMScheduler(num_train_timesteps=1000, beta_schedule="scaled_linear", beta_start=0.00085,
                              beta_end=0.012, steps_offset=1, clip_sample=False)
    pipe = StableDiffusionPipeline(vae=vae, text_encoder=text_encoder, tokenizer=tokenizer, unet=unet,
                                   scheduler=scheduler, safety_checker=None, feature_extractor=None,
                                   requires_safety_checker=False)
    out = root / "tiny-sd"
    pipe.save_pretrained(out)
    return out


_CACHE: dict[str, Path] = {}


def cached(kind: str, tmp_path_factory) -> Path:
    """The tiny 'sd' or 'clip' folder, built once per test session."""
    if kind not in _CACHE:
        root = tmp_path_factory.mktemp(f"tiny_{kind}")
        _CACHE[kind] = make_tiny_sd(root) if kind == "sd" else make_tiny_clip(root)
    return _CACHE[kind]


def make_tiny_clip(root: Path, seed: int = 0, projection_dim: int = 8) -> Path:
    """A transformers CLIP folder (config.json, weights, tokenizer, preprocessor_config.json); 32 px images,
    `projection_dim`-dim embeddings."""
    from transformers import CLIPConfig, CLIPModel

    torch.manual_seed(seed)
    out = root / "tiny-clip"
    tokenizer = tiny_tokenizer(root / "_clip_tok_src")
    text = {**_text_config_kwargs(len(tokenizer.get_vocab())), "projection_dim": projection_dim}
    vision = dict(image_size=32, patch_size=8, hidden_size=16, intermediate_size=32, num_hidden_layers=1,
                  num_attention_heads=2, projection_dim=projection_dim)
    model = CLIPModel(CLIPConfig(text_config=text, vision_config=vision, projection_dim=projection_dim))
    model.save_pretrained(out)
    tokenizer.save_pretrained(out)
    (out / "preprocessor_config.json").write_text(json.dumps({
        "crop_size": {"height": 32, "width": 32}, "size": {"shortest_edge": 32}, "do_normalize": True,
        "image_mean": [0.48145466, 0.4578275, 0.40821073], "image_std": [0.26862954, 0.26130258, 0.27577711],
        "image_processor_type": "CLIPImageProcessor"}))
    return out
