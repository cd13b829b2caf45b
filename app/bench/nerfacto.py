"""`repaint-nerf bench nerfacto`: nerfstudio's nerfacto on a capture beside `bench recon` (core/bench/nerfacto.py):
the same held-out views, images and report times, nerfstudio run from its own venv; writes JSON in recon's shape."""
from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

from repaint_nerf.core.bench.recon import REPORT_AT

HELP = "nerfstudio nerfacto on a capture, side by side with bench recon (same views, images and report times)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scene", required=True, help="capture folder (e.g. one `bench captures --prepare` wrote)")
    p.add_argument("--seconds", type=float, default=60.0, help="wall-clock budget of ns-train, its setup included")
    p.add_argument("--report-at", default=",".join(f"{t:g}" for t in REPORT_AT),
                   help="seconds at which to score the checkpoint saved last before them (comma-separated)")
    p.add_argument("--holdout-every", type=int, default=None, help="as bench recon (default 8)")
    p.add_argument("--eval-views", type=int, default=None,
                   help="score only the first N held-out views, as bench recon --eval-views N (ns-eval on a CPU "
                        "takes minutes a view)")
    p.add_argument("--downscale", type=float, default=1.0)
    p.add_argument("--steps-per-save", type=int, default=25, help="checkpoint interval (the report times' grain)")
    p.add_argument("--ns-venv", default="/work/ns-venv", help="the virtual environment nerfstudio is installed in")
    p.add_argument("--work", default=None, help="working folder for the dataset, run and logs (default: temporary)")
    p.add_argument("--json", required=True, help="output JSON path")


def run(args: argparse.Namespace) -> int:
    from repaint_nerf.app.bench.recon import report_times
    from repaint_nerf.core.bench.nerfacto import measure
    from repaint_nerf.core.errors import UserError
    from repaint_nerf.core.workspace import atomic

    if not args.seconds > 0:
        raise UserError(f"--seconds must be positive, got {args.seconds}")
    if args.eval_views is not None and args.eval_views < 1:
        raise UserError(f"--eval-views must be at least 1, got {args.eval_views}")
    tmp = None if args.work else tempfile.TemporaryDirectory(prefix="repaint-nerf-nerfacto-")
    work = Path(args.work) if args.work else Path(tmp.name)
    try:
        result = measure(Path(args.scene), args.seconds, Path(args.ns_venv), work, report_times(args.report_at),
                         args.holdout_every, args.downscale, args.steps_per_save, args.eval_views)
    finally:
        if tmp is not None:
            tmp.cleanup()
    atomic.write_json(Path(args.json), result)
    run_ = result["run"]
    print(f"ns-train ran {run_['wall_s']:.0f} s (exit {run_['returncode']}), {run_['checkpoints']} checkpoints; "
          f"{result['scene']['test_views']} held-out views ({(result['evaluation']['holdout'] or {}).get('rule')})")
    for t, pt in result["at"].items():
        if pt is None:
            print(f"at {t} s: no checkpoint")
        elif "error" in pt:
            print(f"at {t} s: ns-eval failed: {pt['error']}")
        else:
            print(f"at {t} s: step {pt['step']}, test PSNR {pt['psnr']:.2f} dB, SSIM {pt['ssim']:.4f}")
    print(f"wrote {args.json}")
    return 0
