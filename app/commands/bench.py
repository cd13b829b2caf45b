"""`repaint-nerf bench NAME ...`: benchmarks that write JSON and PNG plots.

Each benchmark is a module in `core/bench/` (or `app/bench/` when it needs a window) with `HELP`,
`add_arguments(parser)` and `run(args) -> int`.
"""
from __future__ import annotations

import argparse
import importlib
import pkgutil

NAME = "bench"
HELP = "run a benchmark (recon, mask, edit, sdcost, viewport, ...) and write its figures as JSON (and PNG)"


def _benchmarks():
    import app.bench
    import core.bench

    for pkg in (core.bench, app.bench):
        for info in sorted(pkgutil.iter_modules(pkg.__path__), key=lambda m: m.name):
            if not info.name.startswith("_"):
                yield info.name, f"{pkg.__name__}.{info.name}"


def add_arguments(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="bench", metavar="NAME", required=True)
    for name, modname in _benchmarks():
        mod = importlib.import_module(modname)
        if not hasattr(mod, "run"):  # a measurement module whose CLI driver lives in app/bench
            continue
        bp = sub.add_parser(name, help=mod.HELP, description=mod.HELP)
        mod.add_arguments(bp)
        bp.set_defaults(_bench_run=mod.run)


def run(args: argparse.Namespace) -> int:
    return args._bench_run(args)
