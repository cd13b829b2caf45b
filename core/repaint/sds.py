"""Stable Diffusion score distillation (paper Eq. SDS) with the official stage-2 settings.

Classifier-free guidance (scale 100), t ~ U[20, 980] of 1000, w(t) = 1 - alpha_bar_t, the render
resized to the model's resolution (or a lower `sds_resolution`, a user's choice: 256 px costs ~1/4)
and VAE-encoded with gradient; the UNet runs without gradient. The UNet's output is read as its scheduler's
`prediction_type` says: the noise (SD 1.x, 2.x base) or v (SD 2.x 768), which is turned into the noise
before guidance. With `profile` set, `stage_seconds` holds the last step's wall time per stage and
`stage_cpu_seconds` this process's CPU time (bench sdcost).
"""
from __future__ import annotations

import time

import torch
import torch.nn.functional as F
from torch import Tensor

from repaint_nerf.core.device import synchronize
from repaint_nerf.core.errors import UserError
from repaint_nerf.core.models.sd import PREDICTION_TYPES, StableDiffusion
from repaint_nerf.core.repaint.guidance import Guidance, GuidanceResult, TimestepSampler, distillation_loss


def noise_from_prediction(pred: Tensor, noisy: Tensor, alpha_bar: Tensor | float, prediction_type: str) -> Tensor:
    """The noise a UNet output stands for: itself for 'epsilon'; for 'v_prediction'
    eps = sqrt(abar) v + sqrt(1 - abar) x_t (v = sqrt(abar) eps - sqrt(1 - abar) x0)."""
    if prediction_type == "epsilon":
        return pred
    if prediction_type == "v_prediction":
        ab = torch.as_tensor(alpha_bar, dtype=pred.dtype, device=pred.device)
        return ab.sqrt() * pred + (1 - ab).sqrt() * noisy.to(pred.dtype)
    raise ValueError(f"unsupported prediction_type {prediction_type!r}; supported: {', '.join(PREDICTION_TYPES)}")


class SDSGuidance(Guidance):
    """Score distillation from a loaded StableDiffusion; prompt embeddings are computed once and cached."""

    def __init__(self, sd: StableDiffusion, prompt: str, negative_prompt: str = "",
                 guidance_scale: float = 100.0, t_range: tuple[float, float] = (0.02, 0.98),
                 clip_value: float | None = None, clip_norm: float | None = None, seed: int | None = None,
                 sds_resolution: int | None = None, t_schedule: str = "uniform", total_steps: int | None = None,
                 profile: bool = False):
        self.sd = sd
        self.resolution = sd.resolution if sds_resolution is None else int(sds_resolution)
        step = sd.vae_scale_factor * 2 ** (len(sd.unet.config.block_out_channels) - 1)  # VAE and UNet downsampling
        if self.resolution < step or self.resolution % step:
            raise UserError(f"the score-distillation resolution must be a multiple of {step} px, got {self.resolution}",
                            hint=f"use e.g. 256 or {sd.resolution} (the model's own)")
        self.profile = profile
        self.stage_seconds: dict[str, float] = {}
        self.stage_cpu_seconds: dict[str, float] = {}
        self.guidance_scale = float(guidance_scale)
        self.clip_value, self.clip_norm = clip_value, clip_norm
        self.generator = torch.Generator().manual_seed(seed) if seed is not None else None
        self.sampler = TimestepSampler(sd.alphas_cumprod.cpu(), t_range, self.generator, t_schedule)
        self.total_steps = total_steps
        self._cache: dict[str, Tensor] = {}
        self.set_prompt(prompt, negative_prompt)

    def embedding(self, prompt: str) -> Tensor:
        """Text embedding (1, L, D) of one prompt, cached."""
        if prompt not in self._cache:
            self._cache[prompt] = self.sd.encode_text([prompt])
        return self._cache[prompt]

    def set_prompt(self, prompt: str, negative_prompt: str = "") -> None:
        """Switch prompts; the [uncond, cond] batch is built from cached embeddings."""
        self.prompt, self.negative_prompt = prompt, negative_prompt
        self._embeddings = torch.cat([self.embedding(negative_prompt), self.embedding(prompt)])

    def _noise(self, like: Tensor) -> Tensor:
        if self.generator is None:
            return torch.randn_like(like)
        return torch.randn(like.shape, generator=self.generator, dtype=like.dtype).to(like.device)

    def loss(self, rgb: Tensor, mask: Tensor | None = None, view: int = 0, step: int = 0) -> GuidanceResult:
        """SDS loss of a render (B,3,H,W) in [0,1]; `step` / total_steps drives an annealed t schedule; `mask`
        and `view` are unused (SD sees the whole view)."""
        sd = self.sd
        res = self.resolution
        self._tick(None)
        x = rgb if rgb.shape[-2:] == (res, res) else F.interpolate(rgb, (res, res), mode="bilinear",
                                                                   align_corners=False)
        self._tick("resize")
        latents = sd.encode_images(x, self.generator)
        self._tick("encode_forward")
        t = self.sampler.sample(step / self.total_steps if self.total_steps else 0.0)
        with torch.no_grad():
            noise = self._noise(latents)
            t_batch = torch.full((latents.shape[0],), t, device=latents.device, dtype=torch.long)
            noisy = sd.scheduler.add_noise(latents.detach(), noise, t_batch)
            emb = self._embeddings.repeat_interleave(latents.shape[0], dim=0)
            pred = sd.predict_noise(torch.cat([noisy, noisy]), torch.cat([t_batch, t_batch]), emb)
            self._tick("unet_forward")
            # fp32 from here on, whatever the UNet ran in
            eps = noise_from_prediction(pred.float(), torch.cat([noisy, noisy]).float(), sd.alphas_cumprod[t],
                                        sd.prediction_type)
            eps_uncond, eps_cond = eps.chunk(2)
            eps_hat = eps_uncond + self.guidance_scale * (eps_cond - eps_uncond)
            grad = self.sampler.weight(t) * (eps_hat - noise.float())
        out = distillation_loss(latents, grad, t, self.clip_value, self.clip_norm)
        self._tick("loss")
        return out

    def _tick(self, stage: str | None) -> None:
        """Record the time since the previous tick under `stage` (None starts a step); only when profiling."""
        if not self.profile:
            return
        synchronize(self.sd.device)
        now, cpu = time.perf_counter(), time.process_time()
        if stage is None:
            self.stage_seconds, self.stage_cpu_seconds = {}, {}
        else:
            self.stage_seconds[stage] = now - self._t_last
            self.stage_cpu_seconds[stage] = cpu - self._cpu_last
        self._t_last, self._cpu_last = now, cpu
