"""Photo-folder intake for structure-from-motion: one clean, upright RGB image per photo.

EXIF rotation is applied, grayscale becomes RGB, alpha is flattened onto white, very large photos
are downscaled, non-image and unreadable files are skipped with a note, and mixed sizes are kept
(COLMAP gives each size its own camera). Unchanged photos are copied byte for byte (keeping EXIF
focal lengths for COLMAP's prior).
"""
from __future__ import annotations

import re
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from repaint_nerf.core.errors import SceneError
from repaint_nerf.core.scene.loaders.images import IMAGE_EXTS, exif_orientation, read_image, resize_image

MAX_SIDE = 1600  # longest side kept for SfM and training; the paper trains LLFF at 504x378
MIN_IMAGES = 3
MIN_SIDE = 32  # smaller photos carry too few features to register


@dataclass
class Intake:
    """The prepared photos: prepared file name per original name, in natural (capture) order, plus notes."""

    names: list[str]  # original file names, natural order
    prepared: dict[str, str]  # original name -> file name in the prepared folder
    sizes: dict[str, tuple[int, int]]  # original name -> (width, height) prepared
    notes: list[str] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)  # files not used, by name
    exif_focal: dict[str, float] = field(default_factory=dict)  # prepared name -> EXIF focal length in px


    def original_of(self) -> dict[str, str]:
        """Prepared file name -> original name."""
        return {v: k for k, v in self.prepared.items()}


EXIF_IFD = 0x8769
FOCAL_35MM = 0xA405  # FocalLengthIn35mmFilm: the focal length a 36 mm-wide frame would need


def exif_focal_px(path: Path, long_side: int) -> float | None:
    """The photo's focal length in pixels of an image `long_side` px long, from its 35 mm-equivalent EXIF tag."""
    try:
        from PIL import Image

        with Image.open(path) as im:
            f35 = float(im.getexif().get_ifd(EXIF_IFD).get(FOCAL_35MM, 0) or 0)
    except Exception:  # noqa: BLE001 - no readable EXIF simply means no focal prior
        return None
    return f35 / 36.0 * long_side if f35 > 0 else None


def natural_key(name: str) -> list:
    """Sort key that orders 'img2' before 'img10' (capture order for sequential matching)."""
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


def photo_files(folder: Path) -> tuple[list[Path], list[str]]:
    """(image files, names of other files skipped) directly inside `folder`, in natural order."""
    files, other = [], []
    for p in sorted(folder.iterdir(), key=lambda q: natural_key(q.name)):
        if p.name.startswith(".") or p.is_dir():
            continue
        if p.suffix.lower() in IMAGE_EXTS:
            files.append(p)
        else:
            other.append(p.name)
    return files, other


def photos_folder(root: Path) -> Path:
    """The folder holding the photos: `root/images` when root itself has none."""
    root = Path(root)
    if not root.is_dir():
        raise SceneError("no such photo folder", root, hint="pass a folder of photos")
    own, _ = photo_files(root)
    if not own and (root / "images").is_dir():
        return root / "images"
    return root


def _flatten(img: np.ndarray) -> np.ndarray:
    """RGBA over white -> RGB (COLMAP and the trainer both see the same pixels)."""
    rgb, a = img[..., :3].astype(np.float32), img[..., 3:4].astype(np.float32) / 255.0
    return (rgb * a + 255.0 * (1.0 - a) + 0.5).astype(np.uint8)


def prepare_photos(src: Path, out: Path, max_side: int = MAX_SIDE) -> Intake:
    """Write the usable photos of `src` into `out` (created fresh) and describe what was done.

    Raises a `SceneError` when fewer than `MIN_IMAGES` usable photos remain.
    """
    src = photos_folder(src)
    files, other = photo_files(src)
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    names, prepared, sizes, notes, skipped = [], {}, {}, [], list(other)
    exif_focal: dict[str, float] = {}
    if other:
        notes.append(f"skipped {len(other)} non-image file(s): {', '.join(other[:5])}"
                     + (" ..." if len(other) > 5 else ""))
    counts = {"rotated": 0, "gray": 0, "alpha": 0, "downscaled": 0, "converted": 0}
    taken = set()
    for p in files:
        try:
            img = read_image(p, orient=True)
        except SceneError:
            skipped.append(p.name)
            notes.append(f"skipped {p.name}: not a readable image")
            continue
        h, w = img.shape[:2]
        if min(h, w) < MIN_SIDE:
            skipped.append(p.name)
            notes.append(f"skipped {p.name}: {w}x{h} is too small for structure-from-motion")
            continue
        raw = cv2.imdecode(np.fromfile(p, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
        changed = False
        if exif_orientation(p) != 1:
            counts["rotated"] += 1
            changed = True
        if raw.ndim == 2 or raw.shape[2] in (1, 2):
            counts["gray"] += 1
            changed = True
        if img.shape[2] == 4:
            counts["alpha"] += 1
            img = _flatten(img)
            changed = True
        if raw.dtype != np.uint8 or p.suffix.lower() not in (".png", ".jpg", ".jpeg"):
            counts["converted"] += 1
            changed = True
        scale = max_side / max(h, w)
        if scale < 1.0:
            counts["downscaled"] += 1
            img = resize_image(img, max(1, round(w * scale)), max(1, round(h * scale)))
            changed = True
        name = p.name if not changed else f"{p.stem}.png"
        if name.lower() in taken:
            name = f"{p.name}.png"
        taken.add(name.lower())
        if changed:
            ok, buf = cv2.imencode(".png", cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
            (out / name).write_bytes(buf.tobytes())
        else:
            shutil.copyfile(p, out / name)
        names.append(p.name)
        prepared[p.name] = name
        sizes[p.name] = (int(img.shape[1]), int(img.shape[0]))
        focal = exif_focal_px(p, max(img.shape[:2]))
        if focal is not None:
            exif_focal[name] = focal
    labels = {"rotated": "rotated upright from EXIF orientation", "gray": "grayscale converted to RGB",
              "alpha": "with alpha flattened onto white", "downscaled": f"downscaled to at most {max_side} px",
              "converted": "converted to 8-bit PNG"}
    notes += [f"{n} photo(s) {labels[k]}" for k, n in counts.items() if n]
    distinct = sorted(set(sizes.values()))
    if len(distinct) > 1:
        notes.append(f"mixed sizes ({', '.join(f'{w}x{h}' for w, h in distinct[:4])}"
                     f"{' ...' if len(distinct) > 4 else ''}): one camera per size")
    if len(names) < MIN_IMAGES:
        raise SceneError(f"structure-from-motion needs at least {MIN_IMAGES} photos; found {len(names)} usable"
                         + (f" ({len(skipped)} skipped: {', '.join(skipped[:5])})" if skipped else ""), src,
                         hint="add overlapping photos of the scene from several viewpoints")
    return Intake(names, prepared, sizes, notes, skipped, exif_focal)


def fingerprint(src: Path) -> list:
    """What identifies the input photos for the cache: (name, bytes, mtime) of every file."""
    src = photos_folder(src)
    return [[p.name, p.stat().st_size, int(p.stat().st_mtime_ns // 1000)]
            for p in sorted(src.iterdir(), key=lambda q: q.name) if p.is_file() and not p.name.startswith(".")]
