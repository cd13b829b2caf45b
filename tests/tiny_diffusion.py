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


# --- the original (CompVis) single-file layout, for the single-file loader's tests --------------------------
_RESNET = (("norm1", "in_layers.0"), ("conv1", "in_layers.2"), ("norm2", "out_layers.0"), ("conv2", "out_layers.3"),
           ("time_emb_proj", "emb_layers.1"), ("conv_shortcut", "skip_connection"))
_VAE_ATTN = (("group_norm", "norm"), ("to_q", "q"), ("to_k", "k"), ("to_v", "v"), ("to_out.0", "proj_out"))


def _unet_key(k: str, per: int, attn_up: set[int]) -> str:
    """A diffusers UNet key in the original layout; `per` = layers_per_block + 1 slots per level."""
    import re

    fixed = {"conv_in.": "input_blocks.0.0.", "time_embedding.linear_1.": "time_embed.0.",
             "time_embedding.linear_2.": "time_embed.2.", "conv_norm_out.": "out.0.", "conv_out.": "out.2.",
             "mid_block.resnets.0.": "middle_block.0.", "mid_block.attentions.0.": "middle_block.1.",
             "mid_block.resnets.1.": "middle_block.2."}
    for a, b in fixed.items():
        if k.startswith(a):
            k = b + k[len(a):]
            break
    else:
        m = re.match(r"(down|up)_blocks\.(\d+)\.(resnets|attentions|downsamplers|upsamplers)\.(\d+)\.(.*)", k)
        side, i, part, j, rest = m[1], int(m[2]), m[3], int(m[4]), m[5]
        if part == "downsamplers":
            k = f"input_blocks.{per * (i + 1)}.0.op.{rest.removeprefix('conv.')}"
        elif part == "upsamplers":
            k = f"output_blocks.{per * i + per - 1}.{2 if i in attn_up else 1}.{rest}"
        else:
            slot = per * i + j + 1 if side == "down" else per * i + j
            k = f"{'input' if side == 'down' else 'output'}_blocks.{slot}.{0 if part == 'resnets' else 1}.{rest}"
    if re.match(r"(input_blocks\.\d+\.0|output_blocks\.\d+\.0|middle_block\.[02])\.", k):
        for a, b in _RESNET:
            k = k.replace(f".{a}.", f".{b}.")
    return k


def _vae_key(k: str, n: int) -> str:
    import re

    k = re.sub(r"encoder\.down_blocks\.(\d+)\.resnets\.", r"encoder.down.\1.block.", k)
    k = re.sub(r"encoder\.down_blocks\.(\d+)\.downsamplers\.0\.", r"encoder.down.\1.downsample.", k)
    k = re.sub(r"decoder\.up_blocks\.(\d+)\.resnets\.", lambda m: f"decoder.up.{n - 1 - int(m[1])}.block.", k)
    k = re.sub(r"decoder\.up_blocks\.(\d+)\.upsamplers\.0\.", lambda m: f"decoder.up.{n - 1 - int(m[1])}.upsample.", k)
    k = k.replace("mid_block.resnets.0.", "mid.block_1.").replace("mid_block.resnets.1.", "mid.block_2.")
    if "mid_block.attentions.0." in k:
        k = k.replace("mid_block.attentions.0.", "mid.attn_1.")
        for a, b in _VAE_ATTN:
            k = k.replace(f".{a}.", f".{b}.")
    return k.replace("conv_norm_out.", "norm_out.").replace("conv_shortcut.", "nin_shortcut.")


def original_state_dict(unet, vae, text) -> dict:
    """An SD UNet, VAE and CLIP text encoder (diffusers / transformers modules) under the original checkpoint's
    names (model.diffusion_model.*, first_stage_model.*, cond_stage_model.transformer.*). Test code only."""
    per = unet.config.layers_per_block + 1
    attn_up = {i for i, t in enumerate(unet.config.up_block_types) if "CrossAttn" in t}
    out = {"model.diffusion_model." + _unet_key(k, per, attn_up): v for k, v in unet.state_dict().items()}
    n = len(vae.config.block_out_channels)
    for k, v in vae.state_dict().items():
        name = _vae_key(k, n)
        if ".mid.attn_1." in name and name.endswith("weight") and v.dim() == 2:
            v = v[:, :, None, None]  # the original attention projections are 1x1 convolutions
        out["first_stage_model." + name] = v
    for k, v in text.state_dict().items():
        out["cond_stage_model.transformer.text_model." + k.removeprefix("text_model.")] = v
    return {k: v.contiguous() for k, v in out.items()}


def save_single_file(folder: Path, out: Path) -> Path:
    """The tiny pipeline as one original-layout .safetensors (or .ckpt with a 'state_dict' wrapper) file."""
    from diffusers import AutoencoderKL, UNet2DConditionModel
    from transformers import CLIPTextModel

    sd = original_state_dict(UNet2DConditionModel.from_pretrained(folder, subfolder="unet", local_files_only=True),
                             AutoencoderKL.from_pretrained(folder, subfolder="vae", local_files_only=True),
                             CLIPTextModel.from_pretrained(folder, subfolder="text_encoder", local_files_only=True))
    out.parent.mkdir(parents=True, exist_ok=True)
    if out.suffix == ".ckpt":
        torch.save({"state_dict": sd}, out)
    else:
        from safetensors.torch import save_file

        save_file(sd, str(out))
    return out


def config_only_copy(folder: Path, out: Path, with_tokenizer: bool = False) -> Path:
    """The pipeline's config files without weights (what --sd-config points at), optionally with tokenizer/."""
    import shutil

    for f in folder.rglob("*.json"):
        if f.parent.name == "tokenizer" and not with_tokenizer:
            continue
        (out / f.relative_to(folder)).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(f, out / f.relative_to(folder))
    return out
