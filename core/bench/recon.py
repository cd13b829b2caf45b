"""Stage-1 reconstruction speed, measured: test PSNR against training seconds (evaluation excluded from the
clock), render time, samples per ray with and without the occupancy grid, peak memory and a per-stage
breakdown of a training step. Returns dicts; the `bench recon` driver (app/bench/recon.py) prints and plots.
"""
from __future__ import annotations

import resource
import time
from pathlib import Path
from typing import Callable

TARGET_PSNR = 25.4
# A reference measured ELSEWHERE, not by this benchmark: nerfstudio's nerfacto, run once side by side on this
# project's 2-core CPU (issue 3) through its PyTorch hash-grid fallback in a configuration reduced for CPU
# (1024 rays per batch, fewer samples), on a 128x128, 100-view synthetic scene (primitives on a checker floor);
# "seconds" are uncontended wall-clock training seconds read from nerfstudio's log, the render time one
# 128x128 view through `ns-render`, the RSS the training process's peak. Ratios against it compare a run of
# this program with those fixed figures, so they are only meaningful for the same scene on a similar CPU.
NERFACTO = {
    "method": "nerfstudio nerfacto (PyTorch hash-grid fallback, 1024 rays/batch, fewer samples)",
    "source": "measured elsewhere (issue 3, side by side on the project's 2-core CPU, 128x128 100-view "
              "synthetic scene), not by this benchmark",
    "iters_per_s": 1.19,
    "curve": [{"seconds": 150.0, "psnr": 16.98}, {"seconds": 300.0, "psnr": 20.84}, {"seconds": 560.0, "psnr": 25.43}],
    "seconds_to_25_4": 560.0,
    "iters_to_25_4": 669,
    "render_s_128": 7.7,
    "peak_rss_gb": 1.85,
}


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # kilobytes on Linux


def _encoder_modules(field) -> list:
    import torch

    return [m for m in field.modules() if isinstance(m, torch.nn.Module) and "Encoding" in type(m).__name__]


def breakdown(trainer, steps: int) -> dict:
    """Mean seconds per stage of `steps` profiled training steps, and their fractions of the step time."""
    from repaint_nerf.core.device import synchronize

    enc_time = [0.0]

    def pre(mod, inp):
        synchronize(trainer.device)
        mod._bench_t0 = time.perf_counter()

    def post(mod, inp, out):
        synchronize(trainer.device)
        enc_time[0] += time.perf_counter() - mod._bench_t0

    hooks = []
    for m in _encoder_modules(trainer.field):
        hooks += [m.register_forward_pre_hook(pre), m.register_forward_hook(post)]
    trainer.profile = True
    acc: dict[str, float] = {}
    total = 0.0
    try:
        for _ in range(steps):
            enc_time[0] = 0.0
            info = trainer.step()
            t = trainer.last_times
            r = t.get("render", {})
            field_s = r.get("field", 0.0)
            enc = min(enc_time[0], field_s)
            parts = {
                "ray_sampling": t.get("batch", 0.0) + r.get("sampling", 0.0),
                "encoding": enc,
                "mlps": field_s - enc,
                "compositing": r.get("compositing", 0.0),
                "backward": t.get("backward", 0.0),
                "optimizer": t.get("optimizer", 0.0),
                "grid_update": t.get("grid_update", 0.0),
            }
            parts["other"] = max(0.0, info["seconds"] - sum(parts.values()))
            for k, v in parts.items():
                acc[k] = acc.get(k, 0.0) + v
            total += info["seconds"]
    finally:
        trainer.profile = False
        for h in hooks:
            h.remove()
    n = max(1, steps)
    return {"step_ms": 1000 * total / n,
            "ms": {k: 1000 * v / n for k, v in acc.items()},
            "fraction": {k: v / max(total, 1e-12) for k, v in acc.items()}}


