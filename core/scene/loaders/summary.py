"""A JSON-ready description of a loaded scene (what `repaint-nerf info` and the editor show)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from repaint_nerf.core.scene.scene import Scene


def _depth_gt(scene: Scene) -> dict:
    gt = Path(scene.extra.get("gt_dir", scene.root / "gt"))
    files = sorted(gt.glob("*/*_depth.npy")) if gt.is_dir() else []
    return {"present": bool(files), "folder": str(gt) if files else None, "files": len(files)}


def _skipped(scene: Scene) -> dict | None:
    """Frames the loader skipped (loaders/frame_select.py), when it skipped any."""
    rep = scene.extra.get("skipped")
    return rep if rep and (rep["missing"] or rep["blurry"]) else None


def scene_summary(scene: Scene) -> dict:
    """Format, splits with image counts and sizes, frames skipped, intrinsics, bounds (world) and normalisation,
    the space warp and why, extras."""
    from repaint_nerf.core.field.appearance import appearance_default
    from repaint_nerf.core.field.contraction import warp_summary

    splits = {}
    for name, sp in scene.splits.items():
        sizes = sorted({(int(w), int(h)) for w, h in zip(sp.cameras.width.tolist(), sp.cameras.height.tolist())})
        splits[name] = {"images": len(sp), "size": list(sizes[0]) if len(sizes) == 1 else [list(s) for s in sizes]}
    first = next(iter(scene.splits.values())).cameras
    intr = np.concatenate([np.stack([s.cameras.fx.numpy(), s.cameras.fy.numpy(), s.cameras.cx.numpy(),
                                     s.cameras.cy.numpy()], 1) for s in scene.splits.values()])
    half = 1.0 / scene.norm.scale
    norm = dict(scene.extra.get("normalization", {}))
    alpha = any(sp.has_alpha for sp in scene.splits.values())
    warp, warp_reason = warp_summary(scene)
    appearance, appearance_reason = appearance_default(scene)
    return {
        "path": str(scene.root),
        "format": scene.format,
        "kind": scene.kind,
        "kind_reason": scene.extra.get("kind_reason", "given by the dataset or --kind"),
        "warp": warp,
        "warp_reason": warp_reason,
        "skipped": _skipped(scene),
        "aabb_scale": scene.extra.get("aabb_scale"),
        "downscale": float(scene.extra.get("downscale", 1.0)),
        "splits": splits,
        "intrinsics": {"fx": float(first.fx[0]), "fy": float(first.fy[0]), "cx": float(first.cx[0]),
                       "cy": float(first.cy[0]), "vary": bool(np.ptp(intr, axis=0).max() > 1e-4)},
        "bounds_world": {"region": norm.get("box"), "rule": norm.get("rule"),
                         "source": scene.extra.get("unit_box_from"),
                         "grown_for_cameras": norm.get("grown_for_cameras"),
                         "field_cube": [[float(c - half) for c in scene.norm.center],
                                        [float(c + half) for c in scene.norm.center]]},
        "normalization": scene.norm.to_dict(),
        "near": float(scene.near),
        "far": float(scene.far),
        "background": None if scene.background is None else [float(c) for c in scene.background],
        "alpha": bool(alpha),
        "masks": scene.extra.get("masks_dir"),
        "points": 0 if scene.points is None else int(len(scene.points)),
        "depth_gt": _depth_gt(scene),
        "camera_models": scene.extra.get("camera_models"),
        "appearance": {"codes": appearance, "reason": appearance_reason},
    }


def format_summary(info: dict) -> str:
    """The summary as aligned human-readable lines."""
    f = lambda v: f"{v:.6g}"  # noqa: E731
    lines = [f"path            {info['path']}", f"format          {info['format']}",
             f"kind            {info['kind']} ({info['kind_reason']})",
             f"space warp      {info['warp']} ({info['warp_reason']})"]
    if info["downscale"] != 1.0:
        lines.append(f"downscale       {f(info['downscale'])}")
    for name, sp in info["splits"].items():
        size = sp["size"]
        size_s = f"{size[0]}x{size[1]}" if isinstance(size[0], int) else ", ".join(f"{w}x{h}" for w, h in size)
        lines.append(f"split {name:<9} {sp['images']} images, {size_s}")
    sk = info.get("skipped")
    if sk:
        ex = sk["examples"]
        if sk["missing"]:
            lines.append(f"skipped         {sk['missing']} frame(s) whose image is missing (e.g. {ex['missing'][0]})")
        if sk["blurry"]:
            lines.append(f"skipped         {sk['blurry']} blurry frame(s) (sharpness below {sk['threshold']:g}x their "
                         f"neighbours' mean)")
    k = info["intrinsics"]
    lines.append(f"intrinsics      fx={f(k['fx'])} fy={f(k['fy'])} cx={f(k['cx'])} cy={f(k['cy'])} "
                 f"(first image; {'vary per image' if k['vary'] else 'same for all images'})")
    if info.get("camera_models"):
        lines.append(f"camera models   {', '.join(info['camera_models'])} (undistorted at load)")
    b = info["bounds_world"]
    if b["region"]:
        lo, hi = b["region"]
        src = b.get("source") if b["rule"] == "unit_box" else b["rule"]
        grown = b.get("grown_for_cameras")
        lines.append(f"scene bounds    [{', '.join(map(f, lo))}] .. [{', '.join(map(f, hi))}] "
                     f"(world, from {src}" + (f"; grown {grown:.3g}x to hold the cameras, as a contracted scene "
                                              "needs them inside the field cube)" if grown else ")"))
    lo, hi = b["field_cube"]
    n = info["normalization"]
    lines.append(f"field cube      [{', '.join(map(f, lo))}] .. [{', '.join(map(f, hi))}] (world)")
    lines.append(f"normalisation   x_field = {f(n['scale'])} * (x_world - [{', '.join(map(f, n['center']))}])")
    lines.append(f"near / far      {f(info['near'])} / {f(info['far'])} (world units)")
    bg = info["background"]
    if bg is not None:
        lines.append(f"background      [{', '.join(map(f, bg))}]" + (", images have alpha" if info["alpha"] else ""))
    elif info["alpha"]:
        why = (f"alpha from the object masks in {info['masks']}/: the background is left out"
               if info.get("masks") else "images have alpha")
        lines.append(f"background      none given, {why} (random in training, white for evaluation)")
    else:
        lines.append("background      not needed (opaque images)")
    lines.append(f"sparse points   {info['points'] or 'none'}")
    d = info["depth_gt"]
    depth = f"yes, {d['files']} files in {d['folder']}" if d["present"] else "none"
    lines.append(f"depth gt        {depth}")
    a = info["appearance"]
    lines.append(f"appearance      {'a code per training image' if a['codes'] else 'none'} by default ({a['reason']}; "
                 f"train --appearance / --no-appearance)")
    return "\n".join(lines)
