"""`repaint-nerf bench teacher`: the 2D ceiling of mask quality for the default feature teacher.

Per preset (or a given scene): a patch placed inside the edited object in one training view, the
cosine similarity of every view's teacher features to the patch mean, mask IoU against the
ground-truth object masks across views at the default threshold, the best threshold, the same
after compression (the K-dim codes the field learns), teacher time per image and MB per image.
"""
from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

HELP = "feature-teacher quality: patch-query mask IoU against ground truth, time and storage per image"
PRESETS = ("demo", "similar", "thin", "forward", "room360", "replace")
THRESHOLDS = np.round(np.arange(0.05, 0.96, 0.05), 2)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--preset", action="append", choices=PRESETS, help="synthetic preset (repeatable; default: all)")
    p.add_argument("--scene", default=None, help="a scene folder with gt/ masks (instead of generated presets)")
    p.add_argument("--size", type=int, default=128, help="image size of generated presets")
    p.add_argument("--views", type=int, default=16, help="training views of generated presets")
    p.add_argument("--object", type=int, default=None, help="object id (default: gt/objects.json edited_object_id)")
    p.add_argument("--json", default="bench_teacher.json", help="output JSON path")
    p.add_argument("--png", default=None, help="output PNG of similarity maps (default: beside the JSON)")


def run(args: argparse.Namespace) -> int:
    from core.errors import UserError

    out = Path(args.json)
    png = Path(args.png) if args.png else out.with_suffix(".png")
    results, rows = {}, []
    with tempfile.TemporaryDirectory(prefix="bench_teacher_") as tmp:
        if args.scene:
            if not (Path(args.scene) / "gt" / "objects.json").is_file():
                raise UserError("scene has no gt/objects.json (ground-truth masks are needed)", args.scene,
                                "use a scene written by `repaint-nerf make-scene`")
            items = [(Path(args.scene).name, Path(args.scene))]
        else:
            from core.synth.generate import make_scene

            items = [(p, make_scene(p, Path(tmp) / p, size=args.size, views=args.views, seed=0, test_views=1))
                     for p in (args.preset or PRESETS)]
        for name, root in items:
            res, row = evaluate_scene(root, Path(tmp) / f"cache_{name}", args.object)
            results[name] = res
            rows.append(row)
            print(f"{name:9s} iou@{res['threshold']:.2f}={res['iou']:.3f} best={res['best_iou']:.3f}"
                  f"@{res['best_threshold']:.2f} compressed={res['iou_compressed']:.3f} "
                  f"{res['ms_per_image']:.0f} ms/img {res['mb_per_image_504x378']:.2f} MB/img@504x378")
    from core.device import describe

    summary = {"min_iou": min(r["iou"] for r in results.values()),
               "min_iou_compressed": min(r["iou_compressed"] for r in results.values())}
    doc = {"benchmark": "teacher", "device": describe(), "teacher": "default", "summary": summary,
           "presets": results, "timing_note": "CPU wall-clock on a shared machine: rough"}
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(doc, indent=2) + "\n")
    if rows:
        cv2.imwrite(str(png), np.concatenate([_pad(r, max(x.shape[1] for x in rows)) for r in rows], 0)[..., ::-1])
    print(f"wrote {out} and {png}")
    return 0


