"""Structure-from-motion measured on rendered photos with known poses (core.sfm.synthetic): each set goes
through the full pipeline (no cache) and recovered poses are compared with the truth after a similarity
alignment. Returns dicts; the `bench sfm` driver (app/bench/sfm.py) prints and writes JSON.
"""
from __future__ import annotations

import time
from pathlib import Path


def bench_one(preset: str, views: int, width: int, height: int, matcher: str, seed: int, tmp: Path) -> dict:
    """Render, run SfM, measure: one row of the benchmark."""
    import numpy as np

    from repaint_nerf.core.sfm.evaluate import pose_errors
    from repaint_nerf.core.sfm.run import run_sfm
    from repaint_nerf.core.sfm.synthetic import render_photos

    root = tmp / f"{preset}_{views}"
    truth = render_photos(preset, root / "photos", views, width, height, seed=seed)
    t0 = time.perf_counter()
    rep = run_sfm(root / "photos", root / "ws", matcher=matcher, force=True)
    total = time.perf_counter() - t0
    from repaint_nerf.core.scene.loaders.colmap import load_colmap

    scene = load_colmap(Path(rep["scene_dir"]))
    originals = rep["names"]
    names = [originals.get(n, n) for s in scene.splits.values() for n in s.names]
    c2w = np.concatenate([s.cameras.c2w.double().numpy() for s in scene.splits.values()])
    err = pose_errors(c2w, truth["c2w"][[truth["names"].index(n) for n in names]])
    return {"views": views, "size": [width, height], "matcher": rep["matcher"], "registered": rep["registered"],
            "unregistered": rep["unregistered"], "points": rep["points"], "seconds": rep["seconds"],
            "seconds_total": round(total, 3), "focal_rel_error": abs(float(scene.train.cameras.fx[0]) / truth["fx"] - 1),
            **err}
