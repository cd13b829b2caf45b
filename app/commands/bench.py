"""`repaint-nerf bench NAME ...`: benchmarks that write JSON and PNG plots.

Each benchmark's driver is a module in `app/bench/` with `HELP`, `add_arguments(parser)` and `run(args) -> int`;
its measurement lives in `core/bench/<name>.py` (functions that return dicts: no argparse, printing or plots).
"""
from __future__ import annotations

import argparse
import importlib
import pkgutil
from pathlib import Path

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
    rc = args._bench_run(args)
    if rc == 0 and getattr(args, "json", None):
        stamp(Path(args.json), getattr(args, "_argv", None) or ["bench", args.bench, "--json", args.json])
    return rc


def stamp(path: Path, argv: list[str]) -> None:
    """Record in the bench's JSON the day it was measured and the command line that measured it (the generated
    docs quote both: `repaint-nerf docs`). A file the bench did not write as a JSON object is left alone."""
    import datetime as dt
    import json
    import shlex

    from repaint_nerf.core.workspace import atomic

    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return
    if isinstance(data, dict):
        data["measured"] = dt.datetime.now(dt.timezone.utc).date().isoformat()
        data["command"] = "repaint-nerf " + " ".join(shlex.quote(a) for a in argv)
        atomic.write_json(path, data)
