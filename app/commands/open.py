"""`repaint-nerf open PATH`: the editor on a dataset, photo folder or workspace (bare command: demo scene)."""
from __future__ import annotations

import argparse

NAME = "open"
HELP = "open the editor on a dataset, photo folder or saved workspace (default: the demo scene)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("path", nargs="?", default=None, help="dataset, photo folder or workspace; omitted: demo scene")
    p.add_argument("--workspace", default=None, help="workspace folder (default: next to the data, or ~/.cache)")


def run(args: argparse.Namespace) -> int:
    from repaint_nerf.app.editor import run_editor  # a missing GUI package is an ImportError, not a quiet exit

    return run_editor(args.path, workspace=args.workspace)
