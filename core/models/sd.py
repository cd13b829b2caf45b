"""The one Stable Diffusion loader: a local diffusers folder, a model id in the local HF cache (resolved by
core.models.paths) or a single-file checkpoint (core.models.sd_single_file), never the network.

Holds the frozen parts score distillation needs (UNet, VAE, text encoder, tokenizer, a DDIM schedule)
and the three operations it performs with them: encode a prompt, encode an image with gradient,
predict noise. fp16 on CUDA with attention/VAE slicing and optional UNet offload; fp32 on CPU.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import Tensor

from repaint_nerf.core.device import get_device, is_cuda
from repaint_nerf.core.errors import ModelNotFoundError
from repaint_nerf.core.models.paths import how_to_set

PREDICTION_TYPES = ("epsilon", "v_prediction")  # what a UNet may predict (core.repaint.sds reads both)
COMPONENTS = ("unet", "vae", "text_encoder", "tokenizer", "scheduler")
SINGLE_FILE_SUFFIXES = (".safetensors", ".ckpt")
# Only alphas_cumprod and add_noise are used; these silence diffusers' warnings about old SD configs.
_DDIM_OVERRIDES = dict(clip_sample=False, set_alpha_to_one=False, steps_offset=1)


@dataclass
class StableDiffusion:
    """Frozen Stable Diffusion parts on one device, plus the schedule's alpha_bar table (fp32, on device)."""

    unet: torch.nn.Module
    vae: torch.nn.Module
    text_encoder: torch.nn.Module
    tokenizer: object
    scheduler: object
    device: torch.device
    dtype: torch.dtype
    offload_unet: bool = False
    path: Path | None = None
    tiny_vae: torch.nn.Module | None = None  # a TAESD-style encoder used instead of the VAE's (core.models.taesd)
    alphas_cumprod: Tensor = field(init=False)

    def __post_init__(self) -> None:
        for m in (self.unet, self.vae, self.text_encoder):
            m.eval()
            m.requires_grad_(False)
        self.alphas_cumprod = self.scheduler.alphas_cumprod.to(self.device, torch.float32)

    @property
    def vae_scale_factor(self) -> int:
        """Pixels per latent cell: 2^(number of VAE down blocks - 1), 8 for SD."""
        return 2 ** (len(self.vae.config.block_out_channels) - 1)

    @property
    def resolution(self) -> int:
        """Image side the UNet was trained for: sample_size x VAE factor (512 for SD 1.5 / 2.0-base)."""
        return int(self.unet.config.sample_size) * self.vae_scale_factor

    @property
    def latent_scale(self) -> float:
        return float(getattr(self.vae.config, "scaling_factor", 0.18215))

    @property
    def prediction_type(self) -> str:
        """What the UNet predicts, from its scheduler: 'epsilon' (SD 1.x, 2.x base) or 'v_prediction' (2.x 768)."""
        return str(getattr(self.scheduler.config, "prediction_type", "epsilon"))

    @property
    def num_train_timesteps(self) -> int:
        return int(self.scheduler.config.num_train_timesteps)

    @property
    def unet_dtype(self) -> torch.dtype:
        return next(self.unet.parameters()).dtype

    def set_unet_dtype(self, dtype: torch.dtype) -> None:
        """Run the (gradient-free) UNet in `dtype`, e.g. bf16 on a CPU with native bf16; its output is
        returned as is and callers upcast it."""
        if self.unet_dtype != dtype:
            self.unet.to(dtype=dtype)

    @torch.no_grad()
    def encode_text(self, prompts: list[str]) -> Tensor:
        """Text-encoder hidden states (B, L, D) for the prompts, in the UNet's dtype on the device."""
        tok = self.tokenizer(prompts, padding="max_length", max_length=self.tokenizer.model_max_length,
                             truncation=True, return_tensors="pt")
        te_device = next(self.text_encoder.parameters()).device
        out = self.text_encoder(tok.input_ids.to(te_device))[0]
        return out.to(self.device, self.dtype)

    def encode_images(self, x01: Tensor, generator: torch.Generator | None = None) -> Tensor:
        """VAE latents (with gradient) of images (B,3,R,R) in [0,1], scaled by the VAE's latent scale."""
        if self.tiny_vae is not None:  # TAESD: [-1, 1] in, latents already in the UNet's scale
            w = next(self.tiny_vae.parameters())
            x = x01.to(self.device, w.dtype) * 2 - 1
            if w.dim() == 4 and w.is_contiguous(memory_format=torch.channels_last) and not w.is_contiguous():
                x = x.contiguous(memory_format=torch.channels_last)  # the weights' layout (sd_speed.set_channels_last)
            return self.tiny_vae.encode(x).latents * float(self.tiny_vae.config.scaling_factor)
        x = x01.to(self.device, self.dtype) * 2 - 1
        posterior = self.vae.encode(x).latent_dist
        return posterior.sample(generator=generator) * self.latent_scale

    @torch.no_grad()
    def predict_noise(self, latents: Tensor, t: Tensor, embeddings: Tensor) -> Tensor:
        """UNet output (no gradient): the noise, or v per `prediction_type`; moves the UNet on and off the GPU
        when offloading."""
        if self.offload_unet:
            self.unet.to(self.device)
        try:
            dt = self.unet_dtype
            return self.unet(latents.to(self.device, dt), t.to(self.device),
                             encoder_hidden_states=embeddings.to(self.device, dt)).sample
        finally:
            if self.offload_unet:
                self.unet.to("cpu")


