"""nerfstudio's nerfacto on the same capture, views and CPU as `bench recon`, for issue 32's side-by-side table.

nerfstudio lives in its own virtual environment (it pins other torch and numpy versions than this project). The
capture is loaded by this project's loader (`load_scene`, the same held-out views, undistortion and image size as
`bench recon`) and written as a nerfstudio dataset: pinhole PNGs and a transforms.json whose split lists name the
held-out views, so both methods train on exactly the same pixels. `ns-train nerfacto` then runs for a wall-clock
budget, reduced for CPU, saving a checkpoint every few steps; `ns-eval` scores the checkpoint saved last before
each report time (PSNR, SSIM; nerfacto evaluates with the mean appearance embedding).
"""
from __future__ import annotations

import json
import re
import shutil
import subprocess
import time
from pathlib import Path

import numpy as np

# CPU reductions of nerfacto (the defaults are sized for a GPU): rays per batch, evaluation chunk, torch hash grid
CPU_OPTIONS = ("--machine.device-type", "cpu", "--machine.num-devices", "1",
               "--pipeline.datamanager.train-num-rays-per-batch", "1024",
               "--pipeline.datamanager.eval-num-rays-per-batch", "1024",
               "--pipeline.model.eval-num-rays-per-chunk", "4096",
               "--pipeline.model.implementation", "torch",
               "--vis", "tensorboard")


# nerfacto builds LPIPS (torchmetrics, AlexNet weights fetched from the internet at model construction); with no
# internet that stops ns-train and ns-eval before the first step. PSNR and SSIM need no LPIPS: run nerfstudio's
# entry points with LPIPS replaced by a stub that returns NaN. torch >= 2.6 loads only plain tensors by default, and
# nerfstudio's checkpoints hold numpy scalars: ns-eval loads them with weights_only=False (our own run's files).
NO_LPIPS = (
    "import importlib, sys, torch, torchmetrics.image.lpip as m\n"
    "class NoLPIPS(torch.nn.Module):\n"
    "    def __init__(self, *a, **k):\n"
    "        super().__init__()\n"
    "    def forward(self, a, b):\n"
    "        return torch.tensor(float('nan'))\n"
    "m.LearnedPerceptualImagePatchSimilarity = NoLPIPS\n"
    "_load = torch.load\n"
    "def load(*a, **k):\n"
    "    k.setdefault('weights_only', False)\n"
    "    return _load(*a, **k)\n"
    "torch.load = load\n"
    "mod, fn = sys.argv.pop(1).split(':')\n"
    "sys.argv[0] = mod\n"
    "getattr(importlib.import_module(mod), fn)()\n")


def ns_command(ns_bin: Path, entry: str) -> list[str]:
    """The command that runs nerfstudio's `entry` (module:function) from its venv, without LPIPS."""
    return [str(ns_bin / "python"), "-c", NO_LPIPS, entry]


def export_scene(scene, out: Path, eval_views: int | None = None) -> dict:
    """Write a loaded `Scene`'s train and test views as a nerfstudio dataset in `out` (PNG images as loaded,
    pinhole intrinsics, OpenGL camera-to-world poses in world units, explicit split lists); returns the JSON.
    `eval_views` keeps only the first N test views, the ones `bench recon --eval-views N` scores."""
    import cv2

    (out / "images").mkdir(parents=True, exist_ok=True)
    frames, lists = [], {"train": [], "test": []}
    for split in ("train", "test"):
        if split not in scene.splits:
            continue
        data = scene.splits[split]
        cams = data.cameras
        images = data.images if split == "train" or eval_views is None else data.images[:eval_views]
        for i, img in enumerate(images):
            name = f"images/{split}_{i:04d}.png"
            px = np.asarray(img)  # RGBA stays RGBA: nerfacto then blends it on its background colour, as we do
            cv2.imwrite(str(out / name), cv2.cvtColor(px, cv2.COLOR_RGBA2BGRA if px.shape[-1] == 4 else cv2.COLOR_RGB2BGR))
            frames.append({"file_path": name, "transform_matrix": cams.c2w[i].double().numpy().tolist(),
                           "fl_x": float(cams.fx[i]), "fl_y": float(cams.fy[i]), "cx": float(cams.cx[i]),
                           "cy": float(cams.cy[i]), "w": int(cams.width[i]), "h": int(cams.height[i])})
            lists[split].append(name)
    meta = {"camera_model": "OPENCV", "frames": frames, "train_filenames": lists["train"],
            "val_filenames": lists["test"], "test_filenames": lists["test"]}
    (out / "transforms.json").write_text(json.dumps(meta))
    return meta


def train_command(ns_bin: Path, data: Path, out: Path, steps_per_save: int, alpha: bool = False) -> list[str]:
    """The `ns-train nerfacto` command line, reduced for CPU, keeping every checkpoint. Images with alpha (a
    masked capture) are blended on white in training and evaluation, nerfstudio's setting for cut-out objects
    and the background this project evaluates them on."""
    white = ("--pipeline.model.background-color", "white") if alpha else ()
    return [*ns_command(ns_bin, "nerfstudio.scripts.train:entrypoint"), "nerfacto", "--output-dir", str(out), "--experiment-name", "bench",
            "--timestamp", "run", "--max-num-iterations", "1000000", "--steps-per-save", str(steps_per_save),
            "--save-only-latest-checkpoint", "False", "--steps-per-eval-image", "1000000",
            "--steps-per-eval-batch", "1000000", "--steps-per-eval-all-images", "1000000", *CPU_OPTIONS, *white,
            "nerfstudio-data", "--data", str(data), "--downscale-factor", "1"]


