"""Feature-teacher quality (measurement; the `bench teacher` driver is app/bench/teacher.py).

Per preset (or a given scene): a patch placed inside the edited object in one training view, the
cosine similarity of every view's teacher features to the patch mean, mask IoU against the
ground-truth object masks across views at the default threshold, the best threshold, the same
after compression (the K-dim codes the field learns), teacher time per image and MB per image.
On a photograph (no ground truth): the mask a patch gives, as the fraction of the image it covers.
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import cv2
import numpy as np

PRESETS = ("demo", "similar", "thin", "forward", "room360", "replace")
THRESHOLDS = np.round(np.arange(0.05, 0.96, 0.05), 2)
# A patch on Grace Hopper's jacket in matplotlib's sample_data/grace_hopper.jpg, as image fractions x0, y0, x1, y1
JACKET_PATCH = (0.12, 0.88, 0.22, 0.96)


def evaluate_scene(root: Path, cache: Path, object_id: int | None = None, teacher=None,
                   threshold: float | None = None) -> tuple[dict, dict]:
    """Quality of `teacher` (default: the built-in one) on one scene folder (train split). Returns (figures,
    maps for a picture: images, sims, gts, view, box, threshold)."""
    from repaint_nerf.core.scene.loaders.detect import load_scene
    from repaint_nerf.core.teachers.cache import build_feature_store
    from repaint_nerf.core.teachers.feature_default import DEFAULT_THRESHOLD, DefaultFeatureTeacher

    threshold = DEFAULT_THRESHOLD if threshold is None else float(threshold)

    scene = load_scene(root, splits=("train",))
    meta = json.loads((root / "gt" / "objects.json").read_text())
    obj = int(object_id if object_id is not None else meta["edited_object_id"])
    images = scene.train.images
    masks = [cv2.imread(str(root / "gt" / "train" / f"{Path(n).stem}_mask.png"), cv2.IMREAD_UNCHANGED)
             for n in scene.train.names]
    masks = [m if m.ndim == 2 else m[..., 0] for m in masks]
    teacher = teacher or DefaultFeatureTeacher()
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
           "teacher": teacher.name, "threshold": threshold, "iou": mask_iou(sims, gts, threshold),
           "best_iou": ious[best_t], "best_threshold": best_t,
           "iou_compressed": mask_iou(sims_c, gts, threshold),
           "iou_by_threshold": {f"{t:.2f}": v for t, v in ious.items()},
           "sim_inside_mean": float(inside.mean()), "sim_outside_p95": float(np.percentile(
               np.concatenate([s[~g] for s, g in zip(sims, gts)]), 95)),
           "ms_per_image": 1000.0 * float(np.median(times)), "image_size": list(images[0].shape[:2]),
           "seconds_504x378_with_compression": t_big, "dims": store.dims,
           "mb_per_image": store.mb_per_image(), "mb_per_image_504x378": big_store.mb_per_image(),
           "pca_explained": store.codec.explained, "views": len(images)}
    return res, {"images": images, "sims": sims, "gts": gts, "view": view, "box": (y0, y1, x0, x1),
                 "threshold": threshold}


def teacher_input(image: np.ndarray) -> np.ndarray:
    from repaint_nerf.core.teachers.base import check_image

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
        from repaint_nerf.core.errors import UserError

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


def patch_box(rect: tuple[float, float, float, float], height: int, width: int) -> tuple[int, int, int, int]:
    """(y0, y1, x0, x1) pixels of a rectangle given as image fractions (x0, y0, x1, y1), at least 1x1."""
    x0, y0, x1, y1 = (float(v) for v in rect)
    px0, py0 = int(np.floor(x0 * width)), int(np.floor(y0 * height))
    return py0, max(py0 + 1, int(np.ceil(y1 * height))), px0, max(px0 + 1, int(np.ceil(x1 * width)))


def evaluate_photo(image: np.ndarray, box: tuple[int, int, int, int], teacher, threshold: float,
                   refine=None) -> tuple[dict, dict]:
    """The mask a patch `box` (y0, y1, x0, x1) gives on one photograph through `teacher`: its area fraction at
    `threshold` and at each of THRESHOLDS, the similarity inside the patch, the teacher's time. `refine`
    (masks -> masks, e.g. SAM) adds the refined mask's area. Returns (figures, maps: image, sim, mask[, refined])."""
    rgb = teacher_input(image)
    teacher(rgb[:32, :32])  # warm-up (lazy allocations)
    t0 = time.perf_counter()
    feat = teacher(rgb)
    seconds = time.perf_counter() - t0
    y0, y1, x0, x1 = box
    q = feat[y0:y1, x0:x1].reshape(-1, feat.shape[-1]).mean(0)
    sim = _cos(feat, q)
    mask = sim > threshold
    res = {"teacher": teacher.name, "dims": int(feat.shape[-1]), "image_size": list(rgb.shape[:2]),
           "patch": {"x0": x0, "y0": y0, "x1": x1, "y1": y1}, "threshold": float(threshold),
           "area_fraction": float(mask.mean()),
           "area_by_threshold": {f"{t:.2f}": float((sim > t).mean()) for t in THRESHOLDS},
           "sim_in_patch_mean": float(sim[y0:y1, x0:x1].mean()), "sim_median": float(np.median(sim)),
           "seconds": seconds}
    maps = {"image": rgb, "sim": sim, "mask": mask, "box": box}
    if refine is not None:
        maps["refined"] = np.asarray(refine([mask])[0], bool)
        res["area_fraction_refined"] = float(maps["refined"].mean())
    return res, maps
