"""bench mask measurements: selection masks from a stage-1 field trained from scratch, against ground truth.

Per scene (a generated preset, or any scene folder with gt/ object masks): teacher features cached in a
workspace, a patch placed automatically inside the object in one training view (the deepest point of its
ground-truth mask, a small square), then mask IoU over all test views: at the automatic threshold
(core.select.autothreshold; this is `final.iou`), at the fixed 0.5, at the best threshold of a sweep,
with and without each geometry part (core.select.geometry: depth edges, seeded growth, holes, the voxel
3D clean-up, creases, the views' vote, border attachment, the photo's edges), against training steps, with and without depth
supervision (sparse/triangulated priors, never the ground-truth depth); the training views' masks (`train_iou`);
patch-to-mask time on a 256x256 feature map and MB of cached features. The geometry runs over the test views
and every training view together, as `select` runs it over the training views (its views carry seeds to each
other and vote: with the patch's view alone beside 4 test views the toys can scored 0.747, with the 24 training
views 0.847).
Returns dicts and picture arrays; the CLI driver is app/bench/mask.py.
"""
from __future__ import annotations

import json
import time
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np
import torch

THRESHOLDS = tuple(float(t) for t in np.round(np.arange(0.2, 0.96, 0.05), 2))
FIXED = 0.5  # the old fixed threshold (the paper's alpha as this project shipped it)


def presets() -> tuple[str, ...]:
    """Every synthetic preset except 'replace' (the demo layout again, with a geometry edit)."""
    from repaint_nerf.core.synth.presets import PRESETS

    return tuple(p for p in PRESETS if p != "replace")


def parts_variants() -> dict:
    """The geometry variants measured: the default (what select saves), all parts, none, and all but one
    (each part's gain)."""
    from repaint_nerf.core.select.geometry import GeometryParts

    from repaint_nerf.core.select.geometry import DEFAULT_PARTS

    full = GeometryParts()
    out = {"default": DEFAULT_PARTS, "all": full, "none": GeometryParts.none()}
    for k in full.names():
        out[f"no_{k}"] = replace(full, **{k: False})
    return out


def make_teacher(spec: str | None):
    """The feature teacher named by --teacher: 'default' (or None) or a model path, through the teachers'
    factory (core.teachers.stage1_targets), so every teacher kind it knows works here."""
    from repaint_nerf.core.teachers.stage1_targets import FeatureModel, make_feature_teacher

    if not spec or spec == "default":
        return make_feature_teacher(FeatureModel())
    return make_feature_teacher(FeatureModel(str(spec)))


@dataclass
class MaskBenchConfig:
    """What one bench mask run measures (the CLI's options)."""

    steps: int = 2000
    evals: int = 5
    rays: int | None = None
    no_depth_run: bool = False
    feature_head: str | None = None
    seed: int = 0
    object: int | None = None
    all_objects: bool = False
    teacher: str | None = None


def summarize(results: dict) -> dict:
    """Across scenes: the worst final IoU (at the automatic threshold), the mean, the worst gap to the best
    threshold, the worst IoU at the fixed 0.5 and without geometry, median patch-to-mask time."""
    finals = {k: r["final"] for k, r in results.items()}
    return {"final": {"iou": min(f["iou"] for f in finals.values()), "min_over_presets": True,
                      "mean_iou": float(np.mean([f["iou"] for f in finals.values()])),
                      "max_auto_gap": max(f["auto_gap"] for f in finals.values()),
                      "min_iou_fixed": min(f["iou_fixed"] for f in finals.values()),
                      "min_iou_no_geometry": min(f["no_geometry"]["iou"] for f in finals.values()),
                      "min_iou_before": min(f["iou_before"] for f in finals.values()),
                      "min_editor_iou": min(f["editor"]["iou"] for f in finals.values()),
                      "min_train_iou": min(f["train_iou"] for f in finals.values())},
            "patch_to_mask_ms": float(np.median([r["patch_to_mask_ms"] for r in results.values()])),
            "feature_mb_per_image": float(np.mean([r["feature_mb_per_image"] for r in results.values()]))}