def run_for(cmd: list[str], seconds: float, log: Path) -> dict:
    """Run `cmd` for `seconds` of wall clock (then interrupt it) with its output in `log`; start time and exit."""
    with open(log, "w") as fh:
        t0 = time.time()
        proc = subprocess.Popen(cmd, stdout=fh, stderr=subprocess.STDOUT)
        try:
            proc.wait(timeout=seconds)
        except subprocess.TimeoutExpired:
            proc.terminate()
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
    return {"started": t0, "returncode": proc.returncode, "wall_s": time.time() - t0}


def checkpoints(run_dir: Path, started: float) -> list[tuple[int, float]]:
    """(step, seconds since ns-train started) of each checkpoint saved, by step."""
    out = []
    for p in (run_dir / "nerfstudio_models").glob("step-*.ckpt"):
        m = re.fullmatch(r"step-(\d+)\.ckpt", p.name)
        if m:
            out.append((int(m.group(1)), p.stat().st_mtime - started))
    return sorted(out)


def evaluate_step(ns_bin: Path, run_dir: Path, step: int, out_json: Path) -> dict:
    """`ns-eval` of the checkpoint at `step` (a copy of the run's config.yml pinned to it): its metrics dict."""
    cfg = (run_dir / "config.yml").read_text()
    pinned = run_dir / f"config-step-{step}.yml"
    pinned.write_text(re.sub(r"(?m)^load_step: .*$", f"load_step: {step}", cfg))
    r = subprocess.run([*ns_command(ns_bin, "nerfstudio.scripts.eval:entrypoint"), "--load-config", str(pinned), "--output-path", str(out_json)],
                       capture_output=True, text=True)
    if r.returncode != 0 or not out_json.is_file():
        return {"error": (r.stderr or r.stdout).strip().splitlines()[-1:] or ["ns-eval failed"]}
    return json.loads(out_json.read_text())["results"]


def measure(scene_path: Path, seconds: float, ns_venv: Path, work: Path, report_at=(60.0, 120.0, 300.0),
            holdout_every: int | None = None, downscale: float = 1.0, steps_per_save: int = 25,
            eval_views: int | None = None) -> dict:
    """nerfacto on `scene_path` for `seconds` of wall clock: PSNR/SSIM of the held-out views at each report
    time (the checkpoint saved last before it), in the shape of `bench recon`'s JSON."""
    from repaint_nerf.core.errors import UserError
    from repaint_nerf.core.scene.loaders.detect import load_scene

    ns_bin = Path(ns_venv).expanduser() / "bin"
    if not (ns_bin / "ns-train").is_file():
        raise UserError(f"no ns-train in {ns_bin}", hint="install nerfstudio into its own venv (docs/ARCHITECTURE.md, "
                                                         "'Real captures'), then give it with --ns-venv")
    scene = load_scene(scene_path, downscale, holdout_every=holdout_every)
    if "test" not in scene.splits:
        raise UserError("this scene has no held-out views to score", hint="give --holdout-every N")
    shutil.rmtree(work, ignore_errors=True)
    data = work / "data"
    meta = export_scene(scene, data, eval_views)
    cmd = train_command(ns_bin, data, work / "out", steps_per_save, alpha=scene.train.has_alpha)
    run = run_for(cmd, seconds, work / "ns-train.log")
    run_dir = work / "out" / "bench" / "nerfacto" / "run"
    ckpts = checkpoints(run_dir, run["started"])
    at: dict = {}
    for t in report_at:
        before = [c for c in ckpts if c[1] <= t]
        if t > seconds or not before:
            at[f"{t:g}"] = None
            continue
        step, secs = before[-1]
        res = evaluate_step(ns_bin, run_dir, step, work / f"eval-{step}.json")
        at[f"{t:g}"] = {"target": t, "seconds": secs, "step": step, "psnr": res.get("psnr"), "ssim": res.get("ssim"),
                        "lpips": res.get("lpips"), **({"error": res["error"]} if "error" in res else {})}
    last = ckpts[-1] if ckpts else None
    return {
        "method": "nerfstudio nerfacto, reduced for CPU (" + " ".join(CPU_OPTIONS) + ")",
        "scene": {"path": str(scene_path), "name": Path(scene_path).name, "format": scene.format,
                  "train_views": len(scene.train), "test_views": len(meta["test_filenames"]),
                  "size": list(scene.train.images[0].shape[:2])},
        "evaluation": {"split": "test", "holdout": scene.extra.get("holdout"),
                       "views": "all" if eval_views is None else f"the first {eval_views}",
                       "images": "this project's loader's images (undistorted, at bench recon's size), written as "
                                 "PNG with split lists, so both methods see the same pixels",
                       "appearance": "nerfacto's mean appearance embedding (use_average_appearance_embedding)",
                       "seconds": "wall clock since ns-train started, its setup included (checkpoint file times)"},
        "train_config": {"seconds": seconds, "steps_per_save": steps_per_save, "command": cmd},
        "run": {"returncode": run["returncode"], "wall_s": run["wall_s"], "checkpoints": len(ckpts),
                "log": str(work / "ns-train.log")},
        "at": at,
        "final": None if last is None else {"step": last[0], "seconds": last[1]},
        "steps_per_s": None if last is None or last[1] <= 0 else last[0] / last[1],
    }
