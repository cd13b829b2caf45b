"""`repaint-nerf bench mask`: selection masks from a stage-1 field trained from scratch, against ground truth.

Per scene (a generated preset, or any scene folder with gt/ object masks): teacher features cached in a
workspace, a patch placed automatically inside the object in one training view (the deepest point of its
ground-truth mask, a small square), then mask IoU over all test views against training steps, with and
without depth supervision (sparse/triangulated priors from the teacher package, never the ground-truth
depth), with and without the 3D clean-up, a threshold sweep at the end, patch-to-mask time on a 256x256
feature map, MB of cached features per image, and a montage (render | similarity | mask | ground truth).
"""
from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import torch

HELP = "mask IoU of patch selections against ground truth vs training steps, with/without depth and 3D clean-up"
THRESHOLDS = tuple(float(t) for t in np.round(np.arange(0.2, 0.91, 0.05), 2))


def add_arguments(p: argparse.ArgumentParser) -> None:
    from core.bench.teacher import PRESETS

    src = p.add_mutually_exclusive_group()
    src.add_argument("--scene", default=None, help="a scene folder with gt/objects.json and gt/ masks")
    src.add_argument("--preset", default="demo", choices=(*PRESETS, "all"), help="synthetic preset (default demo)")
    obj = p.add_mutually_exclusive_group()
    obj.add_argument("--object", type=int, default=None, help="object id (default: edited_object_id)")
    obj.add_argument("--all-objects", action="store_true", help="also report every object's final IoU")
    p.add_argument("--steps", type=int, default=2000, help="training steps (the paper's ablation: 2000)")
    p.add_argument("--evals", type=int, default=5, help="points on the IoU curve (geometric in steps)")
    p.add_argument("--size", type=int, default=128,
                   help="image size of generated presets (default 128: at 64 the thin pole is ~1 px wide)")
    p.add_argument("--views", type=int, default=24, help="training views of generated presets")
    p.add_argument("--test-views", type=int, default=8, help="test views of generated presets")
    p.add_argument("--rays", type=int, default=None, help="rays per batch (default: the trainer's)")
    p.add_argument("--no-depth-run", action="store_true", help="skip the run without depth supervision")
    p.add_argument("--feature-head", default=None, choices=("separate", "trunk"),
                   help="feature head design (default: the field's FieldConfig default)")
    p.add_argument("--threshold", type=float, default=None, help="threshold (default: DEFAULT_THRESHOLD)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", default="bench_mask.json", help="output JSON path")
    p.add_argument("--png", default=None, help="montage PNG (default: beside the JSON)")
    p.add_argument("--device", default=None, help="cpu, cuda, cuda:1")


def run(args: argparse.Namespace) -> int:
    from core.bench.teacher import PRESETS
    from core.device import describe, get_device
    from core.errors import UserError
    from core.select.masks import DEFAULT_THRESHOLD, check_threshold

    if args.steps < 1 or args.evals < 1:
        raise UserError("--steps and --evals must be at least 1")
    threshold = check_threshold(DEFAULT_THRESHOLD if args.threshold is None else args.threshold)
    device = get_device(args.device)
    out = Path(args.json)
    png = Path(args.png) if args.png else out.with_suffix(".png")
    results, rows = {}, []
    with tempfile.TemporaryDirectory(prefix="bench_mask_") as tmp:
        if args.scene:
            root = Path(args.scene)
            if not (root / "gt" / "objects.json").is_file():
                raise UserError("scene has no gt/objects.json (ground-truth masks are needed)", root,
                                "use a scene written by `repaint-nerf make-scene`")
            items = [(root.name, root)]
        else:
            from core.synth.generate import make_scene

            names = PRESETS if args.preset == "all" else (args.preset,)
            items = [(n, make_scene(n, Path(tmp) / n, size=args.size, views=args.views, seed=args.seed,
                                    test_views=args.test_views)) for n in names]
        for name, root in items:
            res, row = bench_scene(root, Path(tmp) / f"ws_{name}", args, threshold, device)
            results[name] = res
            rows.append(row)
            f = res["final"]
            print(f"{name:9s} iou={f['iou']:.3f} (2D only {f['iou_no_cleanup']:.3f}, no depth "
                  f"{f.get('iou_no_depth', float('nan')):.3f}) best {f['best_iou']:.3f}@{f['best_threshold']:.2f} "
                  f"at step {res['curve'][-1]['step']} ({res['curve'][-1]['seconds']:.0f} s train), "
                  f"{res['patch_to_mask_ms']:.1f} ms patch->mask, {res['feature_mb_per_image']:.3f} MB/img")
    first = next(iter(results.values()))
    doc: dict = {"benchmark": "mask", "device": describe(device), "teacher": "default", "threshold": threshold,
                 "steps": args.steps, "timing_note": "CPU wall-clock on a shared machine: rough"}
    if len(results) == 1:
        doc.update({k: first[k] for k in ("curve", "final", "patch_to_mask_ms", "feature_mb_per_image")})
        doc["scene"] = first
    else:
        doc.update(summarize(results, threshold))
        doc["presets"] = results
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(doc, indent=2) + "\n")
    if rows:
        width = max(r.shape[1] for r in rows)
        img = np.concatenate([np.pad(r, ((0, 0), (0, width - r.shape[1]), (0, 0))) for r in rows], 0)
        png.parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(png), img[..., ::-1])
    print(f"wrote {out} and {png}")
    return 0


