"""The edited scene as a dataset other trainers take on: the current version rendered at every training camera
(images/frame_00001.png ...), with `transforms.json` in the nerfstudio / instant-ngp layout: OpenGL camera-to-world
`transform_matrix` in the scene's world units, `fl_x`/`fl_y`/`cx`/`cy`/`w`/`h`, and the selection's masks as a
per-frame `mask_path` (masks/frame_00001.png, 255 = selected; nerfstudio trains on the masked pixels only, so a
dataset with masks trains the selected object). Scenes with transparent images get RGBA renders (alpha = opacity),
and their background colour when the scene names one; `aabb` is the field's box in world units, so our own loader
normalises it as before.
The folder is written beside its final name and renamed when complete."""
from __future__ import annotations

import contextlib
import json
import shutil
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from repaint_nerf.core.errors import UserError
from repaint_nerf.core.export.common import EXPORT_DIR_MODE, Cancel, Progress, check_output_dir, checkpoint
from repaint_nerf.core.export.region import saved_masks
from repaint_nerf.core.scene.normalize import MARGIN


def _check_target(out: Path) -> None:
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise UserError("the dataset folder exists and is not empty", out,
                        hint="choose a new folder name (an export never writes over files)")


@contextlib.contextmanager
def _atomic_folder(out: Path):
    """A temporary folder beside `out` that becomes `out` when the block ends without error."""
    check_output_dir(out.parent, "dataset")
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".tmp", dir=out.parent))
    try:
        yield tmp
        _check_target(out)
        if out.exists():
            out.rmdir()
        tmp.chmod(EXPORT_DIR_MODE)  # mkdtemp made it private
        tmp.rename(out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def _write_png(path: Path, img: np.ndarray) -> None:
    code = cv2.COLOR_RGBA2BGRA if img.ndim == 3 and img.shape[2] == 4 else cv2.COLOR_RGB2BGR
    if not cv2.imwrite(str(path), cv2.cvtColor(img, code) if img.ndim == 3 else img):
        raise UserError("cannot write this image", path, hint="choose a folder you can write to, with free space")


def _intrinsics(cams, i: int) -> dict:
    return {"fl_x": float(cams.fx[i]), "fl_y": float(cams.fy[i]), "cx": float(cams.cx[i]), "cy": float(cams.cy[i]),
            "w": int(cams.width[i]), "h": int(cams.height[i])}


def field_aabb(source) -> list[list[float]]:
    """The world box that core.scene.normalize maps onto the field cube (fit_box's margin undone)."""
    norm = source.scene.norm
    half = 1.0 / (float(norm.scale) * MARGIN)
    c = np.asarray(norm.center, dtype=np.float64)
    return [(c - half).tolist(), (c + half).tolist()]


@torch.no_grad()
def export_dataset(source, out: str | Path, masks: bool | list = True, cancel: Cancel | None = None,
                   progress: Progress | None = None) -> dict:
    """Write the dataset folder; `masks`: True = the saved selection's when there is one, False = none, or a list
    of per-view bool masks. Returns facts for the message (path, frames, masks, bytes, seconds)."""
    from repaint_nerf.core.render.renderer import render_camera

    out = Path(out).expanduser().absolute()
    _check_target(out)
    t0 = time.perf_counter()
    split = source.scene.train
    world, field_cams = split.cameras, source.scene.field_cameras("train")
    mask_list = None
    if masks is not False:
        try:
            mask_list = saved_masks(source, None if masks is True else masks)
        except UserError:
            if masks is not True:  # masks the caller gave must be usable
                raise
    # RGBA when the photos had alpha or the scene names a background to composite on
    transparent = source.scene.background is not None or split.has_alpha
    bg = np.asarray(source.background(), np.float32)
    opts = source.render_options(("rgb", "opacity"))  # black background: un-composited colour + opacity
    dev_cams = field_cams.to(source.device)
    frames = []
    with _atomic_folder(out) as tmp:
        (tmp / "images").mkdir()
        if mask_list is not None:
            (tmp / "masks").mkdir()
        for i in range(len(field_cams)):
            checkpoint(cancel, progress, 0.97 * i / len(field_cams), f"rendering view {i + 1}/{len(field_cams)}")
            r = render_camera(source.field, source.grid, dev_cams, i, opts)
            rgb, alpha = r["rgb"].float().cpu().numpy(), r["opacity"].float().cpu().numpy()[..., None]
            if transparent:
                img = np.concatenate([rgb / np.maximum(alpha, 1e-4), alpha], -1)
            else:
                img = rgb + (1.0 - alpha) * bg
            name = f"frame_{i + 1:05d}.png"
            _write_png(tmp / "images" / name, (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8))
            frame = {"file_path": f"images/{name}", "transform_matrix": world.c2w[i].double().tolist(),
                     **_intrinsics(world, i)}
            if mask_list is not None:
                _write_png(tmp / "masks" / name, mask_list[i].astype(np.uint8) * 255)
                frame["mask_path"] = f"masks/{name}"
            frames.append(frame)
        meta = {"camera_model": "OPENCV"}
        shared = [k for k in ("fl_x", "fl_y", "cx", "cy", "w", "h") if len({f[k] for f in frames}) == 1]
        meta.update({k: frames[0][k] for k in shared})  # instant-ngp reads these at the top level
        for f in frames:
            for k in shared:
                del f[k]
        if source.scene.kind == "bounded":
            meta["aabb"] = field_aabb(source)
        if source.scene.background is not None:
            meta["background"] = [float(c) for c in bg]
        meta["train_filenames"] = [f["file_path"] for f in frames]
        meta["frames"] = frames
        (tmp / "transforms.json").write_text(json.dumps(meta, indent=2) + "\n", encoding="utf-8")
        size = sum(p.stat().st_size for p in tmp.rglob("*") if p.is_file())
    checkpoint(None, progress, 1.0, "dataset written")
    return {"path": str(out), "frames": len(frames), "masks": mask_list is not None, "bytes": size,
            "seconds": time.perf_counter() - t0}
