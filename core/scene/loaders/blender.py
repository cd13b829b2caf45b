"""NeRF-synthetic / Blender scenes: `transforms_{train,val,test}.json` next to the image folders.

Poses are already OpenGL camera-to-world. RGBA images keep their alpha (compositing is the
renderer's choice); a `background` colour, an `aabb` box, a `scene_kind` and a `depth_range` (what
our generator writes) in the JSON are kept on the scene. Frames are chosen and the content's reach read as for
nerfstudio files (frame_select.py, reach.py; instant-ngp reads these files the same way).
"""
from __future__ import annotations

import warnings
from pathlib import Path

from repaint_nerf.core.errors import SceneError, SceneWarning
from repaint_nerf.core.scene.loaders.common import wanted
from repaint_nerf.core.scene.loaders.frame_select import merge_reports, select_frames, warn_skipped
from repaint_nerf.core.scene.loaders.reach import content_reach
from repaint_nerf.core.scene.loaders.transforms_json import (find_image, frames_of, load_frames, parse_aabb,
                                                             parse_background, parse_depth_range, parse_kind, read_json)
from repaint_nerf.core.scene.scene import Scene

SPLITS = ("train", "val", "test")

def is_blender(root: Path) -> bool:
    """Whether `root` holds at least one `transforms_<split>.json`."""
    return any((root / f"transforms_{s}.json").is_file() for s in SPLITS)

def load_blender(root: Path, downscale: float = 1.0, splits=None, max_size: int = 0,
                 sharpness_discard: float | None = None) -> Scene:
    """Load a NeRF-synthetic scene; every split file found becomes a split (train is required)."""
    root = Path(root)
    if not (root / "transforms_train.json").is_file():
        raise SceneError("transforms_train.json not found (a NeRF-synthetic scene needs its train split)", root)
    out, background, aabb, kind, depth_range, reach, reports = {}, None, None, None, None, {}, []
    for split in SPLITS:
        path = root / f"transforms_{split}.json"
        if not path.is_file():
            continue
        meta = read_json(path)
        frames = frames_of(meta, path)
        if split == "train":
            background = parse_background(meta, path)
            aabb = parse_aabb(meta, path)
            kind = parse_kind(meta, path)
            depth_range = parse_depth_range(meta, path)
            reach = content_reach(meta, root, path, aabb)
        if wanted(split, splits):
            try:
                sel = select_frames(meta, frames, list(range(len(frames))),
                                    lambda i: find_image(root, frames[i]["file_path"], path, i), path, sharpness_discard)
            except SceneError as exc:
                if split == "train":
                    raise
                warnings.warn(f"left out the {split} split: {exc}", SceneWarning, stacklevel=2)  # train still opens
                continue
            warn_skipped(sel, len(frames), path)
            reports.append(sel.report())
            out[split] = load_frames(meta, frames, sel.kept, root, path, downscale, same_size=True, max_size=max_size)
    extra: dict = {"gt_dir": str(root / "gt")} if (root / "gt").is_dir() else {}
    if aabb is not None:
        extra["aabb"] = aabb
    extra.update(reach)
    skipped = merge_reports(reports)
    if skipped is not None:
        extra["skipped"] = skipped
    extra["alpha"] = any(sp.has_alpha for sp in out.values())
    extra["kind_given"] = kind is not None
    scene = Scene(root=root, format="blender", splits=out, background=background, kind=kind or "bounded",
                  extra=extra)
    if depth_range is not None:
        extra["depth_range"] = depth_range
        if kind == "forward":
            scene.near, scene.far = 0.9 * depth_range[0], 1.1 * depth_range[1]
    return scene

