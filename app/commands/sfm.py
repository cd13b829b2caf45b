"""`repaint-nerf sfm PHOTOS_DIR --workspace WS [--json OUT.json]`: structure-from-motion on a photo folder.

Prints each phase with its time, the model check's verdict (an implausible model is an error with its
reasons, never "registered"), the photos that could not be registered, and writes the report as JSON;
the workspace then trains like any other scene (`repaint-nerf train PHOTOS_DIR --workspace WS`).
"""
from __future__ import annotations

import argparse
import sys

NAME = "sfm"
HELP = "recover camera poses of a folder of photos (structure-from-motion, cached in the workspace)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("photos", help="folder of photos (or a folder with an images/ subfolder)")
    p.add_argument("--workspace", default=None, help="workspace folder (default: PHOTOS.repaint-nerf beside it)")
    p.add_argument("--json", default=None, help="write the report (total, registered, unregistered, seconds) here")
    p.add_argument("--matcher", default="auto", choices=("auto", "exhaustive", "sequential"),
                   help="feature matching: exhaustive for small sets, sequential (capture order) for large ones")
    p.add_argument("--kind", default=None, choices=("bounded", "forward", "unbounded"),
                   help="override the scene kind chosen from the camera layout")
    p.add_argument("--force", action="store_true", help="run again even when the workspace has a cached result")


def run(args: argparse.Namespace) -> int:
    from repaint_nerf.core.sfm.judge import Verdict
    from repaint_nerf.core.sfm.run import sfm_scene
    from repaint_nerf.core.workspace import atomic

    def progress(phase: str, frac: float, msg: str) -> None:
        if frac == 0.0 or frac >= 1.0:
            print(f"[{phase}] {msg}", file=sys.stderr, flush=True)
        else:
            print(f"\r[{phase}] {msg}", end="", file=sys.stderr, flush=True)

    scene = sfm_scene(args.photos, args.workspace, progress=progress, matcher=args.matcher, kind=args.kind,
                      force=args.force)
    rep = dict(scene.extra["sfm"])
    rep["kind"] = scene.kind
    rep["kind_reason"] = scene.extra.get("kind_reason", "given")
    for note in rep.get("notes", []):
        print(f"note: {note}", file=sys.stderr)
    print(f"model check: {Verdict.from_dict(rep.get('verdict') or {}).summary()}")
    secs = ", ".join(f"{k} {v:.1f} s" for k, v in rep["seconds"].items())
    print(f"registered {rep['registered']} of {rep['total']} photos; {rep['points']} points; "
          f"scene kind {scene.kind}" + (f"; {secs}" if secs else "") + (" (cached)" if rep.get("cached") else ""))
    if rep["unregistered"]:
        print(f"not registered (dropped): {', '.join(rep['unregistered'])}")
    if args.json:
        atomic.write_json(args.json, rep)
    return 0