def _check_folder(path: Path) -> None:
    missing = [c for c in COMPONENTS if not (path / c).is_dir()]
    if missing:
        raise ModelNotFoundError(
            f"not a complete diffusers Stable Diffusion folder: missing {', '.join(m + '/' for m in missing)}",
            path=path,
            hint="point at a folder laid out like a diffusers SD model (model_index.json, unet/, vae/, "
                 "text_encoder/, tokenizer/, scheduler/), or at a single .safetensors/.ckpt file")


def _load_folder(path: Path, dtype: torch.dtype):
    from diffusers import AutoencoderKL, DDIMScheduler, UNet2DConditionModel
    from transformers import CLIPTextModel, CLIPTokenizer

    _check_folder(path)
    kw = dict(local_files_only=True)
    try:
        unet = UNet2DConditionModel.from_pretrained(path, subfolder="unet", torch_dtype=dtype, **kw)
        vae = AutoencoderKL.from_pretrained(path, subfolder="vae", torch_dtype=dtype, **kw)
        text_encoder = CLIPTextModel.from_pretrained(path, subfolder="text_encoder", torch_dtype=dtype, **kw)
        tokenizer = CLIPTokenizer.from_pretrained(path, subfolder="tokenizer", **kw)
        scheduler = DDIMScheduler.from_pretrained(path, subfolder="scheduler", **kw)
    except (OSError, ValueError, EnvironmentError) as exc:
        raise ModelNotFoundError(f"could not load the Stable Diffusion folder: {exc}", path=path,
                                 hint="check that every component folder has its config and weights") from exc
    return unet, vae, text_encoder, tokenizer, scheduler


def _load_single_file(path: Path, dtype: torch.dtype, config: Path | None, family: str | None,
                      prediction_type: str | None):
    """An original-layout checkpoint with the shipped config of its detected family (or `config`), offline."""
    from diffusers import StableDiffusionPipeline

    from repaint_nerf.core.models import sd_single_file as sf

    shapes = sf.checkpoint_shapes(path)
    fam = sf.detect_family(shapes, path, family, prediction_type)
    if config is None:
        config = sf.config_folder(fam)
    elif not (config / "model_index.json").is_file():
        raise ModelNotFoundError("the --sd-config folder has no model_index.json", path=config,
                                 hint="give a diffusers config folder: model_index.json, unet/, vae/, text_encoder/, "
                                      "scheduler/ (the weights are not needed)")
    sf.check_matches_config(shapes, config, path)
    tokenizer = sf.find_tokenizer(fam, path, config)
    try:
        pipe = StableDiffusionPipeline.from_single_file(
            str(path), config=str(config), local_files_only=True, torch_dtype=dtype, tokenizer=tokenizer,
            safety_checker=None, feature_extractor=None)
    except Exception as exc:  # diffusers raises several types here; all mean "cannot build it from this file"
        raise ModelNotFoundError(
            f"could not load the checkpoint as {sf.FAMILIES[fam].title} with the config {config}: {exc}", path=path,
            hint="if it is another model, pass --sd-config DIR with its diffusers config folder, or convert the "
                 "checkpoint to a diffusers folder") from exc
    return pipe.unet, pipe.vae, pipe.text_encoder, pipe.tokenizer, pipe.scheduler


