"""How stage-1 cost grows with the image size (issue 18 item 4): per size, the scene loaded at that long side is
trained for a fixed budget, and the time to each target test PSNR (25 / 30 dB unless told: a real capture may
never reach 30), steps/s early and later, samples per ray, the time of one full-view render, the closing
evaluation and the peak RSS are measured. Each size runs in a
fresh process (spawned), so its peak RSS is its own. Returns dicts; the driver is app/bench/scale.py.

A larger image holds detail a smaller one lacks, so a fixed PSNR near its ceiling asks it for more than the same PSNR
asks of the smaller. Each larger size is therefore also scored on the smallest size's images (seconds_to_<t>_content:
the content both hold), and `detail_ceiling_psnr` says what those images alone would score at the larger size.
"""
from __future__ import annotations

import multiprocessing
import resource
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

from repaint_nerf.core.bench.recon import eval_times, time_to

TARGETS = (25.0, 30.0)
EARLY_SECONDS = 30.0  # training seconds counted as "early" (an untrained, foggy field)
TRACE_POINTS = 60  # rows of the per-size trace (steps/s, samples per ray, grid occupancy along training)
# Evaluations every second up to this many training seconds, besides the evenly spaced ones: a 128-px real capture
# crosses its targets within 5-10 s, between the evenly spaced evaluations of a 120-s run (5 s apart), where a
# linear interpolation of a curve that rises fastest first placed its crossing late, and the size ratios low
DENSE_UNTIL = 10
PSNR_MEASURE = ("test PSNR of the bounded evaluation (Stage1Trainer.evaluate: EVAL_VIEWS test views spread over "
                "the split, an EVAL_GRID x EVAL_GRID grid of pixels spread over each view, at most EVAL_SAMPLE_CAP "
                "samples per ray), "
                "run at `evals` evenly spaced points of the training budget and every second of the first "
                "`dense_until` seconds; evaluation time is not counted as training time; seconds_to_* interpolate "
                "linearly between evaluations")


def goal_target(result: dict | None) -> float:
    """The PSNR (dB) a run's size ratios are read at: the highest of its targets (30 dB unless it was told others)."""
    return max((result or {}).get("targets") or TARGETS)


def size_ratio(result: dict, size: int, smallest: int, target: float) -> float | None:
    """Seconds to `target` dB at `size` over those at `smallest` (issue 33: at most 2x at 256 and 4x at 512 px of
    128); None where either size did not reach it."""
    seconds = {e.get("size"): e.get(f"seconds_to_{target:g}") for e in result.get("sizes", [])}
    lo, hi = seconds.get(smallest), seconds.get(size)
    return hi / lo if lo and hi is not None else None


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # kilobytes on Linux


def _mean(xs: list[float]) -> float | None:
    return sum(xs) / len(xs) if xs else None


