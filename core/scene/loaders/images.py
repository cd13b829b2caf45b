"""Image reading for every loader: uint8 RGB(A) out, whatever the file holds.

EXIF orientation is honoured, grayscale becomes RGB, 16-bit and float images become 8-bit, and a
file that cannot be decoded (missing, truncated, not an image) is a `SceneError` naming it.
"""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from repaint_nerf.core.errors import SceneError

IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".webp", ".bmp", ".exr")
_EXIF_ORIENTATION = 0x0112


def list_images(folder: Path) -> list[Path]:
    """Image files directly inside `folder`, sorted by name (hidden files skipped)."""
    if not folder.is_dir():
        return []
    return sorted(p for p in folder.iterdir()
                  if p.is_file() and p.suffix.lower() in IMAGE_EXTS and not p.name.startswith("."))


def exif_orientation(path: Path) -> int:
    """The EXIF orientation tag (1..8) of an image file; 1 when absent or unreadable."""
    try:
        from PIL import Image

        with Image.open(path) as im:
            value = int(im.getexif().get(_EXIF_ORIENTATION, 1))
    except Exception:  # noqa: BLE001 - a file PIL cannot parse simply has no orientation for us
        return 1
    return value if 1 <= value <= 8 else 1


def image_size(path: str | Path) -> tuple[int, int]:
    """(width, height) of an image as `read_image` returns it, from the file header when possible."""
    path = Path(path)
    try:
        from PIL import Image

        with Image.open(path) as im:
            w, h = im.size
            orientation = int(im.getexif().get(_EXIF_ORIENTATION, 1))
        return (h, w) if orientation in (5, 6, 7, 8) else (w, h)
    except Exception:  # noqa: BLE001 - PIL cannot parse it: decode fully (raises a SceneError on bad files)
        img = read_image(path)
        return img.shape[1], img.shape[0]


def apply_orientation(img: np.ndarray, orientation: int) -> np.ndarray:
    """Rotate/flip pixels so an image with EXIF `orientation` displays upright (tag value -> upright)."""
    ops = {
        1: lambda a: a,
        2: lambda a: a[:, ::-1],
        3: lambda a: a[::-1, ::-1],
        4: lambda a: a[::-1],
        5: lambda a: a.swapaxes(0, 1),
        6: lambda a: np.rot90(a, -1),
        7: lambda a: a.swapaxes(0, 1)[::-1, ::-1],
        8: lambda a: np.rot90(a, 1),
    }
    return np.ascontiguousarray(ops.get(orientation, ops[1])(img))


def to_uint8_rgb(img: np.ndarray) -> np.ndarray:
    """Convert a decoded OpenCV array (BGR(A), gray, 8/16-bit or float) to uint8 RGB(A)."""
    if img.dtype == np.uint16:
        img = ((img.astype(np.uint32) * 255 + 32767) // 65535).astype(np.uint8)
    elif img.dtype.kind == "f":
        img = (np.clip(np.nan_to_num(img), 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    elif img.dtype != np.uint8:
        img = np.clip(img, 0, 255).astype(np.uint8)
    if img.ndim == 2:
        return cv2.cvtColor(img, cv2.COLOR_GRAY2RGB)
    channels = img.shape[2]
    if channels == 1:
        return cv2.cvtColor(img[..., 0], cv2.COLOR_GRAY2RGB)
    if channels == 2:  # gray + alpha
        return np.dstack([img[..., 0]] * 3 + [img[..., 1]])
    if channels == 3:
        return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    return cv2.cvtColor(img[..., :4], cv2.COLOR_BGRA2RGBA)


def read_image(path: str | Path, orient: bool = True) -> np.ndarray:
    """Read an image file as uint8 (H, W, 3|4) RGB(A), upright per its EXIF orientation when `orient`."""
    path = Path(path)
    if not path.is_file():
        raise SceneError("image file not found", path, hint="check the path in the scene description")
    try:
        data = np.fromfile(path, dtype=np.uint8)
    except OSError as exc:
        raise SceneError(f"cannot read image file ({exc.strerror})", path) from exc
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if img is None or img.size == 0:
        raise SceneError("not a readable image (truncated, corrupt or an unsupported format)", path,
                         hint="replace or re-export this image")
    img = to_uint8_rgb(img)
    if orient:
        img = apply_orientation(img, exif_orientation(path))
    return img


def resize_image(img: np.ndarray, width: int, height: int) -> np.ndarray:
    """Resize to (width, height): area averaging when shrinking (no aliasing), bilinear when enlarging."""
    if img.shape[1] == width and img.shape[0] == height:
        return img
    shrink = width <= img.shape[1] and height <= img.shape[0]
    return cv2.resize(img, (int(width), int(height)), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)


def fit_image(img: np.ndarray, width: int, height: int, path: Path) -> np.ndarray:
    """Resize an image to the size its camera expects; a different aspect ratio is a `SceneError`."""
    h, w = img.shape[:2]
    if (w, h) == (width, height):
        return img
    if abs(w / h - width / height) > 0.01 * (width / height) + 1.0 / min(h, height):
        raise SceneError(f"image is {w}x{h} but its camera expects {width}x{height} (another aspect ratio)",
                         path, hint="use the images the poses were computed for")
    return resize_image(img, width, height)
