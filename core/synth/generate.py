"""Generate a synthetic scene with ground truth (depth, object masks, an edited variant) on disk.

Layout (issue 2): NeRF-synthetic `transforms_{train,test}.json` + `{train,test}/r_<i>.png`;
`gt/<split>/r_<i>_depth.npy` (float32 z-depth, 0 = no surface), `gt/<split>/r_<i>_mask.png` (object id
at the pixel centre, 0 = background), `gt/objects.json`; `edited/transforms_<split>.json`,
`edited/<split>/r_<i>.png`, `edited/edit.json` (and `edited/gt/...` when the edit changes geometry).
"""
from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

from repaint_nerf.core.errors import UserError
from repaint_nerf.core.synth.presets import PRESETS, SceneObject, SceneSpec, build_spec
from repaint_nerf.core.synth.raster import Rasterizer, world_bbox
from repaint_nerf.core.synth.writer import transforms, write_depth, write_json, write_png

GENERATOR = "repaint-nerf synth"
GENERATOR_VERSION = 1
SPLITS = ("train", "test")


def list_presets() -> dict[str, str]:
    """Preset name -> one-line description."""
    return {name: desc for name, (desc, _) in PRESETS.items()}


def _check_args(preset: str, out: Path, size: int, views: int, test_views: int) -> None:
    if preset not in PRESETS:
        raise UserError(f"unknown preset '{preset}'", hint=f"choose one of: {', '.join(PRESETS)}")
    if not 8 <= size <= 4096:
        raise UserError(f"image size {size} is out of range", hint="use --size between 8 and 4096")
    if views < 1 or test_views < 1:
        raise UserError(f"need at least one train and one test view (got {views} and {test_views})",
                        hint="use --views >= 1 and --test-views >= 1")
    if out.exists() and not out.is_dir():
        raise UserError("is a file, not a folder", out, hint="choose a folder for the scene")
    if out.is_dir() and any(out.iterdir()) and not (out / "gt" / "objects.json").is_file():
        raise UserError("the folder is not empty and does not hold a generated scene", out,
                        hint="choose an empty or new folder")


def _object_entry(i: int, obj: SceneObject) -> dict:
    return {"id": i, "name": obj.name, "color": list(obj.color), "shape": obj.mesh, "params": obj.params,
            "texture": obj.texture, "bbox": world_bbox(obj).tolist()}


def _edit_entry(spec: SceneSpec) -> dict:
    k = spec.edited_id()
    before, after = spec.objects[k - 1], spec.edited_objects()[k - 1]
    entry = {"kind": spec.edit.kind, "object_id": k, "object_name": spec.edit.target,
             "description": spec.edit.description}
    if spec.edit.kind == "recolor":
        entry |= {"from": {"color": list(before.color)}, "to": {"color": list(after.color)},
                  "masks": "gt"}
    else:
        entry |= {"from": _object_entry(k, before), "to": _object_entry(k, after), "masks": "edited/gt"}
    return entry


def _aabb(objects: list[SceneObject]) -> list[list[float]]:
    boxes = np.stack([world_bbox(o) for o in objects])
    return [boxes[:, 0].min(0).tolist(), boxes[:, 1].max(0).tolist()]


def make_scene(preset: str, out: Path, size: int = 128, views: int = 100, seed: int = 0,
               test_views: int | None = None) -> Path:
    """Render preset `preset` into folder `out` (size x size pixels, `views` train views); returns `out`.

    `test_views` defaults to views // 5 (at least 1). Everything is deterministic from `seed`.
    """
    out = Path(out)
    test_views = max(1, views // 5) if test_views is None else test_views
    _check_args(preset, out, size, views, test_views)
    for sub in ("train", "test", "gt", "edited"):
        shutil.rmtree(out / sub, ignore_errors=True)  # only inside a folder that held a generated scene
    out.mkdir(parents=True, exist_ok=True)

    rng = np.random.default_rng(seed)
    spec = build_spec(preset)
    poses = {"train": spec.rig(views, rng), "test": spec.rig(test_views, rng)}
    fx = fy = 0.5 * size / np.tan(0.5 * spec.camera_angle_x)
    cx = cy = 0.5 * size
    edited = spec.edited_objects()
    geometry_edit = spec.edit.kind != "recolor"
    depth_lo, depth_hi = np.inf, 0.0

    with Rasterizer(size, size, spec.near, spec.far) as ras:
        for split in SPLITS:
            for i, c2w in enumerate(poses[split]):
                frame = ras.render(spec.objects, c2w, fx, fy, cx, cy)
                rgb = frame.rgba[..., :3] if spec.opaque else frame.rgba
                write_png(out / split / f"r_{i}.png", rgb)
                write_depth(out / "gt" / split / f"r_{i}_depth.npy", frame.depth)
                write_png(out / "gt" / split / f"r_{i}_mask.png", frame.mask)
                hit = frame.depth[frame.depth > 0]
                if hit.size:
                    depth_lo, depth_hi = min(depth_lo, float(hit.min())), max(depth_hi, float(hit.max()))
                ed = ras.render(edited, c2w, fx, fy, cx, cy)
                write_png(out / "edited" / split / f"r_{i}.png", ed.rgba[..., :3] if spec.opaque else ed.rgba)
                if geometry_edit:
                    write_depth(out / "edited" / "gt" / split / f"r_{i}_depth.npy", ed.depth)
                    write_png(out / "edited" / "gt" / split / f"r_{i}_mask.png", ed.mask)

    extra = {"aabb": _aabb(spec.objects + edited), "scene_kind": spec.kind,
             "depth_range": [depth_lo if np.isfinite(depth_lo) else 0.0, depth_hi],
             "preset": preset, "seed": seed}
    for split in SPLITS:
        meta = transforms(poses[split], split, fx, fy, cx, cy, size, size, extra)
        write_json(out / f"transforms_{split}.json", meta)
        write_json(out / "edited" / f"transforms_{split}.json", meta)
    write_json(out / "gt" / "objects.json", {
        "objects": [_object_entry(i + 1, o) for i, o in enumerate(spec.objects)],
        "edited_object_id": spec.edited_id(),
        "preset": preset, "scene_kind": spec.kind, "seed": seed, "opaque": spec.opaque,
        "generator": GENERATOR, "generator_version": GENERATOR_VERSION,
    })
    write_json(out / "edited" / "edit.json", _edit_entry(spec))
    return out


__all__ = ["make_scene", "list_presets"]