def evaluate_scene(root: Path, cache: Path, object_id: int | None = None) -> tuple[dict, np.ndarray]:
    """Teacher quality on one scene folder (train split). Returns (figures, an RGB picture row)."""
    from core.scene.loaders.detect import load_scene
    from core.teachers.cache import build_feature_store
    from core.teachers.feature_default import DEFAULT_THRESHOLD, DefaultFeatureTeacher

    scene = load_scene(root, splits=("train",))
    meta = json.loads((root / "gt" / "objects.json").read_text())
    obj = int(object_id if object_id is not None else meta["edited_object_id"])
    images = scene.train.images
    masks = [cv2.imread(str(root / "gt" / "train" / f"{Path(n).stem}_mask.png"), cv2.IMREAD_UNCHANGED)
             for n in scene.train.names]
    masks = [m if m.ndim == 2 else m[..., 0] for m in masks]
    teacher = DefaultFeatureTeacher()
    teacher(images[0])  # warm-up (random features, SLIC allocation)
    feats, times = [], []
    for im in images:
        t0 = time.perf_counter()
        feats.append(teacher(im))
        times.append(time.perf_counter() - t0)
    view, (y0, y1, x0, x1) = place_patch([m == obj for m in masks])
    q = feats[view][y0:y1, x0:x1].reshape(-1, feats[view].shape[-1]).mean(0)
    sims = [f @ (q / max(np.linalg.norm(q), 1e-8)) for f in feats]
    gts = [m == obj for m in masks]
    ious = {float(t): mask_iou(sims, gts, t) for t in THRESHOLDS}
    best_t = max(ious, key=ious.get)

    store = build_feature_store(images, teacher, cache)
    codes = [store.full(i).numpy() for i in range(len(images))]
    qc = codes[view][y0:y1, x0:x1].reshape(-1, store.dims).mean(0)
    sims_c = [_cos(c, qc) for c in codes]
    big = cv2.resize(teacher_input(images[0]), (504, 378), interpolation=cv2.INTER_LINEAR)
    t0 = time.perf_counter()
    big_store = build_feature_store([big], teacher, cache / "big")
    t_big = time.perf_counter() - t0
    inside = sims[view][gts[view]]
    res = {"object_id": obj, "patch": {"view": view, "x0": x0, "y0": y0, "x1": x1, "y1": y1},
           "threshold": DEFAULT_THRESHOLD, "iou": mask_iou(sims, gts, DEFAULT_THRESHOLD),
           "best_iou": ious[best_t], "best_threshold": best_t,
           "iou_compressed": mask_iou(sims_c, gts, DEFAULT_THRESHOLD),
           "iou_by_threshold": {f"{t:.2f}": v for t, v in ious.items()},
           "sim_inside_mean": float(inside.mean()), "sim_outside_p95": float(np.percentile(
               np.concatenate([s[~g] for s, g in zip(sims, gts)]), 95)),
           "ms_per_image": 1000.0 * float(np.median(times)), "image_size": list(images[0].shape[:2]),
           "seconds_504x378_with_compression": t_big, "dims": store.dims,
           "mb_per_image": store.mb_per_image(), "mb_per_image_504x378": big_store.mb_per_image(),
           "pca_explained": store.codec.explained, "views": len(images)}
    return res, picture_row(images, sims, gts, DEFAULT_THRESHOLD, view, (y0, y1, x0, x1))


def teacher_input(image: np.ndarray) -> np.ndarray:
    from core.teachers.base import check_image

    return check_image(image)


def place_patch(masks: list[np.ndarray], frac: float = 1 / 24) -> tuple[int, tuple[int, int, int, int]]:
    """A square patch deep inside the object: the view and pixel where the mask's distance transform peaks."""
    best = (-1.0, 0, 0, 0)
    for i, m in enumerate(masks):
        if not m.any():
            continue
        dist = cv2.distanceTransform(np.pad(m.astype(np.uint8), 1), cv2.DIST_L2, 5)[1:-1, 1:-1]
        y, x = np.unravel_index(int(np.argmax(dist)), dist.shape)
        if dist[y, x] > best[0]:
            best = (float(dist[y, x]), i, int(y), int(x))
    d, i, y, x = best
    if d < 0:
        from core.errors import UserError

        raise UserError("the object is not visible in any training view", hint="choose another --object")
    half = int(max(1, min(round(frac * masks[i].shape[0]), d / 1.5)))
    return i, (y - half, y + half + 1, x - half, x + half + 1)


def mask_iou(sims: list[np.ndarray], gts: list[np.ndarray], threshold: float) -> float:
    """Intersection over union summed over all views of (sim > threshold) against the ground truth."""
    inter = sum(int(np.sum((s > threshold) & g)) for s, g in zip(sims, gts))
    union = sum(int(np.sum((s > threshold) | g)) for s, g in zip(sims, gts))
    return inter / union if union else 1.0


def _cos(f: np.ndarray, q: np.ndarray) -> np.ndarray:
    qn = q / max(float(np.linalg.norm(q)), 1e-8)
    return (f @ qn) / np.maximum(np.linalg.norm(f, axis=-1), 1e-8)


def picture_row(images, sims, gts, threshold, view, box, n: int = 4) -> np.ndarray:
    """Image | similarity | mask (green = hit, red = miss, blue = false) for a few views, RGB uint8."""
    picks = [view] + [i for i in np.linspace(0, len(images) - 1, n).round().astype(int) if i != view][:n - 1]
    tiles = []
    for i in picks:
        img = teacher_input(images[i]).copy()
        if i == view:
            y0, y1, x0, x1 = box
            cv2.rectangle(img, (x0, y0), (x1 - 1, y1 - 1), (255, 255, 0), 1)
        sim = cv2.applyColorMap((np.clip(sims[i], 0, 1) * 255).astype(np.uint8), cv2.COLORMAP_VIRIDIS)[..., ::-1]
        m = sims[i] > threshold
        err = np.zeros_like(img)
        err[m & gts[i]] = (40, 200, 40)
        err[~m & gts[i]] = (220, 40, 40)
        err[m & ~gts[i]] = (40, 80, 230)
        tiles += [img, sim, err]
    return np.concatenate(tiles, 1)


def _pad(row: np.ndarray, width: int) -> np.ndarray:
    return np.pad(row, ((0, 0), (0, width - row.shape[1]), (0, 0)))