def summarize(results: dict, threshold: float) -> dict:
    """Across presets: the mean curve, the worst final IoU, and the threshold that maximises the worst IoU."""
    finals = {k: r["final"] for k, r in results.items()}
    sweep = {t: min(f["iou_by_threshold"][f"{t:.2f}"] for f in finals.values()) for t in THRESHOLDS}
    best_t = max(sweep, key=sweep.get)
    curves = [r["curve"] for r in results.values()]
    n = min(len(c) for c in curves)
    curve = [{"step": curves[0][i]["step"],
              **{k: float(np.mean([c[i][k] for c in curves if k in c[i]])) for k in curves[0][i] if k != "step"}}
             for i in range(n)]
    return {"curve": curve,
            "final": {"iou": min(f["iou"] for f in finals.values()), "threshold": threshold,
                      "min_over_presets": True, "mean_iou": float(np.mean([f["iou"] for f in finals.values()])),
                      "min_iou_no_cleanup": min(f["iou_no_cleanup"] for f in finals.values()),
                      "min_iou_by_threshold": {f"{t:.2f}": v for t, v in sweep.items()},
                      "best_common_threshold": best_t, "min_iou_at_best_common": sweep[best_t]},
            "patch_to_mask_ms": float(np.median([r["patch_to_mask_ms"] for r in results.values()])),
            "feature_mb_per_image": float(np.mean([r["feature_mb_per_image"] for r in results.values()]))}


def _read_masks(root: Path, split: str, names: list[str]) -> list[np.ndarray]:
    from core.errors import UserError

    out = []
    for n in names:
        path = root / "gt" / split / f"{Path(n).stem}_mask.png"
        m = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if m is None:
            raise UserError("ground-truth mask missing", path, "use a scene written by `repaint-nerf make-scene`")
        out.append(m if m.ndim == 2 else m[..., 0])
    return out


def iou(masks: list[np.ndarray], gts: list[np.ndarray]) -> float:
    """Intersection over union summed over all views."""
    inter = sum(int(np.count_nonzero(m & g)) for m, g in zip(masks, gts))
    union = sum(int(np.count_nonzero(m | g)) for m, g in zip(masks, gts))
    return inter / union if union else 1.0


def _cat_cameras(a, b):
    from core.scene.cameras import Cameras

    return Cameras(*(torch.cat([getattr(a, k), getattr(b, k)]) for k in
                     ("c2w", "fx", "fy", "cx", "cy", "width", "height")))


class Evaluator:
    """Masks of the test views for one patch query on the current field, at any threshold, with and
    without the 3D clean-up (the patch's own training view joins the clean-up for its seed points)."""

    def __init__(self, field, grid, train_cams, test_cams):
        from core.select.masks import render_view_maps

        self.test = [render_view_maps(field, grid, test_cams, i) for i in range(len(test_cams))]
        self.field, self.grid, self.train_cams, self.test_cams = field, grid, train_cams, test_cams
        self._train: dict = {}

    def train_maps(self, view: int):
        from core.select.masks import render_view_maps

        if view not in self._train:
            self._train[view] = render_view_maps(self.field, self.grid, self.train_cams, view)
        return self._train[view]

    def masks(self, patch, thresholds, cleanup: bool) -> tuple[dict, list]:
        """{threshold: test masks} and the similarity maps."""
        from core.select.cleanup3d import cleanup_masks
        from core.select.selection import Selection

        pm = self.train_maps(patch.view)
        sel = Selection()
        sel.add_patch(pm.feature, patch)
        sims = [sel.similarity(m.feature) for m in self.test]
        psim = sel.similarity(pm.feature)
        out = {}
        cams = _cat_cameras(self.test_cams.to("cpu"), self.train_cams[patch.view].to("cpu")) if cleanup else None
        n = len(self.test)
        for t in thresholds:
            masks = [s > t for s in sims]
            if cleanup:
                local = type(patch)(n, patch.x0, patch.y0, patch.x1, patch.y1)
                masks = cleanup_masks(masks + [psim > t], [m.depth for m in self.test] + [pm.depth],
                                      [m.opacity for m in self.test] + [pm.opacity], cams, [(n, local)])[:n]
            out[t] = [m.numpy() for m in masks]
        return out, sims