def _read_masks(root: Path, split: str, names: list[str]) -> list[np.ndarray]:
    from repaint_nerf.core.errors import UserError

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


class Evaluator:
    """Masks of the test views for one patch query on the current field, at any threshold and with any
    geometry parts. The geometry runs over the test views and every training view, as `select` runs it over the
    training views: the patch seeds its own training view, and the training views' masks (what `select` writes
    for the repaint) come out beside the test views' (held out: scored against ground truth the field never saw).
    As in `select`, views larger than `map_side` are shaped on maps of that long side (the patch's own view at its
    size) and their masks come out at the view's size; the editor's way votes on maps of `VOTE_SIDE`, as the
    Engine renders its voters."""

    def __init__(self, field, grid, train_cams, test_cams, train_images=None, test_images=None, render_opts=None,
                 map_side: int | None = None):
        from repaint_nerf.core.select.masks import MAP_SIDE, ViewCache

        side = MAP_SIDE if map_side is None else int(map_side)
        # the views' maps, as `select` caches them (at the sample budget the field was trained with)
        self.train_cache = ViewCache(field, grid, train_cams, render_opts=render_opts, map_side=side)
        self._test_cache = ViewCache(field, grid, test_cams, render_opts=render_opts, map_side=side)
        self.test = [self._test_cache.get(i) for i in range(len(test_cams))]
        self.field, self.grid, self.train_cams, self.test_cams = field, grid, train_cams, test_cams
        self.train_images, self.test_images = train_images, test_images  # the photos, for the image part

    def test_mask_maps(self, view: int):
        """Test view `view`'s maps its mask is shaped on: at most the cache's `map_side` px on the long side."""
        return self._test_cache.mask_maps(view, held=False)

    def train_maps(self, view: int):
        return self.train_cache.get(view)

    def selection(self, patch):
        from repaint_nerf.core.select.selection import Selection

        sel = Selection()
        sel.add_patch(self.train_maps(patch.view).feature, patch)
        return sel

    def auto_threshold(self, patch) -> float:
        """The automatic threshold of the patch, from its own view (as `select` chooses it)."""
        from repaint_nerf.core.select.autothreshold import selection_auto_threshold

        return selection_auto_threshold(self.selection(patch), self.train_cache, patch.view)

    def _with_training_views(self, test_views: list[int], patch_view: int | None = None
                             ) -> tuple[list, object, list | None, list[tuple[int, int]]]:
        """(maps, cameras at the maps' size, photos or None, the views' (H, W)) of test views `test_views` followed
        by every training view: the views `select` shapes masks over, with the held-out ones in front; each on the
        maps `select` shapes it on (training view `patch_view` at its own size)."""
        from repaint_nerf.core.scene.cameras import Cameras
        from repaint_nerf.core.select.masks import map_cameras

        train = [self.train_maps(i) if i == patch_view else self.train_cache.mask_maps(i, held=False)
                 for i in range(len(self.train_cams))]  # another object's patch view is not held at its size
        maps = [self.test_mask_maps(i) for i in test_views] + train
        test_cams = self.test_cams.to("cpu")[torch.tensor(test_views, dtype=torch.long)]
        cams = Cameras.cat([test_cams, self.train_cams.to("cpu")])
        images = None if self.test_images is None or self.train_images is None else \
            [self.test_images[i] for i in test_views] + list(self.train_images)
        return maps, map_cameras(cams, maps), images, cams.sizes()

    def all_masks(self, patch, thresholds, parts) -> tuple[dict, list]:
        """({threshold: (test views' masks, training views' masks)} (numpy bool), test similarity maps)."""
        from repaint_nerf.core.select.autothreshold import patch_pixels
        from repaint_nerf.core.select.masks import patch_seeds, shaped_masks

        sel = self.selection(patch)
        n = len(self.test)
        maps, cams, images, sizes = self._with_training_views(list(range(n)), patch.view)
        sims = [sel.similarity(m.feature) for m in maps]
        view = n + patch.view
        pixels = patch_pixels(tuple(maps[view].depth.shape), patch)
        out = {}
        for t in thresholds:  # as select seeds them (masks.selection_seeds)
            m = shaped_masks(sims, maps, cams, patch_seeds(view, pixels, maps, cams, sims, t), t, parts, images,
                             sizes)
            out[t] = (m[:n], m[n:])
        return out, sims[:n]

    def select_seconds(self, patch, threshold: float, parts) -> float:
        """Seconds `select` (core.select.masks.masks_for_views) takes to shape the training views' masks from the
        patch once their maps are rendered (similarity, geometry, clean-up, photo edges; the cost of a Repaint's masks)."""
        from repaint_nerf.core.select.masks import masks_for_views

        self._with_training_views([], patch.view)  # the maps it reads, rendered before the clock starts
        t0 = time.perf_counter()
        masks_for_views(self.field, self.grid, self.train_cams, self.selection(patch), threshold,
                        cache=self.train_cache, parts=parts,
                        images=None if self.train_images is None else list(self.train_images))
        return time.perf_counter() - t0

    def masks(self, patch, thresholds, parts) -> tuple[dict, list]:
        """({threshold: test masks (numpy bool)}, test similarity maps)."""
        out, sims = self.all_masks(patch, thresholds, parts)
        return {t: v[0] for t, v in out.items()}, sims

    def editor_masks(self, view: int, rect, parts_list: list) -> tuple[list[list[np.ndarray]], float]:
        """The editor's way: a patch `rect` (a Patch) drawn in test view `view` as in a free camera (not a training
        view: its surface points seed the others, Engine.select), masks of the other test views, made with the
        training views as `select` makes them, at the patch's automatic threshold, once per geometry parts of
        `parts_list`. Returns (masks of the other test views per parts, the threshold)."""
        from repaint_nerf.core.engine import VOTE_SIDE
        from repaint_nerf.core.select.geometry import anchor_views
        from repaint_nerf.core.select.masks import map_cameras, selection_seeds, shaped_masks
        from repaint_nerf.core.select.selection import Selection

        m = self.test[view]
        sel = Selection()
        sel.add_patch(m.feature, rect)
        auto = sel.anchor_patch(sel.similarity(m.feature).float().numpy(), rect, m.depth.numpy(), m.opacity.numpy(),
                                self.test_cams.to("cpu")[view], m.edge_depth().numpy())
        voters = anchor_views(sel.anchor_points(), self.train_cams)  # as Engine.refine_threshold, a frame later
        if voters:
            vm = [self.train_cache.mask_maps(i, VOTE_SIDE) for i in voters]
            auto = sel.refine_auto_threshold(
                auto, vm, map_cameras(self.train_cams.to("cpu")[torch.tensor(voters, dtype=torch.long)], vm))
        others = [i for i in range(len(self.test)) if i != view]
        maps, cams, images, sizes = self._with_training_views(others)
        sims = [sel.similarity(v.feature) for v in maps]
        seeds = selection_seeds(sel, maps, cams)  # the anchors only: the rect's view (-1) is none of these
        k = len(others)
        return [shaped_masks(sims, maps, cams, seeds, auto, parts, images, sizes)[:k] for parts in parts_list], auto


