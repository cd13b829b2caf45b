"""nerfstudio / instant-ngp scenes: one `transforms.json` with per-file or per-frame intrinsics.

Split lists (`train_filenames`, `val_filenames`, `test_filenames`) are honoured; without them every
8th image (sorted by file path) is test. Distorted cameras (k1.., p1..) are undistorted at load. Frames whose
image is missing, or blurrier than their neighbours on request, are skipped as instant-ngp skips them
(frame_select.py); `aabb_scale` or a nerfstudio scene box say how far the content reaches (reach.py).
"""
from __future__ import annotations

from pathlib import Path

from repaint_nerf.core.errors import SceneError
from repaint_nerf.core.scene.loaders.common import TEST_EVERY, every_eighth_split, holdout_note, wanted
from repaint_nerf.core.scene.loaders.frame_select import select_frames, warn_skipped
from repaint_nerf.core.scene.loaders.reach import content_reach
from repaint_nerf.core.scene.loaders.transforms_json import (find_image, frames_of, load_frames, parse_aabb,
                                                             parse_background, read_json)
from repaint_nerf.core.scene.scene import Scene


def _norm(p: str) -> str:
    p = str(p).replace("\\", "/")
    return p[2:] if p.startswith("./") else p


def load_nerfstudio(root: Path, downscale: float = 1.0, splits=None, max_size: int = 0,
                    sharpness_discard: float | None = None, holdout_every: int = TEST_EVERY) -> Scene:
    """Load `root/transforms.json` (or the JSON file given) as a scene with train/test splits (the file's split
    lists, else every `holdout_every`-th frame with an image, sorted by file path, is test).

    `sharpness_discard` (None: the JSON's `sharpness_discard_threshold`) discards blurry frames (frame_select).
    """
    root = Path(root)
    path = root if root.is_file() else root / "transforms.json"
    root = path.parent
    meta = read_json(path)
    frames = frames_of(meta, path)
    order = sorted(range(len(frames)), key=lambda i: _norm(frames[i]["file_path"]))
    sel = select_frames(meta, frames, order, lambda i: find_image(root, frames[i]["file_path"], path, i), path,
                        sharpness_discard)
    warn_skipped(sel, len(frames), path)
    usable = set(sel.kept)
    order = sel.kept
    lists = {s: meta.get(f"{s}_filenames") for s in ("train", "val", "test")}
    if any(v is not None for v in lists.values()):
        index = {_norm(frames[i]["file_path"]): i for i in range(len(frames))}
        groups = {}
        for s, names in lists.items():
            if names is None:
                continue
            if not isinstance(names, list):
                raise SceneError(f"'{s}_filenames' must be a list of file paths", path)
            missing = [n for n in names if _norm(n) not in index]
            if missing:
                raise SceneError(f"'{s}_filenames' names {len(missing)} file(s) not among the frames, "
                                 f"e.g. '{missing[0]}'", path)
            groups[s] = [index[_norm(n)] for n in names if index[_norm(n)] in usable]
        if not groups.get("train"):
            raise SceneError("the split lists give no 'train_filenames' with an image", path)
        holdout = {"rule": "the file's own split lists (train/val/test_filenames)"}
    else:
        tr, te = every_eighth_split(len(order), holdout_every)
        holdout = holdout_note(holdout_every, "frames with an image, sorted by file path")
        groups = {"train": [order[k] for k in tr]}
        if te:
            groups["test"] = [order[k] for k in te]
    models: set = set()
    out = {s: load_frames(meta, frames, idx, root, path, downscale, same_size=False, max_size=max_size, models=models)
           for s, idx in groups.items() if idx and wanted(s, splits)}
    extra: dict = {"gt_dir": str(root / "gt")} if (root / "gt").is_dir() else {}
    aabb = parse_aabb(meta, path)
    if aabb is not None:
        extra["aabb"] = aabb
    extra.update(content_reach(meta, root, path, aabb))
    extra["skipped"] = sel.report()
    extra["holdout"] = holdout
    if models:
        extra["camera_models"] = sorted(models)
    return Scene(root=root, format="nerfstudio", splits=out, background=parse_background(meta, path), extra=extra)
