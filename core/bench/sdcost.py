"""What one Stable Diffusion score-distillation step costs on this device, stage by stage and option by option.

No SD weights can be downloaded here, but compute does not depend on weight values: the benchmark builds
SD 1.5's (or 2-base's) UNet, VAE and CLIP text encoder from their published configurations with random
weights, assembles them as the loader does (core.models.sd.assemble) and times SDSGuidance steps on a
render of `size` pixels: resize to the SDS resolution, VAE encode forward, the classifier-free UNet pass,
the loss, and the backward (through the encoder to the render). Every speed option (core.models.sd_speed,
SDSGuidance's sds_resolution, token merging) runs in the same process, one after the other or taking turns
over rounds, so their ratios are fair on a shared machine; each step's and stage's CPU time is reported too (on a machine shared with other jobs the
CPU time per step / threads is a steadier guess of an idle machine's wall time than the contended wall
time); peak resident memory is sampled per option. The guidance gradient of every option that changes the
UNet (bf16, token merging) is compared with the fp32 UNet's (cosine) on fixed latents, noise and timesteps. The driver is app/bench/sdcost.py.
"""
from __future__ import annotations

import dataclasses
import hashlib
import statistics
import threading
import time
from dataclasses import asdict, dataclass
from typing import Callable

import torch

PAPER_STEPS = 10000  # stage 2 in the paper (Implementation Details)
FAMILIES = ("sd15", "sd2base")
COSINE_TIMESTEPS = (200, 800)


@dataclass(frozen=True)
class StepOption:
    """One way to run an SDS step: UNet precision, tiny autoencoder or the VAE, SDS resolution."""

    unet_precision: str = "fp32"
    tiny_autoencoder: bool = False
    sds_resolution: int = 512
    channels_last: bool = False
    token_merging: float = 0.0  # ratio of merged tokens in the highest-resolution self-attention (core.models.sd_tome)


OPTIONS: dict[str, StepOption] = {  # fp32 ones first: converting the UNet to bf16 is one-way in a run
    "baseline": StepOption(),
    "tiny_ae": StepOption(tiny_autoencoder=True),
    "sds_256": StepOption(sds_resolution=256),
    "bf16_unet": StepOption(unet_precision="bf16"),
    "bf16+tiny_ae": StepOption("bf16", True),
    "bf16+tiny_ae+sds_256": StepOption("bf16", True, 256),
    "bf16+tiny_ae+nhwc": StepOption("bf16", True, 512, True),
    "bf16+tiny_ae+sds_256+nhwc": StepOption("bf16", True, 256, True),
    # token merging acts at 512 px only (sd_tome.MIN_TOKENS: at 256 px it measured 0.88x-0.91x)
    "bf16+tiny_ae+nhwc+tome": StepOption("bf16", True, 512, True, 0.5),
}


class _HashTokenizer:
    """Token ids of the right shape, different per prompt (so the conditional and unconditional passes differ)."""

    model_max_length = 77

    def __init__(self, vocab_size: int = 49408):
        self.vocab_size = vocab_size

    def __call__(self, prompts, **_):
        rows = []
        for p in prompts:
            h = hashlib.sha256(p.encode()).digest()
            rows.append([h[i % len(h)] * 193 % self.vocab_size for i in range(self.model_max_length)])

        class _Out:
            input_ids = torch.tensor(rows, dtype=torch.long)
        return _Out()