def load_stable_diffusion(path: str | os.PathLike, device: torch.device | str | None = None,
                          dtype: torch.dtype | None = None, cpu_offload: bool = False,
                          attention_slicing: bool = True, config: str | os.PathLike | None = None,
                          family: str | None = None, prediction_type: str | None = None) -> StableDiffusion:
    """Load SD from a local diffusers folder or .safetensors/.ckpt file (`local_files_only=True`, no network).

    A single file is loaded with its family's shipped config (core.models.sd_single_file says how the family
    is told), or `config` (a diffusers config folder); `family` and `prediction_type` override what the
    checkpoint or folder says. fp16 on CUDA (fp32 on CPU) unless `dtype` says otherwise. With `cpu_offload`
    the text encoder stays on the CPU (used once per prompt) and the UNet visits the GPU only for its forward.
    """
    from diffusers import DDIMScheduler

    path = Path(path).expanduser()
    if not path.exists():
        raise ModelNotFoundError("the Stable Diffusion model path does not exist", path=path, hint=how_to_set("sd"))
    if prediction_type is not None and prediction_type not in PREDICTION_TYPES:
        raise ModelNotFoundError(f"unknown prediction type {prediction_type!r}", path=path,
                                 hint=f"use one of: {', '.join(PREDICTION_TYPES)}")
    dev = get_device(str(device)) if device is not None else get_device()
    cuda = is_cuda(dev)
    if dtype is None:
        dtype = torch.float16 if cuda else torch.float32
    if path.is_file():
        if path.suffix.lower() not in SINGLE_FILE_SUFFIXES:
            raise ModelNotFoundError("not a Stable Diffusion checkpoint (expected .safetensors or .ckpt, "
                                     "or a diffusers folder)", path=path, hint=how_to_set("sd"))
        cfg = Path(config).expanduser() if config is not None else None
        unet, vae, text_encoder, tokenizer, scheduler = _load_single_file(path, dtype, cfg, family, prediction_type)
    else:
        unet, vae, text_encoder, tokenizer, scheduler = _load_folder(path, dtype)
    overrides = dict(_DDIM_OVERRIDES, **({"prediction_type": prediction_type} if prediction_type else {}))
    scheduler = DDIMScheduler.from_config(scheduler.config, **overrides)
    if scheduler.config.prediction_type not in PREDICTION_TYPES:
        raise ModelNotFoundError(f"the model predicts {scheduler.config.prediction_type!r}, which score distillation "
                                 f"here does not support", path=path,
                                 hint=f"pass --prediction-type ({' | '.join(PREDICTION_TYPES)}) if its scheduler "
                                      f"config is wrong, or use an SD 1.x/2.x model")
    return assemble(unet, vae, text_encoder, tokenizer, scheduler, dev, dtype, cpu_offload, attention_slicing, path)


def assemble(unet, vae, text_encoder, tokenizer, scheduler, device: torch.device, dtype: torch.dtype,
             cpu_offload: bool = False, attention_slicing: bool = True, path: Path | None = None) -> StableDiffusion:
    """Place loaded (or built) SD parts on `device` in `dtype` with the memory options, as a StableDiffusion."""
    cuda = is_cuda(device)
    for m in (unet, vae, text_encoder):
        if next(m.parameters()).dtype != dtype:
            m.to(dtype=dtype)
    offload = bool(cpu_offload and cuda)
    if offload:
        text_encoder.to("cpu", torch.float32)
        unet.to("cpu")
    else:
        text_encoder.to(device)
        unet.to(device)
    vae.to(device)
    if cuda and attention_slicing:
        unet.set_attention_slice("auto")
        if hasattr(vae, "enable_slicing"):
            vae.enable_slicing()
    return StableDiffusion(unet=unet, vae=vae, text_encoder=text_encoder, tokenizer=tokenizer,
                           scheduler=scheduler, device=device, dtype=dtype, offload_unet=offload, path=path)
