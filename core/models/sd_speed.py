"""Speed options of a loaded Stable Diffusion for score distillation: the UNet's precision and a tiny encoder.

Measured by `bench sdcost` (figures in its JSON); each is a RepaintConfig field so a user can turn it off.
"""
from __future__ import annotations

import os

import torch

from repaint_nerf.core.device import is_cuda
from repaint_nerf.core.errors import UserError
from repaint_nerf.core.models.sd import StableDiffusion

UNET_PRECISIONS = ("auto", "fp32", "bf16", "fp16")


def cpu_has_bf16() -> bool:
    """True when oneDNN runs bf16 natively on this CPU (avx512_bf16 / AMX); emulated bf16 is slower than fp32."""
    try:
        return bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())
    except (AttributeError, RuntimeError):
        return False


def unet_dtype(precision: str, device: torch.device) -> torch.dtype:
    """The UNet dtype for a precision name; 'auto' is fp16 on CUDA, bf16 on a CPU with native bf16, else fp32."""
    if precision not in UNET_PRECISIONS:
        raise UserError(f"unknown UNet precision {precision!r}", hint=f"use one of: {', '.join(UNET_PRECISIONS)}")
    if precision == "auto":
        if is_cuda(device):
            return torch.float16
        return torch.bfloat16 if cpu_has_bf16() else torch.float32
    if precision == "fp16" and not is_cuda(device):
        raise UserError("fp16 UNet needs a CUDA device", hint="use bf16 or fp32 on a CPU")
    return {"fp32": torch.float32, "bf16": torch.bfloat16, "fp16": torch.float16}[precision]


def set_channels_last(sd: StableDiffusion, on: bool) -> None:
    """Store the UNet's and the tiny autoencoder's weights channels-last (NHWC), the layout oneDNN's CPU
    convolutions run without reorders (the tiny encoder's forward and backward at 512 px: 1.5x less CPU time)."""
    fmt = torch.channels_last if on else torch.contiguous_format
    for m in (sd.unet, sd.tiny_vae):
        if m is not None:
            m.to(memory_format=fmt)


def apply_speed_options(sd: StableDiffusion, unet_precision: str = "auto",
                        tiny_autoencoder: str | os.PathLike | None = None,
                        channels_last: bool = False, token_merging: float = 0.0) -> StableDiffusion:
    """Set the UNet's precision, memory layout and token merging (core.models.sd_tome) and, when given,
    encode through a tiny autoencoder (core.models.taesd)."""
    from repaint_nerf.core.models.sd_tome import set_token_merging

    sd.set_unet_dtype(unet_dtype(unet_precision, sd.device))
    set_token_merging(sd.unet, token_merging)
    if tiny_autoencoder:
        from repaint_nerf.core.models.taesd import check_compatible, load_tiny_autoencoder

        ae = load_tiny_autoencoder(tiny_autoencoder, sd.device, sd.dtype)
        check_compatible(ae, int(sd.unet.config.in_channels), sd.vae_scale_factor)
        sd.tiny_vae = ae
    set_channels_last(sd, channels_last)
    return sd