def build_sd(family: str, device, dtype):
    """SD 1.5's or 2-base's parts from their published configurations, random weights, placed like a loaded model."""
    from diffusers import AutoencoderKL, DDIMScheduler, UNet2DConditionModel
    from transformers import CLIPTextConfig, CLIPTextModel

    from repaint_nerf.core.models.sd import assemble

    if family not in FAMILIES:
        raise ValueError(f"unknown family {family!r}; known: {FAMILIES}")
    sd2 = family == "sd2base"
    torch.manual_seed(0)
    unet = UNet2DConditionModel(
        sample_size=64, in_channels=4, out_channels=4, layers_per_block=2,
        block_out_channels=(320, 640, 1280, 1280), cross_attention_dim=1024 if sd2 else 768,
        attention_head_dim=(5, 10, 20, 20) if sd2 else 8, use_linear_projection=sd2,
        down_block_types=("CrossAttnDownBlock2D",) * 3 + ("DownBlock2D",),
        up_block_types=("UpBlock2D",) + ("CrossAttnUpBlock2D",) * 3)
    vae = AutoencoderKL(
        in_channels=3, out_channels=3, latent_channels=4, layers_per_block=2,
        block_out_channels=(128, 256, 512, 512), down_block_types=("DownEncoderBlock2D",) * 4,
        up_block_types=("UpDecoderBlock2D",) * 4, sample_size=512)
    text_cfg = (dict(hidden_size=1024, intermediate_size=4096, num_hidden_layers=23, num_attention_heads=16,
                     hidden_act="gelu") if sd2 else
                dict(hidden_size=768, intermediate_size=3072, num_hidden_layers=12, num_attention_heads=12))
    text = CLIPTextModel(CLIPTextConfig(vocab_size=49408, max_position_embeddings=77, **text_cfg))
    scheduler = DDIMScheduler(num_train_timesteps=1000, beta_schedule="scaled_linear", beta_start=0.00085,
                              beta_end=0.012, clip_sample=False, set_alpha_to_one=False, steps_offset=1)
    return assemble(unet, vae, text, _HashTokenizer(), scheduler, device, dtype)


def build_tiny_autoencoder(device):
    """TAESD's architecture (diffusers AutoencoderTiny defaults) with random weights, frozen."""
    from diffusers import AutoencoderTiny

    torch.manual_seed(1)
    return AutoencoderTiny().eval().requires_grad_(False).to(device)


