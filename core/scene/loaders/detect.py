"""`load_scene`: recognise a dataset folder's format, load it, and normalise it into field space.

Formats: NeRF-synthetic/Blender, nerfstudio `transforms.json`, LLFF `poses_bounds.npy`, COLMAP
sparse models. A folder of bare photos needs structure-from-motion first: when
`core.sfm.run.sfm_scene(root, downscale=..., workspace_dir=..., splits=...) -> Scene` exists it is called (its
result cached in the workspace, by default beside the photos), else a `SceneError` says so.
"""
from __future__ import annotations

import importlib
from pathlib import Path

from repaint_nerf.core.errors import SceneError, UserError
from repaint_nerf.core.scene.loaders.blender import is_blender, load_blender
from repaint_nerf.core.scene.loaders.colmap import find_model, load_colmap
from repaint_nerf.core.scene.loaders.common import (DEFAULT_MAX_SIZE, TEST_EVERY, check_downscale,
                                                    check_holdout_every, check_max_size)
from repaint_nerf.core.scene.loaders.frame_select import check_sharpness_discard
from repaint_nerf.core.scene.loaders.images import list_images
from repaint_nerf.core.scene.loaders.llff import load_llff
from repaint_nerf.core.scene.loaders.nerfstudio import load_nerfstudio
from repaint_nerf.core.scene.kinds import FORWARD_MAX_ANGLE, choose_kind, view_spread_deg
from repaint_nerf.core.scene.normalize import normalize_scene
from repaint_nerf.core.scene.scene import SCENE_KINDS, Scene

FORMATS = ("blender", "nerfstudio", "llff", "colmap", "photos")


def detect_format(path: str | Path) -> tuple[str, Path]:
    """(format, scene root) for a dataset folder or its description file; a `SceneError` when unknown."""
    path = Path(path).expanduser()
    if not path.exists():
        raise SceneError("no such file or folder", path, hint="check the path")
    if path.is_file():
        name = path.name
        if name.startswith("transforms_") and name.endswith(".json"):
            return "blender", path.parent
        if name.endswith(".json"):
            return "nerfstudio", path
        if name == "poses_bounds.npy":
            return "llff", path.parent
        raise SceneError("not a scene description: give a dataset folder, a transforms*.json or poses_bounds.npy",
                         path)
    root = path
    if is_blender(root):
        return "blender", root
    if (root / "transforms.json").is_file():
        return "nerfstudio", root
    if (root / "poses_bounds.npy").is_file():
        return "llff", root
    if find_model(root) is not None:
        return "colmap", root
    if (root / "sparse").is_dir():
        raise SceneError("COLMAP folder without a model: sparse/ holds no cameras/images/points3D files",
                         root / "sparse", hint="run structure-from-motion (`repaint-nerf sfm`) or restore the model")
    if list_images(root) or list_images(root / "images"):
        return "photos", root
    entries = [p for p in root.iterdir() if not p.name.startswith(".")]
    if not entries:
        raise SceneError("the folder is empty", root, hint="point to a dataset folder or a folder of photos")
    raise SceneError("no scene found: expected transforms_train.json (NeRF-synthetic), transforms.json "
                     "(nerfstudio), poses_bounds.npy (LLFF), sparse/0 (COLMAP) or photos", root)


def _sfm_hook():
    """`core.sfm.run.sfm_scene` when that module exists (structure-from-motion on bare photos), else None."""
    try:
        mod = importlib.import_module("repaint_nerf.core.sfm.run")
    except ModuleNotFoundError as exc:
        if exc.name and (exc.name == "repaint_nerf.core.sfm" or exc.name.startswith("repaint_nerf.core.sfm.")):
            return None
        raise
    return getattr(mod, "sfm_scene", None)


