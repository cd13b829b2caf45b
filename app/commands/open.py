"""`repaint-nerf open PATH`: the editor on a dataset, photo folder or workspace (bare command: demo scene)."""
from __future__ import annotations

import argparse

NAME = "open"
HELP = "open the editor on a dataset, photo folder or saved workspace (default: the demo scene)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("path", nargs="?", default=None, help="dataset, photo folder or workspace; omitted: demo scene")
    p.add_argument("--workspace", default=None, help="workspace folder (default: next to the data, or ~/.cache)")


def run(args: argparse.Namespace) -> int:
    try:
        from app.editor import run_editor  # noqa: F401
    except ImportError:
        print("the editor is not built yet")
        return 1
    return run_editor(args.path, workspace=args.workspace)
