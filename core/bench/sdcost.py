"""`repaint-nerf bench sdcost`: what one Stable Diffusion score-distillation step costs on this device.

No SD weights can be downloaded here, but compute does not depend on weight values: the benchmark builds
SD 1.5's UNet, VAE and CLIP text encoder from their published configurations with random weights,
assembles them as the loader does (core.models.sd.assemble: fp16 and attention slicing on CUDA, fp32 on
a CPU) and times SDSGuidance steps (VAE encode with gradient at 512 px, a classifier-free UNet pass, the
backward to the render) on a render of --size pixels, with peak memory; then projects the paper's
stage-2 length (10000 steps). The field's own render and backward per step are `bench edit`'s figures.
"""
from __future__ import annotations

import argparse
import json
import resource
import statistics
import time
from pathlib import Path

HELP = "cost of one Stable Diffusion 1.5 score-distillation step (SD 1.5's architecture, random weights)"
PAPER_STEPS = 10000  # stage 2 in the paper (Implementation Details)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--steps", type=int, default=3, help="timed steps (after one warm-up step)")
    p.add_argument("--size", type=int, default=128, help="render side in pixels (resized to 512 for the VAE)")
    p.add_argument("--json", required=True, help="output JSON path")
    p.add_argument("--device", default=None)


class _FixedTokenizer:
    """Token ids of the right shape for the text encoder (the prompt's content does not change the cost)."""

    model_max_length = 77

    def __call__(self, prompts, **_):
        import torch

        class _Out:
            input_ids = torch.zeros(len(prompts), 77, dtype=torch.long)
        return _Out()


def build_sd15(device, dtype):
    """SD 1.5's parts from their published configurations, random weights, placed like a loaded model."""
    import torch
    from diffusers import AutoencoderKL, DDIMScheduler, UNet2DConditionModel
    from transformers import CLIPTextConfig, CLIPTextModel

    from core.models.sd import assemble

    torch.manual_seed(0)
    unet = UNet2DConditionModel(
        sample_size=64, in_channels=4, out_channels=4, layers_per_block=2,
        block_out_channels=(320, 640, 1280, 1280), cross_attention_dim=768, attention_head_dim=8,
        down_block_types=("CrossAttnDownBlock2D",) * 3 + ("DownBlock2D",),
        up_block_types=("UpBlock2D",) + ("CrossAttnUpBlock2D",) * 3)
    vae = AutoencoderKL(
        in_channels=3, out_channels=3, latent_channels=4, layers_per_block=2,
        block_out_channels=(128, 256, 512, 512), down_block_types=("DownEncoderBlock2D",) * 4,
        up_block_types=("UpDecoderBlock2D",) * 4, sample_size=512)
    text = CLIPTextModel(CLIPTextConfig(vocab_size=49408, hidden_size=768, intermediate_size=3072,
                                        num_hidden_layers=12, num_attention_heads=12, max_position_embeddings=77))
    scheduler = DDIMScheduler(num_train_timesteps=1000, beta_schedule="scaled_linear", beta_start=0.00085,
                              beta_end=0.012, clip_sample=False, set_alpha_to_one=False, steps_offset=1)
    return assemble(unet, vae, text, _FixedTokenizer(), scheduler, device, dtype)


def _count(m) -> int:
    return sum(p.numel() for p in m.parameters())


def run(args: argparse.Namespace) -> int:
    import torch

    from core.device import describe, get_device, is_cuda, synchronize
    from core.repaint.sds import SDSGuidance

    from core.errors import UserError

    if args.steps < 1 or args.size < 8:
        raise UserError(f"--steps must be at least 1 and --size at least 8 (got {args.steps}, {args.size})")
    device = get_device(args.device)
    dtype = torch.float16 if is_cuda(device) else torch.float32
    t0 = time.perf_counter()
    sd = build_sd15(device, dtype)
    build_s = time.perf_counter() - t0
    guidance = SDSGuidance(sd, "a blue rose in leaves", seed=0)
    if is_cuda(device):
        torch.cuda.reset_peak_memory_stats(device)
    times = []
    for i in range(args.steps + 1):
        rgb = torch.rand(1, 3, args.size, args.size, device=device, requires_grad=True)
        synchronize(device)
        t = time.perf_counter()
        out = guidance.loss(rgb)
        out["loss"].backward()
        synchronize(device)
        if i:  # the first step warms up allocators and kernels
            times.append(time.perf_counter() - t)
        assert rgb.grad is not None and bool(torch.isfinite(rgb.grad).all())
    step_s = statistics.median(times)
    result = {
        "device": describe(device), "dtype": str(dtype).replace("torch.", ""),
        "architecture": "Stable Diffusion 1.5 (random weights from its configuration)",
        "parameters_m": {"unet": _count(sd.unet) / 1e6, "vae": _count(sd.vae) / 1e6,
                         "text_encoder": _count(sd.text_encoder) / 1e6},
        "render_size": args.size, "model_resolution": sd.resolution, "build_seconds": build_s,
        "step_seconds": step_s, "step_seconds_all": times,
        "paper_steps": PAPER_STEPS, "paper_steps_hours": step_s * PAPER_STEPS / 3600.0,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
    }
    if is_cuda(device):
        result["peak_gpu_mb"] = torch.cuda.max_memory_allocated(device) / 2 ** 20
    out_path = Path(args.json)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    out_path.write_text(json.dumps(result, indent=2))
    print(json.dumps(result, indent=2))
    return 0
