"""Per-view refinement of selection masks along the photo's own edges (issue 15: "per-view refinement along
image edges with opencv"). The field's masks follow rendered features and depth, which blur an object's outline
by a pixel or two and miss the parts of a label or a stripe the teacher scored low; the photo has the outline.

GrabCut (OpenCV) re-decides only a band of `BAND` pixels around each view's mask, from colour models of the mask
and of its surroundings: the mask's interior and its thin parts (what an opening of the band's width removes: a
pole two pixels wide) stay in, pixels farther out stay out, and a pixel joins only where the field has a surface
(GrabCut alone gave a dark pole the dark empty space beside it).
"""
from __future__ import annotations

import cv2
import numpy as np

BAND = 1  # pixels each side of the mask's border that GrabCut decides
ITERATIONS = 3  # GrabCut's own rounds of colour model and graph cut
MIN_PIXELS = 20  # a smaller mask has too few pixels for a colour model: kept as it is
CONTEXT = 10  # pixels of surroundings around the band that the background's colour model is learned from


def snap_mask(image: np.ndarray, mask: np.ndarray, surface: np.ndarray | None = None, band: int = BAND) -> np.ndarray:
    """`mask` (bool (H, W)) with its border band re-decided by GrabCut on `image` (RGB, uint8 or float in [0, 1],
    resized to the mask when its size differs); `surface` (bool (H, W)): the pixels a mask may gain."""
    full = np.asarray(mask, bool)
    if int(full.sum()) < MIN_PIXELS or full.all():
        return full.copy()
    ys, xs = np.nonzero(full)  # GrabCut runs on the mask's box and its context only (~10x faster at 504x378)
    pad = band + CONTEXT
    box = (slice(max(ys.min() - pad, 0), ys.max() + pad + 1), slice(max(xs.min() - pad, 0), xs.max() + pad + 1))
    m = full[box]
    img = np.ascontiguousarray(_bgr8(image, full.shape)[box])
    k = np.ones((2 * band + 1,) * 2, np.uint8)
    m8 = m.astype(np.uint8)
    sure = cv2.erode(m8, k) > 0
    sure |= m & ~(cv2.morphologyEx(m8, cv2.MORPH_OPEN, k) > 0)  # thin parts: no interior to erode to
    labels = np.full(m.shape, cv2.GC_BGD, np.uint8)
    labels[cv2.dilate(m8, k) > 0] = cv2.GC_PR_BGD
    labels[m] = cv2.GC_PR_FGD
    labels[sure] = cv2.GC_FGD
    if not (labels == cv2.GC_BGD).any():  # GrabCut needs both models: a mask near the whole image stays
        return full.copy()
    bgd, fgd = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
    cv2.setRNGSeed(0)  # GrabCut seeds its colour models by k-means: the same mask and photo give the same result
    cv2.grabCut(img, labels, None, bgd, fgd, ITERATIONS, cv2.GC_INIT_WITH_MASK)
    out = full.copy()
    out[box] = (labels == cv2.GC_FGD) | (labels == cv2.GC_PR_FGD)
    return out & (full | np.asarray(surface, bool)) if surface is not None else out


def snap_masks(images: list[np.ndarray], masks: list[np.ndarray],
               surfaces: list[np.ndarray] | None = None) -> list[np.ndarray]:
    """`snap_mask` for every view (images, masks and surfaces in the same view order)."""
    if len(images) != len(masks):
        raise ValueError(f"{len(images)} images for {len(masks)} masks")
    surfaces = surfaces if surfaces is not None else [None] * len(masks)
    return [snap_mask(im, m, s) for im, m, s in zip(images, masks, surfaces)]


def _bgr8(image: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """A contiguous uint8 BGR copy of an image at `shape` (H, W), read as the teachers read it (`check_image`:
    RGB(A), uint8 or float in [0, 1]; RGBA over white)."""
    from repaint_nerf.core.teachers.base import check_image

    a = check_image(image)
    if a.shape[:2] != tuple(shape):
        a = cv2.resize(a, (shape[1], shape[0]), interpolation=cv2.INTER_AREA)
    return np.ascontiguousarray(a[..., ::-1])
