"""`repaint-nerf select WS --view I --patch x0,y0,x1,y1 [--add ...] [--sub ...] --out DIR` (or `--text PROMPT`
with a CLIP-aligned teacher): select an object through the workspace's feature field; writes the selection
and every training view's mask (into DIR and into the workspace, where the repaint reads them), each
optionally refined by SAM (`--sam-path`) prompted with that view's mask."""
from __future__ import annotations

import argparse
from pathlib import Path

NAME = "select"
HELP = ("select an object by a patch in one training view (or by text with a CLIP-aligned teacher); "
        "writes the selection and a mask per training view")


def add_arguments(p: argparse.ArgumentParser) -> None:
    from repaint_nerf.core.select.geometry import DEFAULT_GEOMETRY, GEOMETRY_NAMES

    p.add_argument("workspace", help="workspace folder trained with a feature head (repaint-nerf train)")
    p.add_argument("--view", type=int, default=None, help="training view index the patches are drawn in")
    query = p.add_mutually_exclusive_group(required=True)
    query.add_argument("--patch", help="x0,y0,x1,y1 in pixels (x1, y1 exclusive): the object's patch (needs --view)")
    query.add_argument("--text", help="what to select, e.g. 'a red ball': needs a workspace trained with a CLIP "
                                      "--feature-model (MaskCLIP), or an LSeg ONNX one and its CLIP (--clip-path)")
    p.add_argument("--clip-path", default=None,
                   help="local CLIP folder of an ONNX teacher's feature space, for --text (else "
                        "$REPAINT_NERF_CLIP_PATH); a CLIP feature teacher uses its own")
    p.add_argument("--sam-path", default=None, metavar="MODEL",
                   help="refine each view's mask with a local SAM (transformers SamModel folder or cached model id) "
                        "prompted by the mask's box and inside point; saved for the workspace ('none' turns it "
                        "off; default: the workspace's choice, else $REPAINT_NERF_SAM_PATH)")
    p.add_argument("--add", action="append", default=[], metavar="x0,y0,x1,y1",
                   help="another positive patch in the same view (repeatable): selects its look-alikes too")
    p.add_argument("--sub", action="append", default=[], metavar="x0,y0,x1,y1",
                   help="a negative patch (repeatable): pixels closer to it than to every positive are dropped")
    p.add_argument("--threshold", type=float, default=None,
                   help="similarity threshold in [0, 1] (default: chosen automatically from the patch's own "
                        "similarity and the field's depth edges in its view; for a text query, Otsu's split of the "
                        "similarities over every view)")
    p.add_argument("--no-cleanup", action="store_true", help="skip the 3D clean-up (keep every pixel above threshold)")
    p.add_argument("--geometry", choices=GEOMETRY_NAMES, default=DEFAULT_GEOMETRY,
                   help="the field's geometry in the masks: 'basic' = the voxel 3D clean-up; 'full' (default) adds "
                        "depth edges, concave creases (contact lines), growth from the patch carried between views, "
                        "the views' vote, hole filling and border pixels given to the surface whose depth they "
                        "share, for objects resting on or touching look-alikes, where the field's depth is smooth "
                        "enough to tell a step (else the clean-up only; see masks/index.json)")
    p.add_argument("--out", required=True, help="folder for the mask PNGs (mask_0000.png ... and index.json)")
    p.add_argument("--device", default=None, help="cpu, cuda, cuda:1 (default: $REPAINT_NERF_DEVICE, else CUDA if present)")


def _patches(args) -> list:
    """The --patch/--add/--sub rectangles of --view; --add/--sub without --patch is a UserError."""
    from repaint_nerf.core.errors import UserError
    from repaint_nerf.core.select.query import Patch

    if args.text is not None:
        if args.add or args.sub:
            raise UserError("--add and --sub are patches; use them with --patch, not --text")
        return []
    if args.view is None:
        raise UserError("--patch needs --view, the training view it is drawn in",
                        hint="e.g. --view 0 --patch 40,30,60,50")
    return [Patch.parse(args.patch, args.view)] + [Patch.parse(t, args.view) for t in args.add] \
        + [Patch.parse(t, args.view, positive=False) for t in args.sub]