def default_parts(ev: Evaluator):
    """What a selection's default geometry gives on this field: the default parts, fitted to its depth (fit_parts)."""
    from repaint_nerf.core.select.geometry import fit_parts

    maps = [ev.test_mask_maps(i) for i in range(len(ev.test))]  # as select fits them, on the maps it shapes on
    return fit_parts(parts_variants()["default"], [m.depth.numpy() for m in maps],
                     [m.opacity.numpy() for m in maps])


def edge_levels(ev: Evaluator) -> dict:
    """The depth-edge level of every view's maps, test and training views as `select` shapes them
    (geometry.edge_level): how many views' depth was rough enough to raise it above DEPTH_EDGE, and by how much."""
    from repaint_nerf.core.select.geometry import DEPTH_EDGE, edge_level

    maps = [ev.test_mask_maps(i) for i in range(len(ev.test))] + \
        [ev.train_cache.mask_maps(i, held=False) for i in range(len(ev.train_cams))]
    levels = [edge_level(m.depth.numpy(), m.opacity.numpy()) for m in maps]
    return {"views": len(levels), "raised": int(sum(v > DEPTH_EDGE for v in levels)),
            "median": float(np.median(levels)) if levels else None, "max": max(levels, default=None)}


def editor_iou(ev: Evaluator, gts: list[np.ndarray]) -> dict:
    """IoU of the editor's way (`Evaluator.editor_masks`) with the patch in the test view where the object is
    seen largest, before (no geometry: the editor had no training-view seed) and with the default parts."""
    from repaint_nerf.core.bench.teacher import place_patch
    from repaint_nerf.core.select.geometry import GeometryParts
    from repaint_nerf.core.select.query import Patch

    view, (y0, y1, x0, x1) = place_patch(gts)
    rect = Patch(-1, x0, y0, x1, y1)
    others = [g for i, g in enumerate(gts) if i != view]
    (masks, plain), auto = ev.editor_masks(view, rect, [default_parts(ev), GeometryParts.none()])
    return {"iou": iou(masks, others), "iou_no_geometry": iou(plain, others), "view": view, "auto_threshold": auto}