class PeakRSS:
    """Peak resident memory of this process while active, sampled every 20 ms from /proc (Linux)."""

    def __init__(self, period: float = 0.02):
        self.period, self.peak, self._stop = period, 0, threading.Event()

    @staticmethod
    def current_mb() -> float:
        try:
            with open("/proc/self/statm") as f:
                import os

                return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2 ** 20
        except OSError:
            return float("nan")

    def _loop(self) -> None:
        while not self._stop.is_set():
            self.peak = max(self.peak, self.current_mb())
            self._stop.wait(self.period)

    def __enter__(self) -> "PeakRSS":
        self.peak = self.current_mb()
        self._thread = threading.Thread(target=self._loop, daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()
        self.peak = max(self.peak, self.current_mb())


def _count(m) -> int:
    return sum(p.numel() for p in m.parameters())


def _guidance_grads(sd, guidance, latents: torch.Tensor, noise: torch.Tensor) -> list[torch.Tensor]:
    """The SDS guidance gradient w(t)(eps_hat - eps) at COSINE_TIMESTEPS for fixed latents and noise (fp32),
    with the UNet as it is set now (precision, token merging)."""
    out = []
    emb = guidance._embeddings
    with torch.no_grad():
        for t in COSINE_TIMESTEPS:
            tb = torch.full((1,), t, device=sd.device, dtype=torch.long)
            noisy = sd.scheduler.add_noise(latents, noise, tb)
            eps = sd.predict_noise(torch.cat([noisy, noisy]), torch.cat([tb, tb]), emb).float()
            u, c = eps.chunk(2)
            out.append(guidance.sampler.weight(t) * (u + guidance.guidance_scale * (c - u) - noise))
    return out


def _changes_unet(opt: "StepOption") -> bool:
    return opt.unet_precision != "fp32" or opt.token_merging > 0


def _cosine(a: torch.Tensor, b: torch.Tensor) -> float:
    return float(torch.nn.functional.cosine_similarity(a.flatten().double(), b.flatten().double(), dim=0))


def _time_steps(sd, guidance, tiny, opt: StepOption, size: int, steps: int, device, raw: dict,
                warm_up: bool) -> None:
    """Time `steps` SDS steps under `opt` (after one untimed warm-up step when `warm_up`), appending the
    wall and CPU seconds, per-stage figures and the peak RSS to `raw`."""
    from repaint_nerf.core.device import synchronize
    from repaint_nerf.core.models.sd_speed import set_channels_last, unet_dtype
    from repaint_nerf.core.models.sd_tome import set_token_merging

    sd.set_unet_dtype(unet_dtype(opt.unet_precision, device))
    sd.tiny_vae = tiny if opt.tiny_autoencoder else None
    set_channels_last(sd, opt.channels_last)
    set_token_merging(sd.unet, opt.token_merging)
    guidance.resolution = opt.sds_resolution
    gen = torch.Generator().manual_seed(len(raw.setdefault("totals", [])))
    with PeakRSS() as mem:
        for i in range(steps + int(warm_up)):
            rgb = torch.rand(1, 3, size, size, generator=gen).to(device).requires_grad_(True)
            synchronize(device)
            t0, c0 = time.perf_counter(), time.process_time()
            out = guidance.loss(rgb)
            t1, c1 = time.perf_counter(), time.process_time()
            out["loss"].backward()
            synchronize(device)
            t2, c2 = time.perf_counter(), time.process_time()
            if not (rgb.grad is not None and bool(torch.isfinite(rgb.grad).all())):
                raise RuntimeError(f"non-finite gradient with option {opt}")
            if i or not warm_up:  # the first step warms up allocators and kernels
                raw["totals"].append(t2 - t0)
                raw.setdefault("cpus", []).append(c2 - c0)
                raw.setdefault("stages", []).append(
                    {**guidance.stage_seconds, "rest": (t1 - t0) - sum(guidance.stage_seconds.values()),
                     "backward": t2 - t1})
                raw.setdefault("cpu_stages", []).append(
                    {**guidance.stage_cpu_seconds, "rest": (c1 - c0) - sum(guidance.stage_cpu_seconds.values()),
                     "backward": c2 - c1})
    raw["peak"] = max(raw.get("peak", 0.0), mem.peak)


def _summary(opt: StepOption, raw: dict) -> dict:
    """Medians over every timed step of an option (all rounds)."""
    totals, cpus, stages, cpu_stages = raw["totals"], raw["cpus"], raw["stages"], raw["cpu_stages"]
    step_s = statistics.median(totals)
    names = stages[0].keys()
    return {"settings": asdict(opt), "step_seconds": step_s, "step_seconds_all": totals,
            "step_cpu_seconds_all": cpus,
            "stages_seconds": {k: statistics.median(s[k] for s in stages) for k in names},
            "step_cpu_seconds": statistics.median(cpus),
            "stages_cpu_seconds": {k: statistics.median(s[k] for s in cpu_stages) for k in names},
            "idle_step_seconds_guess": statistics.median(cpus) / max(1, torch.get_num_threads()),
            "peak_rss_mb": raw["peak"], "paper_steps_hours": step_s * PAPER_STEPS / 3600.0}


def measure(device=None, steps: int = 2, size: int = 128, family: str = "sd15",
            options: list[str] | None = None, progress: Callable[[str], None] | None = None,
            on_option: Callable[[dict], None] | None = None, rounds: int = 1) -> dict:
    """Time an SDS step for each of `options` (names in OPTIONS; default all) in this one process.

    With `rounds` > 1 the options take turns, `steps` steps each per round (the fp32 ones' rounds first:
    converting to bf16 is one-way), so a load that comes and goes on a shared machine weighs on all alike.
    Returns figures per option (median step and per-stage wall and CPU seconds, peak RSS), their speed-up
    over the baseline, and for each option that changes the UNet (precision, token merging) the cosine of
    its guidance gradient with the fp32 UNet's. `on_option(result)` gets the result so far after each option
    (a long run's figures survive an interruption).
    """
    from repaint_nerf.core.device import describe, get_device, is_cuda
    from repaint_nerf.core.errors import UserError
    from repaint_nerf.core.repaint.sds import SDSGuidance

    names = list(OPTIONS) if not options else options
    unknown = [n for n in names if n not in OPTIONS]
    if unknown or steps < 1 or size < 8 or rounds < 1:
        raise UserError(f"bad sdcost request: unknown options {unknown}, steps {steps}, size {size}, rounds {rounds}",
                        hint=f"options: {', '.join(OPTIONS)}; steps >= 1; size >= 8; rounds >= 1")
    say = progress or (lambda _m: None)
    device = get_device(device)
    cuda = is_cuda(device)
    base_dtype = torch.float16 if cuda else torch.float32
    t0 = time.perf_counter()
    with PeakRSS() as mem_build:
        sd = build_sd(family, device, base_dtype)
    build_s = time.perf_counter() - t0
    tiny = build_tiny_autoencoder(device) if any(OPTIONS[n].tiny_autoencoder for n in names) else None
    guidance = SDSGuidance(sd, "a blue rose in leaves", seed=0, profile=True)
    result: dict = {
        "device": describe(device), "threads": torch.get_num_threads(), "family": family,
        "architecture": f"Stable Diffusion {'2-base' if family == 'sd2base' else '1.5'} "
                        "(random weights from its configuration)",
        "parameters_m": {"unet": _count(sd.unet) / 1e6, "vae": _count(sd.vae) / 1e6,
                         "text_encoder": _count(sd.text_encoder) / 1e6,
                         **({"tiny_autoencoder": _count(tiny) / 1e6} if tiny is not None else {})},
        "render_size": size, "model_resolution": sd.resolution, "build_seconds": build_s,
        "build_peak_rss_mb": mem_build.peak, "timed_steps_per_option": steps * rounds, "rounds": rounds,
        "paper_steps": PAPER_STEPS,
        "options": {},
    }
    # Guidance gradients on fixed latents and noise per SDS resolution: the fp32 UNet's (computed before any
    # option converts it to bf16, which is one-way in a run), then each UNet-changing option's, as cosines.
    fixed: dict[int, tuple[torch.Tensor, torch.Tensor]] = {}
    ref_grads: dict[int, list[torch.Tensor]] = {}
    for name in names:
        res = OPTIONS[name].sds_resolution
        if _changes_unet(OPTIONS[name]) and not cuda and res not in fixed:
            gen = torch.Generator().manual_seed(2)
            shape = (1, 4, res // sd.vae_scale_factor, res // sd.vae_scale_factor)
            fixed[res] = (torch.randn(shape, generator=gen).to(device), torch.randn(shape, generator=gen).to(device))
    if fixed:
        sd.set_unet_dtype(torch.float32)
        ref_grads = {res: _guidance_grads(sd, guidance, *fl) for res, fl in fixed.items()}
    def actual(name: str) -> StepOption:
        opt = OPTIONS[name]
        return dataclasses.replace(opt, unet_precision="fp16") if cuda and opt.unet_precision == "fp32" else opt

    raw: dict[str, dict] = {n: {} for n in names}
    groups = [[n for n in names if OPTIONS[n].unet_precision == "fp32"],
              [n for n in names if OPTIONS[n].unet_precision != "fp32"]]
    for group in groups:
        for rnd in range(rounds):
            for name in group:
                opt = actual(name)
                say(f"sdcost: {name} (round {rnd + 1}/{rounds}) ...")
                _time_steps(sd, guidance, tiny, opt, size, steps, device, raw[name], warm_up=rnd == 0)
                r = {**result["options"].get(name, {}), **_summary(opt, raw[name])}
                result["options"][name] = r
                if rnd == 0 and opt.sds_resolution in ref_grads and _changes_unet(opt):
                    got = _guidance_grads(sd, guidance, *fixed[opt.sds_resolution])
                    ref = ref_grads[opt.sds_resolution]
                    r["grad_cosine"] = {str(t): _cosine(a, b) for t, a, b in zip(COSINE_TIMESTEPS, ref, got)}
                    r["grad_rel_error"] = {str(t): float((a - b).norm() / a.norm().clamp_min(1e-12))
                                           for t, a, b in zip(COSINE_TIMESTEPS, ref, got)}
                say(f"sdcost: {name}: {r['step_seconds']:.2f} s/step ({r['step_cpu_seconds']:.1f} CPU s), peak "
                    f"{r['peak_rss_mb']:.0f} MB, " + ", ".join(f"{k} {v:.2f}" for k, v in r["stages_seconds"].items())
                    + (f", gradient cosine vs fp32 {r['grad_cosine']}" if "grad_cosine" in r else ""))
                _speedups(result)
                if on_option is not None:
                    on_option(result)
    if "grad_cosine" in result["options"].get("bf16_unet", {}):
        result["bf16_grad_cosine"] = result["options"]["bf16_unet"]["grad_cosine"]
        result["bf16_grad_rel_error"] = result["options"]["bf16_unet"]["grad_rel_error"]
    _speedups(result)
    return result


def _speedups(result: dict) -> None:
    """Baseline time / option time, by wall time and by CPU time (the steadier one on a shared machine)."""
    base = result["options"].get("baseline")
    if base is not None:
        result["speedup_vs_baseline"] = {n: base["step_seconds"] / r["step_seconds"]
                                         for n, r in result["options"].items()}
        result["cpu_speedup_vs_baseline"] = {n: base["step_cpu_seconds"] / r["step_cpu_seconds"]
                                             for n, r in result["options"].items()}
