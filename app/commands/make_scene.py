"""`repaint-nerf make-scene`: write a synthetic scene with ground truth (depth, masks, an edited variant)."""
from __future__ import annotations

import argparse
from pathlib import Path

NAME = "make-scene"
HELP = "generate a synthetic NeRF-synthetic scene with ground-truth depth, object masks and an edited variant"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--preset", default="demo", help="scene preset (default: demo; --list names them)")
    p.add_argument("--out", type=Path, default=None, help="output folder (new or empty)")
    p.add_argument("--size", type=int, default=128, help="image width and height in pixels (default 128)")
    p.add_argument("--views", type=int, default=100, help="number of training views (default 100)")
    p.add_argument("--test-views", type=int, default=None, help="number of test views (default views/5)")
    p.add_argument("--seed", type=int, default=0, help="random seed for the cameras (default 0)")
    p.add_argument("--list", action="store_true", help="list the presets and exit")


def run(args: argparse.Namespace) -> int:
    from repaint_nerf.core.errors import UserError
    from repaint_nerf.core.synth.generate import list_presets, make_scene

    if args.list:
        presets = list_presets()
        width = max(map(len, presets))
        for name, desc in presets.items():
            print(f"{name:<{width}}  {desc}")
        return 0
    if args.out is None:
        raise UserError("no output folder given", hint="add --out DIR (or --list to see the presets)")
    out = make_scene(args.preset, args.out, size=args.size, views=args.views, seed=args.seed,
                     test_views=args.test_views)
    print(f"wrote preset '{args.preset}' to {out}")
    return 0