def evaluate(ev: Evaluator, patch, gts: list[np.ndarray], train_gts: list[np.ndarray] | None = None) -> dict:
    """The final figures of one field and patch: IoU at the automatic threshold (default geometry parts), at
    the fixed 0.5, at the best of a sweep, without geometry, without each part, and as before this
    change (0.5 and the voxel clean-up only); the seconds `select` takes over the training views; given the training views' ground truth, also the IoU of the
    training views' masks at the automatic threshold (`train_iou`: what `select` writes for the repaint)."""
    from repaint_nerf.core.select.geometry import GeometryParts

    variants = parts_variants()
    variants["default"] = default_parts(ev)
    auto = ev.auto_threshold(patch)
    ts = tuple(sorted(set(THRESHOLDS) | {FIXED, auto}))
    both, _ = ev.all_masks(patch, ts, variants["default"])
    full = {t: v[0] for t, v in both.items()}
    plain, _ = ev.masks(patch, ts, variants["none"])
    by_t = {t: iou(full[t], gts) for t in ts}
    plain_t = {t: iou(plain[t], gts) for t in ts}
    best = max(THRESHOLDS, key=lambda t: by_t[t])
    best_plain = max(THRESHOLDS, key=lambda t: plain_t[t])
    parts = {"default": by_t[auto], "none": plain_t[auto]}
    for name, v in variants.items():
        if name not in parts:
            m, _ = ev.masks(patch, (auto,), v)
            parts[name] = iou(m[auto], gts)
    before, _ = ev.masks(patch, (FIXED,), replace(GeometryParts.none(), cleanup3d=True))
    return {"iou": by_t[auto], "auto_threshold": auto, "iou_fixed": by_t[FIXED], "fixed_threshold": FIXED,
            "best_iou": by_t[best], "best_threshold": best, "auto_gap": max(0.0, by_t[best] - by_t[auto]),
            "iou_by_threshold": {f"{t:.2f}": by_t[t] for t in THRESHOLDS},
            "no_geometry": {"iou": plain_t[auto], "iou_fixed": plain_t[FIXED], "best_iou": plain_t[best_plain],
                            "best_threshold": best_plain,
                            "iou_by_threshold": {f"{t:.2f}": plain_t[t] for t in THRESHOLDS}},
            "parts": parts, "default_parts": variants["default"].names(), "editor": editor_iou(ev, gts),
            "edge_level": edge_levels(ev),
            "iou_before": iou(before[FIXED], gts), "masks": full[auto],
            "select_seconds": ev.select_seconds(patch, auto, variants["default"]), "select_views": len(ev.train_cams),
            "train_iou": None if train_gts is None else iou(both[auto][1], train_gts)}


