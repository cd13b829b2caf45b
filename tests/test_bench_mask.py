"""bench mask's figures on an analytic field (two look-alike balls): every figure the issue asks for is in range,
and the editor's way (a patch in a view that is not a training view) loses the look-alike only with geometry."""
from __future__ import annotations

import math

import numpy as np

from test_selection import Balls, _ball_gt, _ring_cameras


def _balls(size: int, half: int):
    """The look-alike balls seen by 4 training and 4 test views of `size` px: (field, training cameras, test
    cameras, test and training ground truth of the first ball, a patch of 2 * `half` + 1 px on it in view 0)."""
    from repaint_nerf.core.scene.cameras import Cameras, look_at
    from repaint_nerf.core.select.query import Patch

    centers = [(0.35, 0.0, 0.0), (-0.4, -0.3, 0.0), (-0.2, 0.45, 0.0)]
    field = Balls(centers, 0.22, [[1, 0, 0], [1, 0, 0], [0, 1, 0]])
    train = _ring_cameras(4, size)
    f = 0.5 * size / math.tan(0.45)
    test = Cameras.create(np.stack([look_at((2.6 * math.cos(a), 2.6 * math.sin(a), 1.5), (0, 0, 0))
                                    for a in (1.0, 2.4, 3.9, 5.3)]), f, f, size / 2, size / 2, size, size)
    gts = [_ball_gt(test, i, centers[0], 0.22).numpy() for i in range(4)]
    train_gts = [_ball_gt(train, i, centers[0], 0.22).numpy() for i in range(len(train))]
    ys, xs = np.nonzero(train_gts[0])
    cy, cx = int(np.median(ys)), int(np.median(xs))
    return field, train, test, gts, train_gts, Patch(0, cx - half, cy - half, cx + half + 1, cy + half + 1)


def test_bench_mask_figures_and_the_editors_way():
    from repaint_nerf.app.bench.mask import line
    from repaint_nerf.core.bench.mask import Evaluator, evaluate

    field, train, test, gts, train_gts, patch = _balls(32, 1)
    res = evaluate(Evaluator(field, None, train, test), patch, gts, train_gts)
    for k in ("iou", "iou_fixed", "best_iou", "iou_before"):
        assert 0.0 <= res[k] <= 1.0, k
    assert res["best_iou"] == max(res["iou_by_threshold"].values())
    assert res["iou"] > 0.85 and res["no_geometry"]["iou"] < 0.75  # the voxel clean-up drops the look-alike
    assert res["train_iou"] > 0.85  # the training views' masks, which select writes, hold the one ball too
    ed = res["editor"]
    assert ed["iou"] > 0.85 and ed["iou_no_geometry"] < 0.75 and 0 <= ed["view"] < 4
    text = line("balls", {"final": res, "curve": [{"step": 1, "seconds": 0.0}], "patch_to_mask_ms": 1.0,
                          "auto_threshold_ms": 0.5})
    assert f"editor's way {ed['iou']:.3f}" in text and f"training views {res['train_iou']:.3f}" in text
    assert res["select_seconds"] > 0 and res["select_views"] == len(train) and " s select (" in text
    lv = res["edge_level"]
    assert lv["views"] == len(test) + len(train) and 0 <= lv["raised"] <= lv["views"] and lv["max"] >= lv["median"]
    assert f"edge level raised in {lv['raised']} of {lv['views']} views" in text


def test_bench_mask_seeds_run_each_scene_per_seed_and_report_the_worst(tmp_path):
    """`--seeds 0,1` runs the preset twice, its scene and training each following the seed; the JSON keeps
    both runs and the summary's worst and mean, and the headline says how many runs it summarises."""
    import json

    from repaint_nerf.app.benchdocs.headline import ROWS
    from repaint_nerf.app.cli import main

    out = tmp_path / "m.json"
    assert main(["bench", "mask", "--preset", "demo", "--steps", "2", "--evals", "1", "--size", "24", "--views", "4",
                 "--test-views", "2", "--no-depth-run", "--seeds", "0,1", "--json", str(out)]) == 0
    d = json.loads(out.read_text())
    assert d["seeds"] == [0, 1] and sorted(d["presets"]) == ["demo seed 0", "demo seed 1"]
    ious = [r["final"]["iou"] for r in d["presets"].values()]
    assert d["final"]["iou"] == min(ious) and abs(d["final"]["mean_iou"] - sum(ious) / 2) < 1e-9
    headline = dict((src, fn) for src, _, fn in ROWS)["mask"](d)[0]
    assert "2 runs: 1 preset x 2 seeds" in headline


def test_bench_mask_seeds_must_be_distinct_integers(tmp_path, capsys):
    from repaint_nerf.app.cli import main

    assert main(["bench", "mask", "--seeds", "0,x", "--json", str(tmp_path / "m.json")]) != 0
    assert "--seeds" in capsys.readouterr().err and not (tmp_path / "m.json").exists()


def test_bench_mask_shapes_larger_views_on_the_maps_select_shapes_on():
    """Views larger than the Evaluator's `map_side` are shaped on maps of that side, as `select` shapes them (the
    patch's training view at its own size), and their masks come out at the views' size: the figures then score
    what `select` writes, and the clean-up still drops the look-alike."""
    from repaint_nerf.core.bench.mask import Evaluator, default_parts, evaluate, iou
    from repaint_nerf.core.select.masks import ViewCache, masks_for_views

    field, train, test, gts, train_gts, patch = _balls(128, 2)
    ev = Evaluator(field, None, train, test, map_side=64)
    auto = ev.auto_threshold(patch)
    both, _ = ev.all_masks(patch, (auto,), default_parts(ev))
    test_masks, train_masks = both[auto]
    assert all(m.shape == (128, 128) for m in test_masks + train_masks)
    assert [ev.train_cache.mask_maps(i, held=False).depth.shape[0] for i in range(4)] == [64] * 4
    assert [ev.test_mask_maps(i).depth.shape[0] for i in range(4)] == [64] * 4
    # the ball is ~10 px across on the 64-px maps: its outline moves by up to a map pixel (no photo to snap it to)
    assert iou(test_masks, gts) > 0.85 and iou(train_masks, train_gts) > 0.85
    cache = ViewCache(field, None, train, map_side=64)  # what `select` writes from the same patch
    sel = ev.selection(patch)
    cache.get(0)
    written = masks_for_views(field, None, train, sel, auto, cache=cache, parts=default_parts(ev))
    assert iou(train_masks, written) > 0.99  # shaped on the full-size maps they agree at 0.94
    res = evaluate(ev, patch, gts, train_gts)
    assert res["iou"] > 0.85 and res["no_geometry"]["iou"] < 0.75 and res["editor"]["iou"] > 0.8