def render_figures(trainer) -> dict:
    """Time to render one 128x128 test view, and samples per ray with the trained grid and without skipping."""
    import torch

    from repaint_nerf.core.device import synchronize
    from repaint_nerf.core.render.occupancy import grid_for_field
    from repaint_nerf.core.render.renderer import RenderOptions, render_camera

    split = trainer.eval_split()
    cams = trainer.scene.field_cameras(split).to(trainer.device)
    scale = 128.0 / float(cams.width[0])
    opts = RenderOptions(outputs=("rgb",), background=trainer.eval_background(), perturb=False,
                         t_threshold=trainer.cfg.t_threshold, max_samples=trainer.march_samples)
    trainer.field.eval()
    times = []
    with torch.no_grad():
        out = render_camera(trainer.field, trainer.grid, cams, 0, opts, scale=scale)  # warm-up (and compile)
        for _ in range(3):
            synchronize(trainer.device)
            t0 = time.perf_counter()
            out = render_camera(trainer.field, trainer.grid, cams, 0, opts, scale=scale)
            synchronize(trainer.device)
            times.append(time.perf_counter() - t0)
        g = trainer.grid
        full = grid_for_field(trainer.field, g.resolution, g.cascades, device=trainer.device)
        full.mark_all()
        out_full = render_camera(trainer.field, full, cams, 0, opts, scale=scale)
        # training-style rendering (no early stop between rounds), for the samples a step actually evaluates
        train_opts = RenderOptions(outputs=("rgb",), background=trainer.eval_background(), strategy="filter",
                                   t_threshold=trainer.cfg.t_threshold, max_samples=trainer.march_samples)
        out_train = render_camera(trainer.field, trainer.grid, cams, 0, train_opts, scale=scale)
        out_train_full = render_camera(trainer.field, full, cams, 0, train_opts, scale=scale)
    trainer.field.train()
    st, sf = out["stats"], out_full["stats"]
    return {
        "render_ms_128": 1000 * sorted(times)[len(times) // 2],
        "samples_per_ray": {
            "with_grid": st["samples_per_ray"], "without_grid": sf["samples_per_ray"],
            "candidates_with_grid": st.get("candidates_per_ray"), "candidates_without_grid": sf.get("candidates_per_ray"),
            "training_pass_with_grid": out_train["stats"]["samples_per_ray"],
            "training_pass_without_grid": out_train_full["stats"]["samples_per_ray"],
            "occupied_fraction": trainer.grid.occupied_fraction(),
        },
    }


FOG_STEPS = 50  # issue 33: the first 50 steps cost at most 2x a later one


def fog_figures(step_seconds: list[float], first: int = FOG_STEPS) -> dict:
    """The fog phase's cost: mean seconds of the first `first` steps (grid sweeps included) against the median
    step of the run's second half (at least `first` steps after them); None where the run is too short."""
    import statistics

    later = step_seconds[max(first, len(step_seconds) // 2):]
    if len(step_seconds) < first or len(later) < first // 5:
        return {"first_steps": first, "first_mean_ms": None, "later_median_ms": None, "ratio": None}
    a, b = statistics.fmean(step_seconds[:first]), statistics.median(later)
    return {"first_steps": first, "first_mean_ms": 1000 * a, "later_median_ms": 1000 * b, "ratio": a / b}


def time_to(curve: list[dict], target: float) -> float | None:
    for a, b in zip([None] + curve[:-1], curve):
        if b["psnr"] >= target:
            if a is None or b["psnr"] == a["psnr"]:
                return b["seconds"]
            f = (target - a["psnr"]) / (b["psnr"] - a["psnr"])  # linear between evaluations
            return a["seconds"] + f * (b["seconds"] - a["seconds"])
    return None


MINUTE_CURVE = tuple(range(10, 61, 10))  # the first-minute curve: evaluations at 10, 20, ..., 60 training seconds
REPORT_AT = (60.0, 120.0, 300.0)  # the fixed times issue 32's table reports PSNR and SSIM at


def eval_times(seconds: float, evals: int, report_at=REPORT_AT, minute_curve: bool = True) -> list[float]:
    """The training seconds to evaluate at: `evals` evenly spaced, the first-minute curve and the report times
    (those within the budget), the end of the run always last."""
    times = {seconds * k / evals for k in range(1, evals + 1)} | {float(seconds)}
    times |= {float(t) for t in (MINUTE_CURVE if minute_curve else ()) if t < seconds}
    times |= {float(t) for t in report_at if 0 < t < seconds}
    return sorted(times)


def at_times(curve: list[dict], report_at) -> dict:
    """{"60": point, ...}: the curve point evaluated at each report time (None past the run's budget)."""
    by_target = {p.get("target"): p for p in curve}
    return {f"{t:g}": by_target.get(float(t)) for t in report_at}


def evaluation_protocol(scene, trainer, eval_views: int | None, bounded_curve: bool = False) -> dict:
    """How held-out views were scored, for the JSON: which split, how it was held out, the appearance code used."""
    codes = getattr(trainer.field, "appearance", None) is not None
    pixels = "every pixel of each view (full renders), time not counted in training seconds"
    if bounded_curve:
        pixels += ("; only at the report times and the end: the other curve points (marked 'bounded') score an "
                   "evenly spread pixel grid of each view (Stage1Trainer.evaluate)")
    return {"split": trainer.eval_split(), "holdout": scene.extra.get("holdout"),
            "views": "all" if eval_views is None else f"the first {eval_views}",
            "pixels": pixels,
            "appearance": ("the mean code of the training images for every held-out view, as nerfstudio evaluates "
                           "nerfacto (use_average_appearance_embedding); no code is fitted to a test image")
            if codes else "no appearance codes (off for this scene)"}


def measure(scene_path: Path, seconds: float, evals: int = 12, eval_views: int | None = None,
            rays: int | None = None, lr: float | None = None, seed: int = 0, profile_steps: int = 8,
            downscale: float = 1.0, device: str | None = None,
            progress: Callable[[dict], None] | None = None, holdout_every: int | None = None,
            report_at=REPORT_AT, minute_curve: bool = True, bounded_curve: bool | None = None,
            kind: str | None = None, distortion: float | None = None, as_train: bool = False) -> dict:
    """Train stage 1 from scratch on a scene for `seconds` with test evaluations along the way (`evals` evenly
    spaced, the first-minute curve, and PSNR with SSIM at each `report_at` time); the result dict holds the curve,
    the figures at the report times, final PSNR/SSIM, render figures, the breakdown and the nerfacto reference
    (with its ratios, labelled as figures measured elsewhere). A capture without its own test split holds out
    every `holdout_every`-th view (default 8). `progress(point)` gets each curve point. `kind` overrides the
    detected scene kind. By default the field learns colour alone, as nerfacto and instant-ngp train; `as_train`
    adds what the `train` command distils besides (paper Eq. s1): the default teacher's features, arriving on a
    background thread while colour trains, and the depth priors (`train_teachers`)."""
    from repaint_nerf.core.scene.loaders.detect import load_scene
    from repaint_nerf.core.train.stage1 import TrainConfig, check_distortion_weight

    cfg = TrainConfig(seed=seed)
    if distortion is not None:  # before the scene loads: a bad weight fails at once
        cfg.lambda_distortion = check_distortion_weight(distortion)
    scene = load_scene(scene_path, downscale, kind=kind, holdout_every=holdout_every)
    if bounded_curve is None:  # a capture (no rendered test split) evaluates every pixel only at the report times
        bounded_curve = scene.extra.get("holdout", {}).get("rule") != "the dataset's own test split"
    if rays:
        cfg.rays_per_batch = rays
    if lr:
        cfg.lr = lr
    teachers = train_teachers(scene) if as_train else None
    try:
        return _measure(scene, scene_path, cfg, teachers, seconds, evals, eval_views, profile_steps, device, progress,
                        report_at, minute_curve, bounded_curve)
    finally:
        if teachers is not None:
            stop = getattr(teachers["features"], "stop", None)  # a stream still writing into the workspace about to go
            if stop is not None:
                stop()
            teachers["dir"].cleanup()


def train_teachers(scene) -> dict:
    """The `train` command's teachers for `scene` in a fresh temporary workspace, in the order a first `train`
    computes them (session.py): the feature stream first, whose teacher runs on its own thread while the trainer
    consumes its codes, then the depth priors beside it, with the seconds they took (the command spends them before
    training; they are not training seconds, and the teacher's thread has that head start there too)."""
    import tempfile

    from repaint_nerf.core.teachers.stage1_targets import FEATURE_DIMS, depth_priors, feature_stream
    from repaint_nerf.core.workspace.workspace import Workspace

    tmp = tempfile.TemporaryDirectory(prefix="repaint-nerf-bench-ws-")
    ws = Workspace.open_or_create(Path(tmp.name) / "ws")
    notes: list[str] = []
    features = feature_stream(scene, ws, FEATURE_DIMS, notes=notes)
    t0 = time.perf_counter()
    try:
        depth = depth_priors(scene, ws, notes)
    except BaseException:
        features.stop()  # the teacher's thread must not outlive a failed setup
        raise
    depth_s = time.perf_counter() - t0
    what = {"features": str(ws.settings.get("teacher") or "the default teacher"),
            "depth_priors": None if depth is None else ("SfM points" if scene.points is not None and len(scene.points)
                                                         else "triangulated from the known poses"),
            "depth_priors_s": round(depth_s, 2), "notes": notes}
    return {"dir": tmp, "features": features, "depth": depth, "what": what}


def _measure(scene, scene_path: Path, cfg, teachers: dict | None, seconds: float, evals: int, eval_views: int | None,
             profile_steps: int, device, progress, report_at, minute_curve: bool, bounded_curve: bool) -> dict:
    """`measure`'s run on a loaded scene (its trainer built with `teachers`, from `train_teachers`, when given)."""
    import torch

    from repaint_nerf.core.device import describe
    from repaint_nerf.core.train.stage1 import Stage1Trainer

    trainer = Stage1Trainer(scene, None, cfg, device=device,
                            feature_targets=None if teachers is None else teachers["features"],
                            depth_priors=None if teachers is None else teachers["depth"])
    trainer.plan(seconds=seconds)
    # Every pixel of the first eval views, as the figures in earlier notes were measured (training's own
    # evaluation is the bounded one; the curve's time excludes evaluation either way).
    eval_kw = dict(max_views=eval_views, full=True)
    # The untrained field's point is the bounded evaluation: marching every pixel of a fog to the far bound
    # without the sample cap took minutes per view on a real capture, for a figure nobody reads.
    curve = [{"seconds": 0.0, "step": 0, "psnr": trainer.evaluate(max_views=eval_views)["psnr"], "bounded": True}]
    if progress is not None:
        progress(curve[0])
    step_seconds: list[float] = []
    with_ssim = {float(t) for t in report_at}
    for target in eval_times(seconds, evals, report_at, minute_curve):
        trainer.train(seconds=target, callback=lambda info: step_seconds.append(info["seconds"]))
        # every pixel at the report times; the points between them (the curve, the first minute) take the bounded
        # evaluation, so a real capture's curve does not cost more than its training (a full one of 7 fox views
        # marches ~100M samples)
        report = target in with_ssim or not bounded_curve
        ev = trainer.evaluate(**(eval_kw if report else dict(max_views=eval_views)), with_ssim=target in with_ssim)
        point = {"target": target, "seconds": trainer.train_seconds, "step": trainer.step_count, "psnr": ev["psnr"]}
        if not report:
            point["bounded"] = True
        if "ssim" in ev:
            point["ssim"] = ev["ssim"]
        curve.append(point)
        if progress is not None:
            progress(curve[-1])
    final_ev = trainer.evaluate(with_ssim=True, full=True)
    steps, secs = trainer.step_count, trainer.train_seconds
    figures = render_figures(trainer)
    bd = breakdown(trainer, profile_steps)
    t25 = time_to(curve, TARGET_PSNR)
    result = {
        "scene": {"path": str(scene_path), "name": Path(scene_path).name, "format": scene.format,
                  "kind": scene.kind, "kind_reason": scene.extra.get("kind_reason"),
                  "train_views": len(scene.train), "test_views": len(scene.split(trainer.eval_split())),
                  "size": list(scene.train.images[0].shape[:2])},
        "evaluation": evaluation_protocol(scene, trainer, eval_views, bounded_curve),
        "device": describe(trainer.device),
        "train_config": {"rays_per_batch": cfg.rays_per_batch, "lr": cfg.lr, "schedule": cfg.schedule,
                         "lambda_distortion": trainer.cfg.lambda_distortion, "seconds": seconds},
        "trains": ("colour alone (as nerfacto and instant-ngp)" if teachers is None else
                   {"as": "the train command: colour, teacher features and depth priors (paper Eq. s1)",
                    **teachers["what"], "feature_dim": int(getattr(trainer.field_cfg, "feature_dim", 0))}),
        "curve": curve,
        "at": at_times(curve, report_at),
        "minute_curve": [p for p in curve if p.get("target") in {float(t) for t in MINUTE_CURVE}],
        "final": {"psnr": final_ev["psnr"], "ssim": final_ev["ssim"], "steps": steps, "seconds": secs,
                  "views": final_ev["views"]},
        "steps_per_s": steps / max(secs, 1e-9),
        "fog": fog_figures(step_seconds),
        "seconds_to_25_4": t25,
        "peak_rss_mb": _peak_rss_mb(),
        **figures,
        "breakdown": bd,
        "reference": {"nerfacto": NERFACTO},
        "ratios_to_reference_measured_elsewhere": {
            "time_to_25_4_speedup_vs_nerfacto": None if t25 is None else NERFACTO["seconds_to_25_4"] / t25,
            "render_speedup_vs_nerfacto": NERFACTO["render_s_128"] / (figures["render_ms_128"] / 1000.0),
            "peak_rss_vs_nerfacto": _peak_rss_mb() / (NERFACTO["peak_rss_gb"] * 1024),
        },
    }
    if trainer.device.type == "cuda":
        result["peak_gpu_mb"] = torch.cuda.max_memory_allocated(trainer.device) / 2 ** 20
    return result