def bench_scene(root: Path, ws_dir: Path, cfg: MaskBenchConfig, device, log=None) -> tuple[dict, np.ndarray]:
    """Train with (and unless cfg.no_depth_run, without) depth priors, evaluating the masks along the way;
    returns (figures, montage row). `log(str)` hears progress."""
    from repaint_nerf.core.bench.teacher import place_patch
    from repaint_nerf.core.scene.loaders.detect import load_scene
    from repaint_nerf.core.select.query import Patch
    from repaint_nerf.core.teachers.cache import build_feature_store
    from repaint_nerf.core.teachers.depth_sparse import depth_for_scene
    from repaint_nerf.core.workspace.workspace import Workspace

    log = log or (lambda _msg: None)
    scene = load_scene(root)
    meta = json.loads((root / "gt" / "objects.json").read_text())
    obj = int(cfg.object if cfg.object is not None else meta["edited_object_id"])
    train_gt = _read_masks(root, "train", scene.train.names)
    test_split = "test" if "test" in scene.splits else "train"
    test_gt = _read_masks(root, test_split, scene.split(test_split).names)
    objects = [int(o["id"]) for o in meta["objects"]] if cfg.all_objects else [obj]
    patches = {}
    for o in objects:
        view, (y0, y1, x0, x1) = place_patch([m == o for m in train_gt])
        patches[o] = Patch(view, x0, y0, x1, y1)
    ws = Workspace.create(ws_dir)
    teacher = make_teacher(cfg.teacher)
    t0 = time.perf_counter()
    store = build_feature_store(scene.train.images, teacher, ws.teachers_dir)
    teacher_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    depth = depth_for_scene(scene)
    depth_s = time.perf_counter() - t0
    evals = sorted({int(round(s)) for s in np.geomspace(max(1, cfg.steps / 2 ** (cfg.evals - 1)), cfg.steps,
                                                         cfg.evals)})
    gts = [g == obj for g in test_gt]
    runs = {"depth": _train_run(scene, store, depth, cfg, device, evals, patches[obj], gts, log)}
    if not cfg.no_depth_run:
        runs["no_depth"] = _train_run(scene, store, None, cfg, device, evals, patches[obj], gts, log)
    curve = []
    for i, row in enumerate(runs["depth"]["curve"]):
        r = dict(row)
        if "no_depth" in runs:
            nd = runs["no_depth"]["curve"][i]
            r.update(iou_no_depth=nd["iou"], iou_no_depth_no_geometry=nd["iou_no_geometry"],
                     seconds_no_depth=nd["seconds"])
        curve.append(r)
    ev, trainer = runs["depth"]["evaluator"], runs["depth"]["trainer"]
    final = evaluate(ev, patches[obj], gts, [g == obj for g in train_gt])
    masks = final.pop("masks")
    final["psnr"] = runs["depth"]["psnr"]
    if "no_depth" in runs:
        final.update(iou_no_depth=curve[-1]["iou_no_depth"], psnr_no_depth=runs["no_depth"]["psnr"])
    if cfg.all_objects:
        from repaint_nerf.core.select.geometry import GeometryParts

        final["objects"] = {}
        for o in objects:
            g = [t == o for t in test_gt]
            auto = ev.auto_threshold(patches[o])
            m3, _ = ev.all_masks(patches[o], (auto,), default_parts(ev))
            m2, _ = ev.masks(patches[o], (auto,), GeometryParts.none())
            final["objects"][str(o)] = {"iou": iou(m3[auto][0], g), "iou_no_geometry": iou(m2[auto], g),
                                        "train_iou": iou(m3[auto][1], [t == o for t in train_gt]),
                                        "auto_threshold": auto}
    _, sims = ev.masks(patches[obj], (), parts_variants()["none"])
    ptm = patch_to_mask_ms(trainer, patches[obj])
    res = {"object_id": obj, "patch": patches[obj].to_dict(), "curve": curve, "final": final,
           "patch_to_mask_ms": ptm["total"], "auto_threshold_ms": ptm["auto"],
           "feature_mb_per_image": store.mb_per_image(),
           "feature_mb_per_image_504x378": store.mb_per_image() * (504 * 378) / float(np.mean(
               [h * w for h, w in store.sizes])),
           "feature_dims": store.dims, "teacher": getattr(teacher, "name", type(teacher).__name__),
           "teacher_seconds": teacher_s, "depth_prior_seconds": depth_s,
           "depth_points": depth.count(), "seconds_per_step": runs["depth"]["seconds_per_step"],
           "field_config": runs["depth"]["field_config"], "image_size": list(scene.train.images[0].shape[:2]),
           "train_views": len(scene.train), "test_views": len(test_gt)}
    row = montage_row(trainer, ev, sims, masks, gts)
    return res, row


