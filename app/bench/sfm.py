"""`repaint-nerf bench sfm --views 20,50,100 --size 400x300 --json OUT.json`: the driver of core/bench/sfm.py
(SfM time per phase and pose accuracy for several photo counts)."""
from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

from repaint_nerf.core.bench.sfm import bench_one

HELP = "structure-from-motion: seconds per phase and pose error against the truth for several photo counts"


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must be WIDTHxHEIGHT, got {text!r}") from None
    return w, h


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--views", default="20,50,100", help="comma-separated photo counts")
    p.add_argument("--size", type=_size, default=(400, 300), help="photo size WIDTHxHEIGHT")
    p.add_argument("--preset", default="room360", help="synthetic preset (room360, forward, demo, ...)")
    p.add_argument("--matcher", default="auto", choices=("auto", "exhaustive", "sequential"))
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", required=True, help="output JSON path")


def run(args: argparse.Namespace) -> int:
    from repaint_nerf.core.device import describe
    from repaint_nerf.core.errors import UserError
    from repaint_nerf.core.workspace import atomic

    try:
        counts = [int(v) for v in str(args.views).split(",") if v.strip()]
    except ValueError:
        raise UserError(f"--views must be comma-separated integers, got {args.views!r}") from None
    w, h = args.size
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench_sfm_") as tmp:
        for n in counts:
            row = bench_one(args.preset, n, w, h, args.matcher, args.seed, Path(tmp))
            rows.append(row)
            secs = " ".join(f"{k}={v:.1f}" for k, v in row["seconds"].items())
            print(f"{n:4d} views {w}x{h} ({row['matcher']}): registered {row['registered']}, {secs}, "
                  f"total {row['seconds_total']:.1f} s; rot max {row['rotation_deg_max']:.3f} deg, "
                  f"pos max {100 * row['position_rel_max']:.2f}% of radius", flush=True)
            atomic.write_json(args.json, {"bench": "sfm", "preset": args.preset, "device": describe(),
                                          "note": "CPU times on a shared machine are rough", "rows": rows})
    return 0
