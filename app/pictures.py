"""Writing the documentation's pictures: PNGs kept small, and labelled side-by-side comparisons."""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

MAX_BYTES = 290_000  # a README picture stays under ~300 KB


def save_png(rgb: np.ndarray, path: str | Path, max_bytes: int = MAX_BYTES) -> Path:
    """Write an RGB uint8 picture; when the lossless file exceeds `max_bytes`, with 256 colours, then fewer
    (UI text stays sharp; only renders' gradients lose a little)."""
    from PIL import Image

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    img = Image.fromarray(np.ascontiguousarray(rgb[..., :3]))
    img.save(path, optimize=True)
    for colors in (256, 128, 64, 32):
        if path.stat().st_size <= max_bytes:
            break
        img.quantize(colors, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE).save(path, optimize=True)
    return path


def side_by_side(images: Sequence[np.ndarray], labels: Sequence[str], gap: int = 8,
                 max_height: int = 420) -> np.ndarray:
    """The images in a row at a common height (at most `max_height`), each under its label, on the editor's dark
    background."""
    import cv2

    h = min(max_height, *(im.shape[0] for im in images))
    resized = [cv2.resize(im, (round(im.shape[1] * h / im.shape[0]), h), interpolation=cv2.INTER_AREA)
               for im in images]
    bar = 34
    width = sum(im.shape[1] for im in resized) + gap * (len(resized) + 1)
    out = np.full((h + bar + gap, width, 3), (26, 26, 31), np.uint8)
    x = gap
    for im, label in zip(resized, labels):
        out[bar:bar + h, x:x + im.shape[1]] = im[..., :3]
        cv2.putText(out, label, (x + 2, bar - 11), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (235, 235, 235), 1, cv2.LINE_AA)
        x += im.shape[1] + gap
    return out
