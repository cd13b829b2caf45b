"""Tiny dataset writers for the loader tests: known cameras in, files in each format's layout out."""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from repaint_nerf.core.scene.cameras import look_at


def ring_poses(n: int, radius: float = 4.0, height: float = 1.0, seed: int = 0) -> np.ndarray:
    """(n, 4, 4) OpenGL camera-to-world poses on a jittered ring, looking near the origin."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        a = 2 * np.pi * i / n + rng.uniform(-0.2, 0.2)
        eye = np.array([radius * np.cos(a), radius * np.sin(a), height + rng.uniform(-0.3, 0.3)])
        out.append(look_at(eye, rng.uniform(-0.1, 0.1, 3)))
    return np.stack(out)


def pattern(h: int, w: int, seed: int, channels: int = 3) -> np.ndarray:
    """A smooth deterministic uint8 image (smooth so resizing compares well with a plain reference)."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w] / max(h, w)
    chans = [127.5 + 127.5 * np.sin(2 * np.pi * (rng.uniform(0.5, 2) * xx + rng.uniform(0.5, 2) * yy
                                                   + rng.uniform())) for _ in range(3)]
    if channels == 4:
        chans.append(np.where(xx < 0.5, 255.0, 128.0))
    return np.clip(np.stack(chans, -1) + 0.5, 0, 255).astype(np.uint8)


def write_image(path: Path, img: np.ndarray) -> Path:
    """Write RGB(A) uint8 (or 16-bit / gray) with OpenCV, which stores BGR(A)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    arr = img
    if img.ndim == 3 and img.shape[2] == 3:
        arr = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
    elif img.ndim == 3 and img.shape[2] == 4:
        arr = cv2.cvtColor(img, cv2.COLOR_RGBA2BGRA)
    assert cv2.imwrite(str(path), arr)
    return path


def write_blender(root: Path, counts=None, w: int = 24, h: int = 16, fl: float = 30.0, rgba: bool = True,
                  angle: bool = True, extra: dict | None = None, seed: int = 0) -> dict:
    """A NeRF-synthetic scene; returns {split: (poses (N,4,4), images)} plus 'fx' for checks."""
    counts = counts or {"train": 5, "test": 2}
    truth = {"fx": fl}
    for k, (split, n) in enumerate(counts.items()):
        poses = ring_poses(n, seed=seed + k)
        imgs = [pattern(h, w, seed * 100 + k * 10 + i, 4 if rgba else 3) for i in range(n)]
        frames = []
        for i, (m, im) in enumerate(zip(poses, imgs)):
            write_image(root / split / f"r_{i}.png", im)
            frames.append({"file_path": f"./{split}/r_{i}", "transform_matrix": m.tolist()})
        meta = {"camera_angle_x": 2 * np.arctan(0.5 * w / fl)} if angle else {"fl_x": fl, "fl_y": fl,
                                                                             "cx": w / 2, "cy": h / 2}
        meta.update(extra or {})
        meta["frames"] = frames
        (root / f"transforms_{split}.json").write_text(json.dumps(meta))
        truth[split] = (poses, imgs)
    return truth


def write_llff(root: Path, c2w: np.ndarray, h: int, w: int, focal: float, bounds: np.ndarray,
               folder: str = "images") -> list[np.ndarray]:
    """An LLFF scene from OpenGL poses: poses_bounds.npy in LLFF's [down, right, back] layout + images."""
    from repaint_nerf.core.scene.loaders.llff import opengl_to_llff

    n = len(c2w)
    mats = opengl_to_llff(c2w)
    hwf = np.broadcast_to(np.array([h, w, focal], dtype=np.float64)[None, :, None], (n, 3, 1))
    arr = np.concatenate([np.concatenate([mats, hwf], axis=2).reshape(n, 15), bounds], axis=1)
    root.mkdir(parents=True, exist_ok=True)
    np.save(root / "poses_bounds.npy", arr)
    imgs = [pattern(h, w, i) for i in range(n)]
    for i, im in enumerate(imgs):
        write_image(root / folder / f"IMG_{i:03d}.png", im)
    return imgs


