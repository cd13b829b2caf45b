"""`repaint-nerf bench mask`: the CLI driver of core/bench/mask.py (options, printing, JSON and montage PNG).

Per scene: mask IoU at the automatic threshold (`final.iou`), at the fixed 0.5, at the best threshold and
the automatic threshold's value; with and without each geometry part; `--teacher` picks the teacher.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import tempfile
from pathlib import Path

import cv2
import numpy as np

HELP = ("mask IoU of patch selections against ground truth: automatic vs fixed vs best threshold, each "
        "geometry part, vs training steps")


def add_arguments(p: argparse.ArgumentParser) -> None:
    from repaint_nerf.core.bench.mask import presets

    src = p.add_mutually_exclusive_group()
    src.add_argument("--scene", default=None, help="a scene folder with gt/objects.json and gt/ masks")
    src.add_argument("--preset", default="demo", choices=(*presets(), "all"), help="synthetic preset (default demo)")
    obj = p.add_mutually_exclusive_group()
    obj.add_argument("--object", type=int, default=None, help="object id (default: edited_object_id)")
    obj.add_argument("--all-objects", action="store_true", help="also report every object's final IoU")
    p.add_argument("--teacher", default="default",
                   help="feature teacher: 'default' (weight-free) or a model path the teacher factory loads")
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
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--seeds", default=None, metavar="S0,S1,...",
                   help="run each scene once per seed (the scene and the training both follow it) and report the mean "
                        "and the worst: one field's IoU on a cluttered preset varies by 0.2 from seed to seed")
    p.add_argument("--json", default="bench_mask.json", help="output JSON path")
    p.add_argument("--png", default=None, help="montage PNG (default: beside the JSON)")
    p.add_argument("--device", default=None, help="cpu, cuda, cuda:1")


def run(args: argparse.Namespace) -> int:
    from repaint_nerf.core.bench.mask import MaskBenchConfig, bench_scene, presets, summarize
    from repaint_nerf.core.device import describe, get_device
    from repaint_nerf.core.errors import UserError

    if args.steps < 1 or args.evals < 1:
        raise UserError("--steps and --evals must be at least 1")
    cfg = MaskBenchConfig(steps=args.steps, evals=args.evals, rays=args.rays, no_depth_run=args.no_depth_run,
                          feature_head=args.feature_head, seed=args.seed, object=args.object,
                          all_objects=args.all_objects, teacher=args.teacher)
    device = get_device(args.device)
    seeds = _seeds(args)
    out = Path(args.json)
    png = Path(args.png) if args.png else out.with_suffix(".png")
    results, rows = {}, []
    with tempfile.TemporaryDirectory(prefix="bench_mask_") as tmp:
        if args.scene:
            root = Path(args.scene)
            if not (root / "gt" / "objects.json").is_file():
                raise UserError("scene has no gt/objects.json (ground-truth masks are needed)", root,
                                "use a scene written by `repaint-nerf make-scene`")
            items = [(root.name, seed, lambda s, r=root: r) for seed in seeds]
        else:
            from repaint_nerf.core.synth.generate import make_scene

            names = presets() if args.preset == "all" else (args.preset,)
            items = [(n, seed, lambda s, n=n: make_scene(n, Path(tmp) / f"{n}_{s}", size=args.size, views=args.views,
                                                         seed=s, test_views=args.test_views))
                     for n in names for seed in seeds]
        for name, seed, make in items:
            key = name if len(seeds) == 1 else f"{name} seed {seed}"
            run_cfg = dataclasses.replace(cfg, seed=seed)
            res, row = bench_scene(make(seed), Path(tmp) / f"ws_{name}_{seed}", run_cfg, device,
                                   log=lambda m: print(m, flush=True))
            results[key] = res
            rows.append(row)
            print(line(key, res), flush=True)
    doc: dict = {"benchmark": "mask", "device": describe(device), "teacher": args.teacher, "steps": args.steps,
                 "seeds": seeds, "timing_note": "CPU wall-clock on a shared machine: rough"}
    if len(results) == 1:
        first = next(iter(results.values()))
        doc.update({k: first[k] for k in ("curve", "final", "patch_to_mask_ms", "feature_mb_per_image")})
        doc["scene"] = first
    else:
        doc.update(summarize(results))
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


def _seeds(args: argparse.Namespace) -> list[int]:
    """The seeds to run: --seeds, else --seed."""
    from repaint_nerf.core.errors import UserError

    if args.seeds is None:
        return [int(args.seed)]
    try:
        seeds = [int(s) for s in str(args.seeds).split(",") if s.strip()]
    except ValueError:
        seeds = []
    if not seeds or len(set(seeds)) != len(seeds):
        raise UserError(f"--seeds {args.seeds!r} is not a list of distinct integers", hint="for example --seeds 0,1,2")
    return seeds


def line(name: str, res: dict) -> str:
    """One scene's summary line: auto / fixed / best, no geometry, each part's IoU, timing."""
    f = res["final"]
    parts = " ".join(f"{k}={v:.3f}" for k, v in f["parts"].items())
    train = "" if f.get("train_iou") is None else f" (training views {f['train_iou']:.3f})"
    return (f"{name:9s} iou={f['iou']:.3f} at auto {f['auto_threshold']:.2f}{train} | fixed 0.5 {f['iou_fixed']:.3f} | "
            f"best {f['best_iou']:.3f}@{f['best_threshold']:.2f} | no geometry {f['no_geometry']['iou']:.3f} "
            f"(best {f['no_geometry']['best_iou']:.3f}) | before {f['iou_before']:.3f} | {parts} | "
            f"editor's way {f['editor']['iou']:.3f} (no geometry {f['editor']['iou_no_geometry']:.3f}) | "
            f"edge level raised in {f['edge_level']['raised']} of {f['edge_level']['views']} views | "
            f"step {res['curve'][-1]['step']} ({res['curve'][-1]['seconds']:.0f} s), "
            f"{res['patch_to_mask_ms']:.1f} ms patch->mask ({res['auto_threshold_ms']:.1f} auto), "
            f"{f['select_seconds']:.1f} s select ({f['select_views']} views)")