def _load_photos(root: Path, downscale: float, splits, workspace=None, max_size: int = 0) -> Scene:
    sfm = _sfm_hook()
    if sfm is None:
        raise SceneError("this folder holds photos without camera poses: structure-from-motion is needed", root,
                         hint="run `repaint-nerf sfm` on it first (not available in this version yet)")
    more = {k: v for k, v in (("workspace_dir", workspace), ("splits", splits)) if v is not None}
    return sfm(root, downscale=downscale, max_size=max_size, **more)


LOADERS = {"blender": load_blender, "nerfstudio": load_nerfstudio, "llff": load_llff, "colmap": load_colmap,
           "photos": _load_photos}


def load_scene(path: str | Path, downscale: float = 1.0, kind: str | None = None, splits=None,
               workspace: str | Path | None = None, max_size: int = DEFAULT_MAX_SIZE,
               sharpness_discard: float | None = None, holdout_every: int | None = None) -> Scene:
    """Load any supported dataset as a `Scene` in world units with `scene.norm` set.

    `downscale` divides image width and height (2 = half size); `kind` overrides the scene kind, which
    is otherwise the dataset's (LLFF: forward; a transforms JSON's `scene_kind`) or detected from the
    camera layout (`core.scene.kinds`); `splits` restricts which splits' images are read;
    `workspace` is where structure-from-motion on a photo folder caches its result; images whose longest
    side exceeds `max_size` after `downscale` are loaded smaller to fit it (0 = full size), with their
    intrinsics scaled alike; `sharpness_discard` drops blurry frames of transforms JSONs as instant-ngp's
    `sharpness_discard_threshold` does (None: the file's own threshold, else none; loaders/frame_select.py);
    `holdout_every` N holds out images 0, N, 2N, ... as the test split of a capture without its own split (None:
    every 8th, as nerfstudio and instant-ngp do); a NeRF-synthetic scene or a file with split lists keeps its own.
    """
    downscale = check_downscale(downscale)
    max_size = check_max_size(max_size)
    if kind is not None and kind not in SCENE_KINDS:
        raise UserError(f"unknown scene kind {kind!r}", hint=f"use one of {', '.join(SCENE_KINDS)}")
    splits = None if splits is None else ((splits,) if isinstance(splits, str) else tuple(splits))
    fmt, root = detect_format(path)
    extra_args = {"workspace": workspace} if fmt == "photos" else {}
    if fmt in ("nerfstudio", "llff", "colmap"):
        extra_args["holdout_every"] = TEST_EVERY if holdout_every is None else check_holdout_every(holdout_every)
    elif fmt == "photos" and holdout_every not in (None, TEST_EVERY):
        raise UserError("--holdout-every applies to scenes with poses; a photo folder holds out every 8th view "
                        "after structure-from-motion", hint="run `repaint-nerf sfm` first and point to its result")
    if fmt in ("blender", "nerfstudio"):
        extra_args["sharpness_discard"] = None if sharpness_discard is None else check_sharpness_discard(
            sharpness_discard)
    scene = LOADERS[fmt](root, downscale=downscale, splits=splits, max_size=max_size, **extra_args)
    if not scene.splits or sum(len(s) for s in scene.splits.values()) == 0:
        raise SceneError(f"no images loaded (requested splits: {', '.join(splits or ('all',))})", root)
    if kind is not None:
        scene.kind = kind
    elif fmt in ("blender", "nerfstudio", "colmap") and not scene.extra.get("kind_given"):
        choose_kind(scene)
    elif fmt == "llff" and "train" in scene.splits and \
            view_spread_deg(scene.train.cameras.c2w.double().numpy()) > FORWARD_MAX_ANGLE:
        # poses_bounds.npy also carries 360-degree captures (mip-NeRF 360 ships them so): decide from the layout
        bounds = scene.extra["bounds"]
        scene.extra.setdefault("depth_range", [float(bounds.min()), float(bounds.max())])
        choose_kind(scene)
    scene.extra.setdefault("holdout", {"rule": "the dataset's own test split"})
    scene.extra.setdefault("downscale", downscale)
    scene.extra.setdefault("max_size", max_size)
    normalize_scene(scene)
    return scene
