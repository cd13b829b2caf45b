"""`repaint-nerf repair WS`: check every file of a workspace against its content hash and bring it back to one
that opens (damaged files set aside under WS/damaged/, the index and settings rebuilt, masks and caches
recomputed). One line per action; nothing when the workspace is healthy."""
from __future__ import annotations

import argparse

NAME = "repair"
HELP = ("check a workspace's files and repair it: damaged files set aside in WS/damaged (never deleted), the "
        "version index and settings rebuilt from the versions, masks and caches recomputed")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("workspace", help="workspace folder (the one given to repaint-nerf train --workspace)")
    p.add_argument("--no-recompute", action="store_true",
                   help="only check and set aside files; do not recompute masks or teacher caches (no scene needed)")


def run(args: argparse.Namespace) -> int:
    from repaint_nerf.core.workspace.repair import repair_workspace

    for line in repair_workspace(args.workspace, recompute=not args.no_recompute):
        print(line)
    return 0