def render_ms(trainer, repeats: int = 3, warmup: int = 1) -> tuple[float, float]:
    """(median ms, samples per ray) of rendering test view 0 at its full size, as `render` does (no sample cap),
    after `warmup` untimed renders: the evaluations before render a grid of pixels, not a full view, so the first
    full view pays for touching its buffers (ethiopian_head at 256 px: 656 ms, then 327-337 ms)."""
    import torch

    from repaint_nerf.core.device import synchronize
    from repaint_nerf.core.render.renderer import RenderOptions, render_camera

    cams = trainer.scene.field_cameras(trainer.eval_split()).to(trainer.device)
    opts = RenderOptions(outputs=("rgb",), background=trainer.eval_background(), perturb=False,
                         t_threshold=trainer.cfg.t_threshold, max_samples=trainer.march_samples)
    trainer.field.eval()
    times, spr = [], 0.0
    with torch.no_grad():
        for i in range(warmup + repeats):
            synchronize(trainer.device)
            t0 = time.perf_counter()
            out = render_camera(trainer.field, trainer.grid, cams, 0, opts)
            synchronize(trainer.device)
            if i >= warmup:
                times.append(time.perf_counter() - t0)
            spr = float(out["stats"]["samples_per_ray"])
    trainer.field.train()
    return 1000.0 * sorted(times)[len(times) // 2], spr


def detail_ceiling(scene, smaller, background) -> float:
    """Mean PSNR (dB) over the test views of `smaller`'s images (the same capture loaded smaller) resized bilinearly to
    `scene`'s size against `scene`'s own, both over `background`: what a field that held exactly the smaller images'
    content would score at this size. A target near it asks the larger size for detail the smaller never had."""
    import cv2
    import numpy as np

    from repaint_nerf.core.train.stage1 import target_image

    split = next((s for s in ("test", "val", "train") if s in scene.splits and len(scene.splits[s])), "train")
    scores = []
    for big, small in zip(scene.split(split).images, smaller.split(split).images):
        ref = target_image(big, background).cpu().numpy()
        low = cv2.resize(target_image(small, background).cpu().numpy(), (ref.shape[1], ref.shape[0]),
                         interpolation=cv2.INTER_LINEAR)
        scores.append(-10.0 * np.log10(max(float(np.mean((low - ref) ** 2)), 1e-12)))
    return float(np.mean(scores))


def measure_size(scene_path: str, size: int, seconds: float, evals: int = 12, seed: int = 0,
                 device: str | None = None, rays: int | None = None,
                 early_seconds: float = EARLY_SECONDS, early_max_samples: int | None = None,
                 targets: tuple[float, ...] = TARGETS, dense_until: int = DENSE_UNTIL,
                 content_size: int | None = None) -> dict:
    """Train the scene loaded at long side `size` for `seconds` (evaluation excluded) and measure it; one
    entry of the `sizes` list (see the module docstring), with seconds_to_<t> for each of `targets` (dB).
    `early_max_samples` overrides TrainConfig's (0 = the image's sample budget from the first step, as before
    coarse-to-fine marching). With `content_size` below `size`, every evaluation also scores the field on the
    images loaded at that size (the content both sizes hold: seconds_to_<t>_content), and `detail_ceiling_psnr`
    is what the smaller images alone would score (detail_ceiling)."""
    from repaint_nerf.core.device import describe
    from repaint_nerf.core.scene.loaders.detect import load_scene
    from repaint_nerf.core.train.stage1 import Stage1Trainer, TrainConfig

    t_load = time.perf_counter()
    scene = load_scene(scene_path, max_size=int(size))
    load_seconds = time.perf_counter() - t_load
    cfg = TrainConfig(seed=seed)
    if rays:
        cfg.rays_per_batch = rays
    if early_max_samples is not None:
        cfg.early_max_samples = int(early_max_samples)
    trainer = Stage1Trainer(scene, None, cfg, device=device)
    trainer.plan(seconds=seconds)
    content = load_scene(scene_path, max_size=int(content_size)) if content_size and content_size < size else None
    early = {"steps": 0, "seconds": 0.0, "samples": [], "candidates": []}
    late = {"steps": 0, "seconds": 0.0, "samples": [], "candidates": []}
    trace: list[dict] = []
    span = {"steps": 0, "seconds": 0.0, "samples": 0.0}
    work = {"samples": 0.0}  # samples evaluated with grad so far (rays x samples per ray): the load-free cost

    def on_step(info: dict) -> None:
        part = early if trainer.train_seconds - info["seconds"] < early_seconds else late
        part["steps"] += 1
        part["seconds"] += info["seconds"]
        part["samples"].append(info.get("samples_per_ray", 0.0))
        part["candidates"].append(info.get("candidates_per_ray", 0.0))
        span["steps"] += 1
        span["seconds"] += info["seconds"]
        span["samples"] += info.get("samples_per_ray", 0.0)
        work["samples"] += info.get("samples_per_ray", 0.0) * trainer.cfg.rays_per_batch
        if trainer.train_seconds >= seconds * (len(trace) + 1) / TRACE_POINTS:
            trace.append({"seconds": trainer.train_seconds, "step": trainer.step_count,
                          "steps_per_s": span["steps"] / max(span["seconds"], 1e-9),
                          "samples_per_ray": span["samples"] / span["steps"],
                          "march_samples": trainer.march_samples,
                          "occupied": trainer.grid.occupied_fraction(), "batch_psnr": info.get("psnr")})
            span.update(steps=0, seconds=0.0, samples=0.0)

    eval_total = 0.0
    curve: list[dict] = []
    for t in [0.0] + eval_times(seconds, evals, report_at=tuple(range(1, int(dense_until) + 1)), minute_curve=False):
        if t > 0:
            trainer.train(seconds=t, callback=on_step)
        ev = trainer.evaluate()
        eval_total += ev["seconds"]
        point = {"seconds": trainer.train_seconds, "step": trainer.step_count, "msamples": work["samples"] / 1e6,
                 "psnr": ev["psnr"]}
        if content is not None:
            point["psnr_content"] = trainer.evaluate(scene=content)["psnr"]
        curve.append(point)
    closing = trainer.evaluate(with_ssim=True)
    ms, render_spr = render_ms(trainer)
    h, w = scene.train.images[0].shape[:2]
    every = early["samples"] + late["samples"]
    return {
        "size": int(size),
        "image_size": [int(h), int(w)],
        "train_views": len(scene.train),
        **{f"seconds_to_{t:g}": time_to(curve, t) for t in targets},
        # the same targets in steps and in millions of samples evaluated with grad: figures a shared machine's load
        # does not change, for comparing sizes measured at different times
        **{f"{name}_to_{t:g}": time_to([{**p, "seconds": p[key]} for p in curve], t)
           for name, key in (("steps", "step"), ("msamples", "msamples")) for t in targets},
        **({f"seconds_to_{t:g}_content": time_to([{**p, "psnr": p["psnr_content"]} for p in curve], t)
            for t in targets} if content is not None else {}),
        "content_size": int(content_size) if content is not None else None,
        "detail_ceiling_psnr": detail_ceiling(scene, content, trainer.eval_background()) if content is not None
        else None,
        "steps_per_s_early": early["steps"] / early["seconds"] if early["seconds"] > 0 else None,
        "steps_per_s": late["steps"] / late["seconds"] if late["seconds"] > 0 else None,
        "steps_per_s_overall": trainer.step_count / max(trainer.train_seconds, 1e-9),
        "samples_per_ray": _mean(every),
        "samples_per_ray_early": _mean(early["samples"]),
        "density_samples_per_ray": _mean(early["candidates"] + late["candidates"]),
        "density_samples_per_ray_early": _mean(early["candidates"]),
        "render_ms": ms,
        "render_samples_per_ray": render_spr,
        "eval_seconds": closing["seconds"],
        "eval_fraction_of_training": closing["seconds"] / max(trainer.train_seconds, 1e-9),
        "eval_seconds_along_training": eval_total,
        "train_seconds": trainer.train_seconds,
        "steps": trainer.step_count,
        "steps_early": early["steps"],
        "max_samples": trainer.cfg.max_samples,
        "early_max_samples": trainer.cfg.early_max_samples,
        "fog_cleared_step": trainer.fog_cleared_step,  # the march ramp's start (stage1.march_budget)
        "final_psnr": closing["psnr"],
        "final_ssim": closing["ssim"],
        "load_seconds": load_seconds,
        "peak_rss_mb": _peak_rss_mb(),
        "curve": curve,
        "trace": trace,
        "device": describe(trainer.device),
    }


def measure(scene_path: str | Path, sizes: list[int], seconds: float, evals: int = 12, seed: int = 0,
            device: str | None = None, rays: int | None = None, early_seconds: float = EARLY_SECONDS,
            early_max_samples: int | None = None, isolate: bool = True, progress: Callable[[dict], None] | None = None,
            targets: tuple[float, ...] = TARGETS, dense_until: int = DENSE_UNTIL) -> dict:
    """`measure_size` for each size, each in a fresh spawned process when `isolate` (peak RSS per size);
    `progress(entry)` gets each size's entry as it completes."""
    entries = []
    for size in sizes:
        kw = dict(evals=evals, seed=seed, device=device, rays=rays, early_seconds=early_seconds,
                  early_max_samples=early_max_samples, targets=tuple(float(t) for t in targets),
                  dense_until=int(dense_until), content_size=int(min(sizes)))
        if isolate:
            with ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("spawn")) as pool:
                entry = pool.submit(measure_size, str(scene_path), int(size), float(seconds), **kw).result()
        else:
            entry = measure_size(str(scene_path), int(size), float(seconds), **kw)
        entries.append(entry)
        if progress is not None:
            progress(entry)
    return {
        "sizes": entries,
        "scene": {"path": str(scene_path), "name": Path(scene_path).name},
        "seconds_per_size": float(seconds),
        "targets": [float(t) for t in targets],
        "early_seconds": float(early_seconds),
        "dense_until": int(dense_until),
        "psnr_measured": PSNR_MEASURE,
        "isolated_processes": bool(isolate),
        "peak_rss_measured": "ru_maxrss of the process that ran the size" + (
            " (a fresh spawned process per size)" if isolate else " (one process for all sizes: cumulative)"),
        "device": entries[0]["device"] if entries else None,
    }