def bench_scene(root: Path, ws_dir: Path, args, threshold: float, device) -> tuple[dict, np.ndarray]:
    """Train with and without depth priors, evaluating the masks along the way; returns (figures, montage row)."""
    from core.bench.teacher import place_patch
    from core.scene.loaders.detect import load_scene
    from core.select.query import Patch
    from core.teachers.cache import build_feature_store
    from core.teachers.depth_sparse import depth_for_scene
    from core.teachers.feature_default import DefaultFeatureTeacher
    from core.workspace.workspace import Workspace

    scene = load_scene(root)
    meta = json.loads((root / "gt" / "objects.json").read_text())
    obj = int(args.object if args.object is not None else meta["edited_object_id"])
    train_gt = _read_masks(root, "train", scene.train.names)
    test_split = "test" if "test" in scene.splits else "train"
    test_gt = _read_masks(root, test_split, scene.split(test_split).names)
    objects = [int(o["id"]) for o in meta["objects"]] if args.all_objects else [obj]
    patches = {}
    for o in objects:
        view, (y0, y1, x0, x1) = place_patch([m == o for m in train_gt])
        patches[o] = Patch(view, x0, y0, x1, y1)
    ws = Workspace.create(ws_dir)
    t0 = time.perf_counter()
    store = build_feature_store(scene.train.images, DefaultFeatureTeacher(), ws.teachers_dir)
    teacher_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    depth = depth_for_scene(scene)
    depth_s = time.perf_counter() - t0
    evals = sorted({int(round(s)) for s in np.geomspace(max(1, args.steps / 2 ** (args.evals - 1)), args.steps,
                                                         args.evals)})
    gts = [g == obj for g in test_gt]
    runs = {"depth": _train_run(scene, store, depth, args, device, evals, patches[obj], gts, threshold)}
    if not args.no_depth_run:
        runs["no_depth"] = _train_run(scene, store, None, args, device, evals, patches[obj], gts, threshold)
    curve = []
    for i, row in enumerate(runs["depth"]["curve"]):
        r = {"step": row["step"], "seconds": row["seconds"], "iou": row["iou"], "iou_no_cleanup": row["iou_2d"]}
        if "no_depth" in runs:
            nd = runs["no_depth"]["curve"][i]
            r.update(iou_no_depth=nd["iou"], iou_no_depth_no_cleanup=nd["iou_2d"], seconds_no_depth=nd["seconds"])
        curve.append(r)
    ev, trainer = runs["depth"]["evaluator"], runs["depth"]["trainer"]
    sweep, sims = ev.masks(patches[obj], THRESHOLDS + (threshold,), cleanup=True)
    sweep_2d, _ = ev.masks(patches[obj], THRESHOLDS, cleanup=False)
    by_t = {f"{t:.2f}": iou(sweep[t], gts) for t in THRESHOLDS}
    best = max(by_t, key=by_t.get)
    final = {"iou": iou(sweep[threshold], gts), "threshold": threshold, "iou_no_cleanup": curve[-1]["iou_no_cleanup"],
             "iou_by_threshold": by_t, "iou_no_cleanup_by_threshold": {f"{t:.2f}": iou(sweep_2d[t], gts)
                                                                      for t in THRESHOLDS},
             "best_iou": by_t[best], "best_threshold": float(best), "psnr": runs["depth"]["psnr"]}
    if "no_depth" in runs:
        final.update(iou_no_depth=curve[-1]["iou_no_depth"], iou_no_depth_no_cleanup=curve[-1]["iou_no_depth_no_cleanup"],
                     psnr_no_depth=runs["no_depth"]["psnr"])
    if args.all_objects:
        final["objects"] = {}
        for o in objects:
            g = [t == o for t in test_gt]
            m3, _ = ev.masks(patches[o], (threshold,), cleanup=True)
            m2, _ = ev.masks(patches[o], (threshold,), cleanup=False)
            final["objects"][str(o)] = {"iou": iou(m3[threshold], g), "iou_no_cleanup": iou(m2[threshold], g)}
    res = {"object_id": obj, "patch": patches[obj].to_dict(), "curve": curve, "final": final,
           "patch_to_mask_ms": patch_to_mask_ms(trainer, patches[obj]),
           "feature_mb_per_image": store.mb_per_image(),
           "feature_mb_per_image_504x378": store.mb_per_image() * (504 * 378) / float(np.mean(
               [h * w for h, w in store.sizes])),
           "feature_dims": store.dims, "teacher_seconds": teacher_s, "depth_prior_seconds": depth_s,
           "depth_points": depth.count(), "seconds_per_step": runs["depth"]["seconds_per_step"],
           "field_config": runs["depth"]["field_config"], "image_size": list(scene.train.images[0].shape[:2]),
           "train_views": len(scene.train), "test_views": len(test_gt)}
    row = montage_row(trainer, ev, sims, sweep[threshold], gts)
    return res, row


