"""Object masks shipped beside a capture's images (NeRD's layout: `masks/NAME.jpg` for `images/NAME.JPG`).

A turntable capture (the object turns, the camera stays) has poses that describe the object alone: its static
background contradicts them, and no field can fit it (ethiopian_head trained to 18 dB on its own training views).
Such captures ship masks; they become the images' alpha, so the object is trained as a cut-out, against a random
background in training and white for evaluation, as NeRF-synthetic objects are.
"""
from __future__ import annotations

import re
import warnings
from pathlib import Path

import cv2
import numpy as np

from repaint_nerf.core.errors import SceneError, SceneWarning
from repaint_nerf.core.scene.loaders.images import list_images

ALPHA_FLOOR, ALPHA_CEIL = 12, 243  # JPEG masks ring near 0 and 255: below / above these they are 0 / 255


def mask_folder(root: Path, image_folder: Path) -> Path | None:
    """`masks_N/` beside an `images_N/` folder when it exists, else `masks/`, else None."""
    m = re.fullmatch(r"images_(\d+)", image_folder.name)
    for name in ([f"masks_{m.group(1)}"] if m else []) + ["masks"]:
        if list_images(root / name):
            return root / name
    return None


def find_masks(root: Path, image_folder: Path, images: list[Path]) -> list[Path] | None:
    """One mask per image, matched by file stem, or None when the capture ships none. Masks for only some
    images are ignored with a warning: a half-masked capture would train some views as cut-outs, some not."""
    folder = mask_folder(root, image_folder)
    if folder is None:
        return None
    by_stem = {p.stem.lower(): p for p in list_images(folder)}
    found = [by_stem.get(p.stem.lower()) for p in images]
    missing = [p.name for p, m in zip(images, found) if m is None]
    if missing:
        warnings.warn(f"{folder}: {len(images) - len(missing)} of {len(images)} images have a mask (none for "
                      f"e.g. {missing[0]!r}); the masks are not used", SceneWarning, stacklevel=2)
        return None
    return found  # type: ignore[return-value]


REDUCED = {8: cv2.IMREAD_REDUCED_GRAYSCALE_8, 4: cv2.IMREAD_REDUCED_GRAYSCALE_4, 2: cv2.IMREAD_REDUCED_GRAYSCALE_2,
           1: cv2.IMREAD_GRAYSCALE}


def read_mask(path: Path, width: int, height: int) -> np.ndarray:
    """A mask as uint8 (height, width) alpha. A mask much larger than the image is decoded at 1/2, 1/4 or 1/8
    of its size (JPEG's reduced decoding: a 4000-px mask in milliseconds, not the full decode). The 1/8 decode
    comes first: it is cheap and its size gives the full size to within 8 px."""
    data = np.fromfile(path, dtype=np.uint8) if path.is_file() else None
    small = cv2.imdecode(data, REDUCED[8]) if data is not None and data.size else None
    if small is None:
        raise SceneError("not a readable mask image", path, hint="replace it, or move the masks folder aside to "
                                                                 "train on the full images")
    k = next((k for k in (8, 4, 2) if small.shape[1] * 8 >= k * width and small.shape[0] * 8 >= k * height), 1)
    mask = small if k == 8 else cv2.imdecode(data, REDUCED[k])
    if mask.shape[1] * height != mask.shape[0] * width:
        raise SceneError(f"mask is {mask.shape[1]}x{mask.shape[0]} as read at 1/{k} of its size, its image's "
                         f"aspect is {width}x{height}", path, hint="masks must have their images' aspect ratio")
    if mask.shape[:2] != (height, width):
        mask = cv2.resize(mask, (width, height), interpolation=cv2.INTER_AREA)
    alpha = (mask.astype(np.float32) - ALPHA_FLOOR) * (255.0 / (ALPHA_CEIL - ALPHA_FLOOR))
    return np.clip(np.rint(alpha), 0, 255).astype(np.uint8)


def with_mask(img: np.ndarray, mask_path: Path) -> np.ndarray:
    """The image's RGB with the mask as its alpha (an alpha the image already has is multiplied in)."""
    alpha = read_mask(mask_path, img.shape[1], img.shape[0])
    if img.shape[2] == 4:
        alpha = (alpha.astype(np.uint16) * img[..., 3] // 255).astype(np.uint8)
    return np.dstack([img[..., :3], alpha])  # read_image gives RGB(A), never grey
