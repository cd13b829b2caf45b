"""`repaint-nerf bench NAME ...`: benchmarks that write JSON and PNG plots.

Each benchmark's driver is a module in `app/bench/` with `HELP`, `add_arguments(parser)` and `run(args) -> int`;
its measurement lives in `core/bench/<name>.py` (functions that return dicts: no argparse, printing or plots).
"""
from __future__ import annotations

import argparse
import importlib
import pkgutil

NAME = "bench"
HELP = "run a benchmark (recon, mask, edit, sdcost, viewport, ...) and write its figures as JSON (and PNG)"


def _benchmarks():
    """(name, module) of every driver in app/bench."""
    import repaint_nerf.app.bench as bench

    for info in sorted(pkgutil.iter_modules(bench.__path__), key=lambda m: m.name):
        if not info.name.startswith("_"):
            yield info.name, f"repaint_nerf.app.bench.{info.name}"


def add_arguments(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="bench", metavar="NAME", required=True)
    for name, modname in _benchmarks():
        mod = importlib.import_module(modname)
        bp = sub.add_parser(name, help=mod.HELP, description=mod.HELP)
        mod.add_arguments(bp)
        bp.set_defaults(_bench_run=mod.run)


def run(args: argparse.Namespace) -> int:
    return args._bench_run(args)