def _train_run(scene, store, depth, cfg, device, evals, patch, gts, log) -> dict:
    import dataclasses

    from repaint_nerf.core.render.renderer import RenderOptions
    from repaint_nerf.core.train.stage1 import Stage1Trainer, TrainConfig

    tcfg = TrainConfig(seed=cfg.seed)
    if cfg.rays:
        tcfg.rays_per_batch = cfg.rays
    if depth is None:
        tcfg.lambda_depth = 0.0
    field_cfg = None
    if cfg.feature_head:  # 'separate' (DFF's own grid + MLP) or 'trunk' (a head on the density trunk)
        from repaint_nerf.core.field.field import default_field_config

        size = max(max(im.shape[:2]) for im in scene.train.images)
        field_cfg = default_field_config(device, size, feature_head=cfg.feature_head)
    trainer = Stage1Trainer(scene, None, tcfg, field_cfg=field_cfg, device=device,
                            feature_targets=store.codes, depth_priors=depth)
    trainer.plan(cfg.steps)
    train_cams = scene.field_cameras("train").to(device)
    test_cams = scene.field_cameras("test" if "test" in scene.splits else "train").to(device)
    curve, ev = [], None
    variants = parts_variants()
    for s in evals:
        trainer.train(steps=s)
        trainer.field.eval()
        ev = Evaluator(trainer.field, trainer.grid, train_cams, test_cams, scene.train.images,
                       scene.split("test" if "test" in scene.splits else "train").images,
                       RenderOptions(max_samples=trainer.march_samples))
        auto = ev.auto_threshold(patch)
        m3, _ = ev.masks(patch, (auto,), default_parts(ev))
        m2, _ = ev.masks(patch, (auto,), variants["none"])
        trainer.field.train()
        curve.append({"step": trainer.step_count, "seconds": trainer.train_seconds, "auto_threshold": auto,
                      "iou": iou(m3[auto], gts), "iou_no_geometry": iou(m2[auto], gts)})
        log(f"  {'depth' if depth is not None else 'no depth'} step {trainer.step_count}: iou {curve[-1]['iou']:.3f} "
            f"at auto {auto:.2f} (no geometry {curve[-1]['iou_no_geometry']:.3f}), {trainer.train_seconds:.0f} s")
    trainer.field.eval()
    return {"curve": curve, "evaluator": ev, "trainer": trainer, "psnr": trainer.evaluate()["psnr"],
            "seconds_per_step": trainer.train_seconds / max(1, trainer.step_count),
            "field_config": dataclasses.asdict(trainer.field_cfg)}