def _train_run(scene, store, depth, args, device, evals, patch, gts, threshold) -> dict:
    import dataclasses

    from core.train.stage1 import Stage1Trainer, TrainConfig

    cfg = TrainConfig(seed=args.seed)
    if args.rays:
        cfg.rays_per_batch = args.rays
    if depth is None:
        cfg.lambda_depth = 0.0
    field_cfg = None
    if args.feature_head:  # 'separate' (DFF's own grid + MLP) or 'trunk' (a head on the density trunk)
        from core.field.field import default_field_config

        size = max(max(im.shape[:2]) for im in scene.train.images)
        field_cfg = default_field_config(device, size, feature_head=args.feature_head)
    trainer = Stage1Trainer(scene, None, cfg, field_cfg=field_cfg, device=device,
                            feature_targets=store.codes, depth_priors=depth)
    trainer.plan(args.steps)
    train_cams = scene.field_cameras("train").to(device)
    test_cams = scene.field_cameras("test" if "test" in scene.splits else "train").to(device)
    curve, ev = [], None
    for s in evals:
        trainer.train(steps=s)
        trainer.field.eval()
        ev = Evaluator(trainer.field, trainer.grid, train_cams, test_cams)
        m3, _ = ev.masks(patch, (threshold,), cleanup=True)
        m2, _ = ev.masks(patch, (threshold,), cleanup=False)
        trainer.field.train()
        curve.append({"step": trainer.step_count, "seconds": trainer.train_seconds,
                      "iou": iou(m3[threshold], gts), "iou_2d": iou(m2[threshold], gts)})
        print(f"  {'depth' if depth is not None else 'no depth'} step {trainer.step_count}: "
              f"iou {curve[-1]['iou']:.3f} (2D {curve[-1]['iou_2d']:.3f}), {trainer.train_seconds:.0f} s", flush=True)
    trainer.field.eval()
    return {"curve": curve, "evaluator": ev, "trainer": trainer, "psnr": trainer.evaluate()["psnr"],
            "seconds_per_step": trainer.train_seconds / max(1, trainer.step_count),
            "field_config": dataclasses.asdict(trainer.field_cfg)}


def patch_to_mask_ms(trainer, patch, size: int = 256, repeats: int = 15) -> float:
    """Median ms from a rendered 256x256 feature map and a patch to a mask (query, similarity, threshold)."""
    from core.render.renderer import RenderOptions, render_camera
    from core.select.query import Patch
    from core.select.selection import Selection

    cams = trainer.cameras
    scale = size / float(max(int(cams.width[patch.view]), int(cams.height[patch.view])))
    feat = render_camera(trainer.field, trainer.grid, cams, patch.view,
                         RenderOptions(outputs=("feature",)), scale=scale)["feature"]
    big = Patch(patch.view, *(int(round(v * scale)) for v in (patch.x0, patch.y0, patch.x1, patch.y1)))
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        sel = Selection()
        sel.add_patch(feat, big)
        m = sel.mask(feat)
        _ = bool(m[0, 0])  # the result is on the host
        times.append(time.perf_counter() - t0)
    return 1000.0 * float(np.median(times))


def montage_row(trainer, ev, sims, masks, gts, n: int = 3) -> np.ndarray:
    """Render | similarity | mask | ground truth for `n` test views, side by side (RGB uint8)."""
    from core.render.renderer import RenderOptions, render_camera

    picks = np.linspace(0, len(gts) - 1, min(n, len(gts))).round().astype(int)
    bg = trainer.eval_background()
    tiles = []
    for i in picks:
        rgb = render_camera(trainer.field, trainer.grid, ev.test_cams, int(i),
                            RenderOptions(outputs=("rgb",), background=bg))["rgb"]
        img = (rgb.clamp(0, 1).cpu().numpy() * 255 + 0.5).astype(np.uint8)
        sim = cv2.applyColorMap((np.clip(sims[i].numpy(), 0, 1) * 255).astype(np.uint8),
                                cv2.COLORMAP_VIRIDIS)[..., ::-1]
        m = np.repeat((masks[i] * 255).astype(np.uint8)[..., None], 3, 2)
        g = np.repeat((gts[i] * 255).astype(np.uint8)[..., None], 3, 2)
        sep = np.full((img.shape[0], 2, 3), 128, np.uint8)
        tiles += [img, sim, m, g, sep]
    return np.concatenate(tiles[:-1], 1)