def _check_patches(patches: list, cams, view: int | None) -> None:
    """Raise a UserError unless --view exists and every patch lies inside it."""
    from repaint_nerf.core.errors import UserError

    if not patches:
        return
    n = len(cams)
    if not 0 <= view < n:
        raise UserError(f"--view {view} does not exist; the scene has {n} training views",
                        hint=f"choose --view between 0 and {n - 1}")
    w, h = int(cams.width[view]), int(cams.height[view])
    for p in patches:
        p.check(w, h)


def _describe(args, patches: list) -> str:
    """What was selected with, for the summary line."""
    if args.text is not None:
        return f"selected by text {args.text!r}"
    return (f"selected with {sum(p.positive for p in patches)} positive and {sum(not p.positive for p in patches)} "
            f"negative patch(es) in view {args.view}")


def run(args: argparse.Namespace) -> int:
    import json
    import time

    import numpy as np

    from repaint_nerf.core.select.autothreshold import selection_auto_threshold, text_auto_threshold
    from repaint_nerf.core.select.masks import DEFAULT_THRESHOLD, ViewCache, check_threshold, masks_for_views, write_masks
    from repaint_nerf.core.select.selection import Selection
    from repaint_nerf.core.session import open_trained

    threshold = None if args.threshold is None else check_threshold(args.threshold)
    patches = _patches(args)
    trained = open_trained(args.workspace, args.device, need_features=True)
    ws, scene, field, grid = trained.workspace, trained.scene, trained.field, trained.grid
    cams = scene.field_cameras("train")
    _check_patches(patches, cams, args.view)
    from repaint_nerf.core.teachers.sam_refine import workspace_refiner

    refine = workspace_refiner(ws, scene.train.images, args.sam_path)  # a missing SAM fails before any render

    t0 = time.perf_counter()
    cache = ViewCache(field, grid, cams, render_opts=trained.render_options())
    sel = Selection(threshold=DEFAULT_THRESHOLD if threshold is None else threshold,
                    cleanup=not args.no_cleanup and bool(patches),  # text: no seed patch
                    teacher=str(ws.settings.get("teacher") or "default"))
    if args.text is not None:
        from repaint_nerf.core.teachers.text import workspace_text_query

        sel.add_text(args.text, *workspace_text_query(scene, ws, args.clip_path))
        views = [cache.mask_maps(i) for i in range(len(cams))]  # the maps the masks are shaped on
        sel.auto_threshold = text_auto_threshold([sel.similarity(m.feature).float().numpy() for m in views],
                                                 [m.opacity.numpy() > 0.5 for m in views])
        if threshold is None:
            sel.threshold = sel.auto_threshold
    else:
        feat = cache.get(args.view).feature
        for p in patches:
            sel.add_patch(feat, p)
        sel.auto_threshold = selection_auto_threshold(sel, cache, args.view)
        if threshold is None:
            sel.threshold = sel.auto_threshold
    threshold = sel.threshold
    names = list(scene.train.names)
    sel.geometry = args.geometry
    masks = masks_for_views(field, grid, cams, sel, workspace=ws, cache=cache, names=names, refine=refine,
                            images=scene.train.images)
    sel_path = sel.save(ws)
    out = Path(args.out)
    write_masks(out, masks, names, {"threshold": threshold, "cleanup": sel.cleanup})
    sel_copy = out / "selection.json"
    from repaint_nerf.core.workspace import atomic

    atomic.write_json(sel_copy, sel.to_dict())
    cover = np.mean([m.mean() for m in masks])
    how = "automatic" if args.threshold is None and sel.auto_threshold is not None else "given"
    used = json.loads((ws.masks_dir / "index.json").read_text(encoding="utf-8")).get("geometry") or []
    print(f"{_describe(args, patches)}, threshold {threshold:.2f} ({how}), geometry "
          f"{', '.join(used) or 'none'}{', SAM-refined' if refine else ''}: {len(masks)} masks covering "
          f"{100 * cover:.1f}% of pixels on average "
          f"({time.perf_counter() - t0:.1f} s)")
    print(f"wrote {out} (mask_0000.png ...), {ws.masks_dir} and {sel_path}")
    return 0
