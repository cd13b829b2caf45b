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
    add_sharpness_argument(p)
    p.add_argument("--json", action="store_true", help="print the description as JSON")


def add_sharpness_argument(p: argparse.ArgumentParser) -> None:
    """--sharpness-discard, for every command that opens a scene (instant-ngp's sharpness_discard_threshold)."""
    p.add_argument("--sharpness-discard", type=float, default=None, metavar="F",
                   help="transforms.json scenes: discard frames whose 'sharpness' is below F times the mean of the "
                        "3 frames on each side, as instant-ngp's sharpness_discard_threshold does (default: the "
                        "file's own threshold, else 0 = keep all; e.g. 0.8)")


def run(args: argparse.Namespace) -> int:
    import json

    from repaint_nerf.core.scene.loaders.detect import load_scene
    from repaint_nerf.core.scene.loaders.summary import format_summary, scene_summary

    info = scene_summary(load_scene(args.path, downscale=args.downscale, kind=args.kind,
                                         sharpness_discard=args.sharpness_discard))
    print(json.dumps(info, indent=2) if args.json else format_summary(info))
    return 0