def write_colmap(root: Path, c2w_gl: np.ndarray, model: str, params, w: int, h: int, points: np.ndarray,
                 colors: np.ndarray, text: bool = False, images: list[np.ndarray] | None = None) -> None:
    """A COLMAP scene written by pycolmap: one shared camera, OpenGL poses converted to COLMAP's
    world-to-camera OpenCV form, 3D points with colours, images in images/."""
    import pycolmap

    from repaint_nerf.core.scene.cameras import opencv_to_opengl

    rec = pycolmap.Reconstruction()
    cam = pycolmap.Camera.create_from_model_name(1, model, 1.0, w, h)
    cam.params = np.asarray(params, dtype=np.float64)
    rec.add_camera_with_trivial_rig(cam)
    for i, m in enumerate(c2w_gl):
        w2c = np.linalg.inv(opencv_to_opengl(m))
        img = pycolmap.Image(name=f"img_{i:02d}.png", camera_id=1, image_id=i + 1)
        rec.add_image_with_trivial_frame(img, pycolmap.Rigid3d(w2c[:3, :4]))
        write_image(root / "images" / f"img_{i:02d}.png", images[i] if images is not None else pattern(h, w, i))
    for p, c in zip(points, colors):
        rec.add_point3D(np.asarray(p, dtype=np.float64), pycolmap.Track(), np.asarray(c, dtype=np.uint8))
    out = root / "sparse" / "0"
    out.mkdir(parents=True, exist_ok=True)
    rec.write_text(str(out)) if text else rec.write(str(out))


def distort(img: np.ndarray, fx: float, fy: float, cx: float, cy: float, k1: float, k2: float, p1: float,
            p2: float) -> np.ndarray:
    """What an OpenCV-model lens (k1, k2, p1, p2) with these intrinsics shows of a pinhole image of the same ones."""
    import pycolmap

    h, w = img.shape[:2]
    cam = pycolmap.Camera.create_from_model_name(1, "OPENCV", 1.0, w, h)
    cam.params = [fx, fy, cx, cy, k1, k2, p1, p2]
    vv, uu = np.mgrid[0:h, 0:w] + 0.5
    xy = cam.cam_from_img(np.stack([uu.ravel(), vv.ravel()], 1))  # ideal normalised coordinates per pixel
    mx = (xy[:, 0] * fx + cx - 0.5).reshape(h, w).astype(np.float32)
    my = (xy[:, 1] * fy + cy - 0.5).reshape(h, w).astype(np.float32)
    return cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)


def write_ngp_capture(scene_dir: Path, out: Path, missing=(), sharpness=None, extra: dict | None = None,
                      gains=None, alpha: bool = True, lens: dict | None = None, width: int | None = None) -> dict:
    """An instant-ngp style capture from a generated scene: one `transforms.json` listing its train and test
    frames (file paths images/NNNN.png), with per-frame `sharpness` when given, the frames numbered in `missing`
    listed without their image, `extra` top-level keys (e.g. aabb_scale) and per-frame RGB `gains` (exposure /
    white balance) multiplied into the images' colour; `alpha=False` drops a transparent background's alpha (an
opaque photo of the object on a plain background); `lens` {k1, k2, p1, p2} distorts the images as that lens
would and writes the coefficients; `width` keeps that many central columns (a portrait capture from square
renders). Returns the JSON written."""
    frames, meta = [], None
    for split in ("train", "test"):
        m = json.loads((Path(scene_dir) / f"transforms_{split}.json").read_text())
        meta = meta or {k: m[k] for k in ("fl_x", "fl_y", "cx", "cy", "w", "h")}
        for fr in m["frames"]:
            frames.append((Path(scene_dir) / (fr["file_path"] + ".png"), fr["transform_matrix"]))
    out_frames = []
    for i, (src, pose) in enumerate(frames):
        frame = {"file_path": f"images/{i:04d}.png", "transform_matrix": pose}
        if sharpness is not None:
            frame["sharpness"] = float(sharpness[i])
        out_frames.append(frame)
        if i in set(missing):
            continue
        img = cv2.imread(str(src), cv2.IMREAD_UNCHANGED)
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2RGBA if img.shape[2] == 4 else cv2.COLOR_BGR2RGB)
        img = img[..., :3] if not alpha else img
        if width is not None:
            x0 = (img.shape[1] - width) // 2
            img = img[:, x0:x0 + width]
        if gains is not None:
            rgb = img[..., :3].astype(np.float32) * np.asarray(gains[i], np.float32) + 0.5
            img = np.concatenate([np.clip(rgb, 0, 255).astype(np.uint8), img[..., 3:]], axis=-1)
        if lens:
            cx = meta["cx"] - (meta["w"] - width) // 2 if width is not None else meta["cx"]
            img = distort(img, meta["fl_x"], meta["fl_y"], cx, meta["cy"], **lens)
        write_image(out / "images" / f"{i:04d}.png", img)
    if width is not None:
        meta = {**meta, "w": width, "cx": meta["cx"] - (meta["w"] - width) // 2}
    data = {**meta, **(lens or {}), **(extra or {}), "frames": out_frames}
    out.mkdir(parents=True, exist_ok=True)
    (out / "transforms.json").write_text(json.dumps(data))
    return data
