"""`repaint-nerf info PATH`: what a dataset folder holds, as the loader sees it (text or --json)."""
from __future__ import annotations

import argparse

NAME = "info"
HELP = "describe a dataset: format, images per split, intrinsics, bounds and normalisation, points, depth"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("path", help="dataset folder (NeRF-synthetic, nerfstudio, LLFF, COLMAP) or its transforms JSON")
    p.add_argument("--downscale", type=float, default=1.0, help="divide image width and height by F at load")
    p.add_argument("--kind", default=None, choices=("bounded", "forward", "unbounded"),
                   help="scene kind (default: the dataset's, else detected from the camera layout)")
    p.add_argument("--json", action="store_true", help="print the description as JSON")


def run(args: argparse.Namespace) -> int:
    import json

    from repaint_nerf.core.scene.loaders.detect import load_scene
    from repaint_nerf.core.scene.loaders.summary import format_summary, scene_summary

    info = scene_summary(load_scene(args.path, downscale=args.downscale, kind=args.kind))
    print(json.dumps(info, indent=2) if args.json else format_summary(info))
    return 0