def patch_to_mask_ms(trainer, patch, size: int = 256, repeats: int = 15) -> dict:
    """Median ms from a rendered 256x256 feature map and a patch to a mask on screen as the editor does it (query,
    similarity, automatic threshold, threshold, the patch's surface points): {"total", "auto" (the automatic
    threshold's share)}."""
    from repaint_nerf.core.render.renderer import RenderOptions, render_camera
    from repaint_nerf.core.select.autothreshold import patch_auto_threshold
    from repaint_nerf.core.select.masks import FIRST_SURFACE
    from repaint_nerf.core.select.query import Patch
    from repaint_nerf.core.select.selection import Selection

    cams = trainer.cameras
    scale = size / float(max(int(cams.width[patch.view]), int(cams.height[patch.view])))
    out = render_camera(trainer.field, trainer.grid, cams, patch.view,
                        RenderOptions(outputs=("feature", "depth", "median_depth", "opacity"),
                                      feature_first_surface=FIRST_SURFACE), scale=scale)
    feat, depth, opacity = out["feature"], out["median_depth"].cpu().numpy(), out["opacity"].cpu().numpy()
    expected = out["depth"].cpu().numpy()  # the automatic threshold's edges, as Engine.select reads them
    cam = cams.to("cpu")[patch.view].scaled(scale)
    big = Patch(patch.view, *(int(round(v * scale)) for v in (patch.x0, patch.y0, patch.x1, patch.y1)))
    total, auto = [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        sel = Selection()
        sel.add_patch(feat, big)
        sim = sel.similarity(feat).float().cpu().numpy()  # on the host, as Engine.select has it
        t = sel.anchor_patch(sim, big, depth, opacity, cam, expected)  # what Engine.select runs
        _ = sim > t  # the mask on screen
        total.append(time.perf_counter() - t0)
        t1 = time.perf_counter()  # the automatic threshold's share, timed on its own
        patch_auto_threshold(sim, big, expected, opacity)
        auto.append(time.perf_counter() - t1)
    return {"total": 1000.0 * float(np.median(total)), "auto": 1000.0 * float(np.median(auto))}


def montage_row(trainer, ev, sims, masks, gts, n: int = 3) -> np.ndarray:
    """Render | similarity | mask | ground truth for `n` test views, side by side (RGB uint8)."""
    import cv2

    from repaint_nerf.core.render.renderer import RenderOptions, render_camera

    picks = np.linspace(0, len(gts) - 1, min(n, len(gts))).round().astype(int)
    bg = trainer.eval_background()
    tiles = []
    for i in picks:
        rgb = render_camera(trainer.field, trainer.grid, ev.test_cams, int(i),
                            RenderOptions(outputs=("rgb",), background=bg))["rgb"]
        img = (rgb.clamp(0, 1).cpu().numpy() * 255 + 0.5).astype(np.uint8)
        sim = cv2.applyColorMap((np.clip(sims[i].float().numpy(), 0, 1) * 255).astype(np.uint8),
                                cv2.COLORMAP_VIRIDIS)[..., ::-1]
        if sim.shape[:2] != img.shape[:2]:  # a view larger than the maps its mask was shaped on
            sim = cv2.resize(sim, (img.shape[1], img.shape[0]), interpolation=cv2.INTER_NEAREST)
        m = np.repeat((masks[i] * 255).astype(np.uint8)[..., None], 3, 2)
        g = np.repeat((gts[i] * 255).astype(np.uint8)[..., None], 3, 2)
        sep = np.full((img.shape[0], 2, 3), 128, np.uint8)
        tiles += [img, sim, m, g, sep]
    return np.concatenate(tiles[:-1], 1)
