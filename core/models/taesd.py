"""The one loader of a tiny autoencoder (TAESD, diffusers `AutoencoderTiny`) with Stable Diffusion's latent space.

Score distillation differentiates through the VAE encoder at 512 px, the costliest part of a CPU step
(`bench sdcost`); TAESD's encoder is ~100x cheaper and maps images to (approximately) the same scaled
latents, so it can stand in for the encoder. Loaded from a local folder or a model id already in the
local Hugging Face cache (e.g. madebyollin/taesd for SD 1.x/2.x), never from the network.
"""
from __future__ import annotations

import os
from pathlib import Path

import torch

from repaint_nerf.core.errors import ModelNotFoundError, UserError
from repaint_nerf.core.models.paths import cached_snapshot

HINT = ("pass a local folder holding a diffusers AutoencoderTiny (config.json + diffusion_pytorch_model.safetensors, "
        "e.g. a download of madebyollin/taesd), or its model id when it is already in the Hugging Face cache")


def load_tiny_autoencoder(path_or_id: str | os.PathLike, device: torch.device,
                          dtype: torch.dtype = torch.float32) -> torch.nn.Module:
    """AutoencoderTiny from a local folder or a cached id (`local_files_only=True`), frozen, on `device`."""
    from diffusers import AutoencoderTiny

    name = str(path_or_id)
    local = Path(name).expanduser()
    try:
        folder = local if local.exists() else cached_snapshot(name)
        if folder is None:
            raise ModelNotFoundError(f"no tiny autoencoder {name!r}: no such folder, and no such model id in the local "
                                     "Hugging Face cache", path=local, hint=HINT)
        if not (folder / "config.json").is_file():
            raise ModelNotFoundError("not a tiny-autoencoder folder (no config.json)", path=folder, hint=HINT)
        ae = AutoencoderTiny.from_pretrained(str(folder), local_files_only=True, torch_dtype=dtype)
    except (OSError, ValueError, EnvironmentError) as exc:
        raise ModelNotFoundError(f"could not load the tiny autoencoder {name!r} without a network: {exc}",
                                 path=local if local.exists() else None, hint=HINT) from exc
    ae.eval().requires_grad_(False)
    return ae.to(device)


def check_compatible(ae: torch.nn.Module, latent_channels: int, scale_factor: int) -> None:
    """Raise UserError unless the tiny autoencoder makes latents of the UNet's channels and downscale."""
    ch = int(ae.config.latent_channels)
    down = 2 ** (len(ae.config.encoder_block_out_channels) - 1)
    if ch != latent_channels or down != scale_factor:
        raise UserError(f"the tiny autoencoder makes {ch}-channel latents at 1/{down} scale, the UNet wants "
                        f"{latent_channels} channels at 1/{scale_factor}",
                        hint="use the TAESD built for this model family (taesd for SD 1.x/2.x, taesdxl for SDXL)")
