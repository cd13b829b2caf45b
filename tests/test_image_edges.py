"""Masks snapped to the photo's edges (core.select.image_edges) and the `image` geometry part in shaped masks."""
from __future__ import annotations

import numpy as np
import pytest

from repaint_nerf.core.select.image_edges import snap_mask, snap_masks


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / max((a | b).sum(), 1))


def _disc_photo(size: int = 64, r: float = 14.0, seed: int = 0):
    """A red disc on a textured grey-blue ground (RGB uint8) and its true mask."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:size, :size]
    disc = (yy - size / 2) ** 2 + (xx - size / 2) ** 2 <= r * r
    img = np.empty((size, size, 3), np.float32)
    img[...] = (0.45, 0.5, 0.62)
    img += rng.normal(0, 0.04, img.shape)
    img[disc] = (0.8, 0.15, 0.1)
    img[disc] += rng.normal(0, 0.03, (int(disc.sum()), 3))
    return (np.clip(img, 0, 1) * 255).astype(np.uint8), disc


def test_a_mask_one_pixel_off_the_outline_snaps_to_it():
    """A field's mask blurs the outline by a pixel: grown by one pixel all round, or shrunk by one, the band
    GrabCut decides brings it back onto the disc's edge."""
    import cv2

    img, disc = _disc_photo()
    k = np.ones((3, 3), np.uint8)
    for off in (cv2.dilate(disc.astype(np.uint8), k) > 0, cv2.erode(disc.astype(np.uint8), k) > 0):
        assert _iou(off, disc) < 0.9
        assert _iou(snap_mask(img, off), disc) > 0.97
        assert (snap_mask(img, off) == snap_mask(img, off)).all()  # the same input gives the same mask


def test_far_pixels_and_pixels_without_a_surface_never_join():
    """Only the band next to the mask is decided: a second red disc elsewhere stays out, and with a surface map
    a pixel the field has no surface at never joins (a dark pole's dark empty surroundings)."""
    img, disc = _disc_photo()
    twin = np.zeros_like(disc)
    twin[2:8, 2:8] = True
    img[twin] = img[disc][0]
    grown = snap_mask(img, disc)
    assert not (grown & twin).any()
    import cv2

    shrunk = cv2.erode(disc.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    assert not (snap_mask(img, shrunk, surface=shrunk) & ~shrunk).any()


def test_a_thin_part_stays_whatever_its_colour():
    """A two-pixel pole has no interior to erode to: it stays in the mask even where its colour matches the
    background beside it (and nothing without a surface joins it)."""
    img, disc = _disc_photo()
    mask = disc.copy()
    mask[4:int(64 / 2 - 14), 31:33] = True  # a pole above the disc
    img[4:18, 31:33] = img[0, 0]  # of the ground's colour
    out = snap_mask(img, mask, surface=mask)
    assert out[4:18, 31:33].all()


def test_small_or_whole_image_masks_are_kept_and_views_must_match():
    img, _ = _disc_photo()
    tiny = np.zeros((64, 64), bool)
    tiny[30:33, 30:33] = True
    assert (snap_mask(img, tiny) == tiny).all()
    full = np.ones((64, 64), bool)
    assert snap_mask(img, full).all()
    assert (snap_mask(img.astype(np.float32) / 255.0, tiny) == tiny).all()  # float images are accepted
    with pytest.raises(ValueError):
        snap_masks([img], [tiny, tiny])


def test_shaped_masks_use_the_photos_only_when_given_and_asked():
    """The `image` part runs last in shaped_masks given the views' photos; without photos, or with the part
    off (and in the 'basic' geometry), the masks are the geometry's own."""
    import torch

    from repaint_nerf.core.scene.cameras import Cameras, look_at
    from repaint_nerf.core.select.geometry import BASIC_PARTS, FULL_PARTS, GeometryParts
    from repaint_nerf.core.select.masks import ViewMaps, shaped_masks

    img, disc = _disc_photo()
    import cv2

    blurred = cv2.dilate(disc.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0  # the field's outline: 1 px out
    sim = torch.from_numpy(np.where(blurred, 0.9, 0.1).astype(np.float32))
    depth = torch.full((64, 64), 3.0)
    maps = [ViewMaps(torch.zeros(64, 64, 4, dtype=torch.float16), depth, torch.ones(64, 64))]
    cams = Cameras.create(look_at((0.0, -3.0, 0.0), (0.0, 0.0, 0.0))[None], 60.0, 60.0, 32.0, 32.0, 64, 64)
    seed = np.zeros((64, 64), bool)
    seed[30:34, 30:34] = True
    parts = GeometryParts(edges=False, grow=True, holes=False, cleanup3d=False, creases=False, vote=False,
                          attach=False, image=True)
    plain = shaped_masks([sim], maps, cams, [(0, seed)], 0.5, parts)[0]
    assert (plain == blurred).all()
    snapped = shaped_masks([sim], maps, cams, [(0, seed)], 0.5, parts, [img])[0]
    assert _iou(snapped, disc) > 0.97 > _iou(plain, disc)
    off = GeometryParts(**{**parts.__dict__, "image": False})
    assert (shaped_masks([sim], maps, cams, [(0, seed)], 0.5, off, [img])[0] == blurred).all()
    assert "image" in FULL_PARTS.names() and "image" not in BASIC_PARTS.names()
