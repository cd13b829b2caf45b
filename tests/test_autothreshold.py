"""The automatic threshold (core.select.autothreshold) and the geometry in masks (core.select.geometry)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from repaint_nerf.core.scene.cameras import Cameras, look_at
from repaint_nerf.core.select.autothreshold import auto_threshold, choose_threshold, patch_auto_threshold, patch_pixels
from repaint_nerf.core.select.geometry import GeometryParts, depth_edges, fill_holes, geometric_masks, grow


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / max((a | b).sum(), 1))


def _disc(h: int, w: int, cy: float, cx: float, r: float) -> np.ndarray:
    yy, xx = np.mgrid[:h, :w]
    return (yy - cy) ** 2 + (xx - cx) ** 2 <= r * r


def _disc_before_slab(size: int, disc: tuple[float, float, float], slab: tuple[int, int, int, int]):
    """(disc, slab) bool masks of a size x size image: a disc (cy, cx, r) and the rows/columns (y0, y1, x0, x1)
    of a slab it touches, without the disc."""
    d = _disc(size, size, *disc)
    s = np.zeros((size, size), bool)
    s[slab[0]:slab[1], slab[2]:slab[3]] = True
    return d, s & ~d


def test_two_clear_modes_give_a_threshold_between_them():
    rng = np.random.default_rng(0)
    obj = _disc(96, 96, 48, 48, 20)
    sim = np.where(obj, 0.85, 0.25) + rng.normal(0.0, 0.03, obj.shape)
    seeds = patch_pixels(obj.shape, (0.45, 0.45, 0.55, 0.55))
    a = auto_threshold(sim, seeds)
    assert 0.4 < a.value < 0.75, a.value
    assert _iou(sim > a.value, obj) > 0.97


def test_support_of_similar_colour_touching_the_object_is_left_out():
    """The object (0.95) rests on a support (0.72, touching it) amid clutter (0.2): the grown region jumps
    where it leaks onto the support, and the threshold stays above that jump."""
    rng = np.random.default_rng(1)
    h = w = 96
    obj, support = _disc_before_slab(h, (40, 48, 16), (54, 80, 10, 86))
    sim = np.full((h, w), 0.2) + rng.normal(0.0, 0.02, (h, w))
    sim[support] = 0.72 + rng.normal(0.0, 0.02, int(support.sum()))
    sim[obj] = 0.95 + rng.normal(0.0, 0.015, int(obj.sum()))
    seeds = patch_pixels((h, w), (0.45, 0.35, 0.55, 0.45))
    a = auto_threshold(sim, seeds)
    assert a.jump is not None and a.jump < a.value
    assert 0.76 < a.value < 0.92, a.value
    assert _iou(grow(sim > a.value, seeds), obj) > 0.95
    assert _iou(sim > 0.5, obj) < 0.6  # what the fixed 0.5 did


def test_choose_threshold_ignores_the_fall_to_the_patch_alone():
    ts = np.round(np.arange(0.02, 0.985, 0.01), 2)
    areas = np.where(ts < 0.9, 1000, 25)  # the object until 0.9, then only the 25 patch pixels
    value, jump = choose_threshold(ts, areas, seed_area=25)
    assert jump is None and 0.3 < value < 0.6


def test_the_object_is_the_longest_plateau_above_a_leak_not_a_slow_shrink_right_above_it():
    """A trained room360 field's curve without depth edges, in shape: a leak at 0.1, then a shadow whose
    similarity fades (the area shrinks ~2% per 0.01 from 0.15 to 0.40), a step, and the object's own long
    plateau 0.44-0.82. The object is the plateau (the old rule took the shadow stretch's middle, ~0.28)."""
    ts = np.round(np.arange(0.02, 0.985, 0.01), 2)
    areas = np.select([ts < 0.10, ts < 0.15, ts < 0.40, ts < 0.44, ts <= 0.82],
                      [16000.0, 4000.0, 3600.0 - 2400.0 * (ts - 0.15), 3000.0 - 7500.0 * (ts - 0.40),
                       2700.0 - 180.0 * (ts - 0.44)], 100.0)
    value, jump = choose_threshold(ts, np.round(areas), seed_area=100)
    assert jump is not None and jump < 0.15
    assert 0.55 <= value <= 0.72, value


def test_an_object_of_two_parts_is_the_plateau_right_above_the_leak_not_its_longer_part():
    """A printed can under the blended teacher, in shape: the patch's colour alone holds 0.38-0.98 (~330 px),
    the whole can 0.12-0.32 (~760 px: a step of 1.9x joins its other colour), the room leaks in at 0.09.
    The can is the plateau right above the leak (the old rule took the longer upper plateau: test IoU 0.52)."""
    ts = np.round(np.arange(0.02, 0.985, 0.01), 2)
    areas = np.select([ts < 0.09, ts < 0.34, ts < 0.37], [4800.0, 790.0 - 250.0 * (ts - 0.12), 700.0],
                      385.0 - 160.0 * (ts - 0.37))
    value, jump = choose_threshold(ts, np.round(areas), seed_area=121)
    assert jump is not None and jump < 0.12
    assert 0.15 <= value <= 0.30, value


def test_a_leak_followed_by_a_slow_shrink_still_finds_the_plateau_above_it():
    """The region covers most of the view up to 0.62, collapses by 3x within 0.04, shrinks ~10% per 0.02 for
    a while, and settles on the object near 0.8: the object is that plateau, not the view's (the old rule
    required the plateau within 0.08 of the leak and fell back to the view: test IoU 0.04 instead of 0.83)."""
    ts = np.round(np.arange(0.02, 0.985, 0.01), 2)
    areas = np.select([ts < 0.62, ts < 0.70, ts < 0.79, ts < 0.85],
                      [6700.0, 6700.0 - 70000.0 * (ts - 0.62), 1100.0 * np.exp(-6.0 * (ts - 0.70)), 640.0],
                      640.0 * np.exp(-8.0 * (ts - 0.85)))
    value, jump = choose_threshold(ts, np.round(areas), seed_area=121)
    assert jump is not None and 0.6 <= jump <= 0.7
    assert 0.79 <= value <= 0.85, value


def test_the_patch_view_uses_depth_edges_only_where_the_masks_can():
    """A disc (0.8) in front of a touching slab of a similar colour (0.6): smooth depth closes the disc with
    an edge, so its plateau runs to the bottom of the grid; on depth rougher than `DEPTH_EDGE` (where the
    masks keep only the 3D clean-up, `fit_parts`) and with the 'basic' geometry, the threshold comes from
    the similarity alone and stays above the slab."""
    from repaint_nerf.core.select.geometry import DEPTH_EDGE

    rng = np.random.default_rng(3)
    h = w = 64
    disc, slab = _disc_before_slab(h, (32, 32, 12), (20, 60, 8, 56))
    sim = np.where(disc, 0.8, np.where(slab, 0.6, 0.1)) + rng.normal(0.0, 0.01, (h, w))
    depth = np.where(disc, 3.0, 4.0).astype(np.float32)
    opacity = np.ones((h, w), np.float32)
    patch = (0.45, 0.45, 0.55, 0.55)
    smooth = patch_auto_threshold(sim, patch, depth, opacity)
    assert smooth < 0.55, smooth  # the edge holds the region: anything below the disc is safe here
    alone = patch_auto_threshold(sim, patch, None, opacity)
    assert 0.62 < alone < 0.78, alone
    rough = (depth * np.exp(rng.normal(0.0, 2.0 * DEPTH_EDGE / np.sqrt(6), depth.shape))).astype(np.float32)
    assert patch_auto_threshold(sim, patch, rough, opacity) == alone
    assert patch_auto_threshold(sim, patch, depth, opacity, edges=False) == alone


def test_a_free_view_patch_takes_its_threshold_from_the_edge_depth_and_its_points_from_the_depth():
    """Selection.anchor_patch (the editor's patch): its automatic threshold's region stops at the edges of
    `edge_depth` (the expected depth, ViewMaps.edge_depth) and its surface points lie on `depth` (the median)."""
    from repaint_nerf.core.select.selection import Selection

    rng = np.random.default_rng(3)
    h = w = 64
    disc, slab = _disc_before_slab(h, (32, 32, 12), (20, 60, 8, 56))
    sim = np.where(disc, 0.8, np.where(slab, 0.6, 0.1)) + rng.normal(0.0, 0.01, (h, w))
    edged = np.where(disc, 3.0, 4.0).astype(np.float32)
    flat = np.full((h, w), 2.5, np.float32)  # no edge: the region leaks onto the slab
    opacity = np.ones((h, w), np.float32)
    cam = Cameras.create(look_at((0.0, -5.0, 0.0), (0.0, 0.0, 0.0))[None], 60.0, 60.0, w / 2, h / 2, w, h)
    patch = (0.45, 0.45, 0.55, 0.55)
    sel = Selection()
    with_edges = sel.anchor_patch(sim, patch, flat, opacity, cam, edge_depth=edged)
    assert with_edges == patch_auto_threshold(sim, patch, edged, opacity) < 0.55
    pts = sel.anchor_points()
    eye = np.array([0.0, -5.0, 0.0])
    along = (pts - eye) @ np.array([0.0, 1.0, 0.0])  # z-depth: the camera looks along +y
    assert len(pts) and np.allclose(along, 2.5, atol=1e-3)  # on `depth`, not on `edge_depth`'s 3.0
    without = Selection().anchor_patch(sim, patch, flat, opacity, cam)
    assert without == patch_auto_threshold(sim, patch, flat, opacity) > 0.62  # above the slab: no edge holds it


def test_a_patch_covering_most_of_a_small_object_still_finds_it():
    """A 12x12 object (0.9) on a table of similar colour (0.45) that fills the view: the 9x9 patch covers more than
    half of the object, and the few patch pixels on the object's far side of a barrier do not count as seeds. The
    object's plateau (1.8x the patch) is the object, not the patch alone; at 2x the table's plateau won."""
    rng = np.random.default_rng(4)
    h = w = 64
    obj = np.zeros((h, w), bool)
    obj[26:38, 26:38] = True
    sim = np.where(obj, 0.9, 0.45) + rng.normal(0.0, 0.01, (h, w))
    barrier = np.zeros((h, w), bool)
    barrier[:, 26] = True  # a depth edge along the object's left side, under the patch's first column
    seeds = np.zeros((h, w), bool)
    seeds[27:36, 26:35] = True
    a = auto_threshold(sim, seeds, barrier)
    assert a.jump is not None and 0.4 <= a.jump < a.value < 0.88, (a.value, a.jump)
    assert _iou(grow(sim > a.value, seeds, barrier), obj & ~barrier) > 0.95


def test_patch_auto_threshold_accepts_a_fraction_rect_and_big_maps():
    sim = np.full((300, 200), 0.1, np.float32)
    sim[100:200, 50:150] = 0.9
    t = patch_auto_threshold(torch.from_numpy(sim), (0.4, 0.5, 0.5, 0.55))
    assert 0.1 < t < 0.9


def test_depth_edges_mark_the_far_side_of_a_step_and_not_a_grazing_plane():
    h, w, f = 64, 64, 80.0
    cams = Cameras.create(look_at((0.0, -3.0, 1.2), (0.0, 0.0, 0.0))[None], f, f, w / 2, h / 2, w, h)
    o, d, dz = cams.image_rays(0)
    t = -o[:, 2] / d[:, 2]  # the ground plane z = 0, seen at ~22 degrees
    plane = (t * dz).reshape(h, w).numpy()
    assert (plane > 0).all()
    assert not depth_edges(plane).any(), "a plane at a grazing angle has no depth edge"
    step = plane.copy()
    box = np.zeros((h, w), bool)
    box[20:40, 20:44] = True
    step[box] *= 0.9  # a box standing 10% nearer
    e = depth_edges(step)
    ring = np.zeros_like(box)
    ring[19:41, 19:45] = True
    assert e.any() and not (e & box).any(), "only the far side is a barrier"
    assert (e & ~ring).sum() == 0, "edges only next to the box"
    assert e[19, 25] and e[40, 25] and e[30, 19] and e[30, 44]


def test_depth_edges_within_a_patch_are_the_full_maps_edges_there():
    """The patch's anchors read depth edges on the patch's box only: equal to the whole map's there, patches at
    the image's borders and corners included (where a wrapped-around neighbour must not make an edge)."""
    from repaint_nerf.core.select.geometry import depth_edges_within

    rng = np.random.default_rng(3)
    h, w = 48, 64
    depth = np.exp(rng.normal(0.0, 0.08, (h, w))) * 2.0
    depth[10:30, 20:40] *= 0.8  # a box standing nearer: real edges
    depth[0, :] *= 0.5  # the top row far nearer than the bottom one: a wrap-around would see a step there
    opacity = (rng.random((h, w)) > 0.05).astype(np.float32)
    full = depth_edges(depth, opacity)
    assert full.any() and not full.all()
    for y0, y1, x0, x1 in ((0, 6, 0, 9), (40, 48, 55, 64), (8, 32, 18, 42), (0, 48, 30, 31), (20, 21, 0, 64)):
        where = np.zeros((h, w), bool)
        where[y0:y1, x0:x1] = True
        where &= rng.random((h, w)) > 0.3  # scattered, as the patch's pixels on the object are
        got = depth_edges_within(where, depth, opacity)
        np.testing.assert_array_equal(got, full & where)
    assert not depth_edges_within(np.zeros((h, w), bool), depth, opacity).any()


def test_rough_depth_turns_the_2d_geometry_off_and_clean_depth_keeps_it():
    from repaint_nerf.core.select.geometry import DEPTH_EDGE, FULL_PARTS, depth_noise, fit_parts

    h, w, f = 64, 64, 80.0
    cams = Cameras.create(look_at((0.0, -3.0, 1.2), (0.0, 0.0, 0.0))[None], f, f, w / 2, h / 2, w, h)
    o, d, dz = cams.image_rays(0)
    plane = ((-o[:, 2] / d[:, 2]) * dz).reshape(h, w).numpy().astype(np.float64)
    ones = np.ones((h, w), bool)
    assert depth_noise(1.0 / plane, ones) < 1e-6  # inverse depth is affine on a plane
    rng = np.random.default_rng(0)
    for sigma in (0.004, 0.02):  # multiplicative noise: the second difference's sigma is sqrt(6) sigma
        rough = plane * np.exp(rng.normal(0, sigma, plane.shape))
        assert depth_noise(1.0 / rough, ones) == pytest.approx(np.sqrt(6) * sigma, rel=0.15)
    ops = [np.ones((h, w), np.float32)]
    assert fit_parts(FULL_PARTS, [plane], ops) == FULL_PARTS
    quiet = plane * np.exp(rng.normal(0, 0.25 * DEPTH_EDGE / np.sqrt(6), plane.shape))
    assert fit_parts(FULL_PARTS, [quiet], ops) == FULL_PARTS
    rough = plane * np.exp(rng.normal(0, 2.0 * DEPTH_EDGE / np.sqrt(6), plane.shape))
    assert depth_edges(rough, rel=DEPTH_EDGE).mean() > 0.2  # on such depth a quarter of the pixels look like edges
    kept = fit_parts(FULL_PARTS, [rough], ops)
    assert kept.names() == ["cleanup3d"]


def test_fill_holes_keeps_holes_with_a_barrier():
    m = np.zeros((20, 20), bool)
    m[2:18, 2:18] = True
    m[5:8, 5:8] = False  # a printed letter: filled
    m[11:15, 11:15] = False  # the hole of a ring onto the floor: kept
    barrier = np.zeros_like(m)
    barrier[12, 12] = True
    out = fill_holes(m, barrier)
    assert out[5:8, 5:8].all() and not out[11:15, 11:15].any()


def _two_view_scene(eyes=((0.3, -3.0, 1.5), (-1.2, -2.7, 1.4)), size: int = 64):
    """A box of its support's colour just above a ground plane (as a loaf touches its board at one point,
    its whole silhouette is a depth step), seen by cameras at `eyes` (two by default): depth and ids per view."""
    h = w = size
    f = 70.0 * size / 64
    cams = Cameras.create(np.stack([look_at(e, (0.0, 0.0, 0.2)) for e in eyes]), f, f, w / 2, h / 2, w, h)
    depths, ids = [], []
    lo, hi = np.array([-0.3, -0.3, 0.12]), np.array([0.3, 0.3, 0.62])
    for i in range(len(eyes)):
        o, d, dz = cams.image_rays(i)
        o, d = o.numpy().astype(np.float64), d.numpy().astype(np.float64)
        t_ground = np.where(d[:, 2] < 0, -o[:, 2] / np.minimum(d[:, 2], -1e-9), np.inf)
        with np.errstate(divide="ignore", invalid="ignore"):
            t0, t1 = (lo - o) / d, (hi - o) / d
        tmin = np.nanmax(np.minimum(t0, t1), 1)
        tmax = np.nanmin(np.maximum(t0, t1), 1)
        hit_box = (tmax >= tmin) & (tmin > 0)
        t = np.where(hit_box & (tmin < t_ground), tmin, t_ground)
        depths.append((t * dz.numpy()).reshape(h, w).astype(np.float32))
        ids.append(np.where(hit_box & (tmin < t_ground), 2, 1).reshape(h, w))
    return cams, depths, ids


def test_mask_stops_at_a_depth_edge():
    """The support has the object's colour (similarity 0.9 on both): without geometry the mask takes the
    support; with the depth edges and seeded growth it stops at the box's silhouette, in both views
    (the second view is seeded through the first view's surface points)."""
    cams, depths, ids = _two_view_scene()
    gts = [i == 2 for i in ids]
    sims = [np.where(g, 0.95, 0.9).astype(np.float32) for g in gts]
    ops = [np.ones_like(d) for d in depths]
    ys, xs = np.nonzero(gts[0])
    cy, cx = int(np.median(ys)), int(np.median(xs))
    seed = np.zeros_like(gts[0])
    seed[cy - 2:cy + 3, cx - 2:cx + 3] = True
    assert gts[0][seed].all()
    plain = geometric_masks(sims, depths, ops, cams, [(0, seed)], 0.5, GeometryParts.none())
    assert all(_iou(m, g) < 0.3 for m, g in zip(plain, gts))
    shaped = geometric_masks(sims, depths, ops, cams, [(0, seed)], 0.5, GeometryParts())
    for m, g in zip(shaped, gts):
        assert _iou(m, g) > 0.9, _iou(m, g)
    no_edges = geometric_masks(sims, depths, ops, cams, [(0, seed)], 0.5, GeometryParts(edges=False))
    assert _iou(no_edges[0], gts[0]) < 0.3  # the edges are what stops it


def _blocks(depth: np.ndarray, seed: int, step: float, share: float) -> np.ndarray:
    """`depth` with 4-px blocks, `share` of them offset by +-`step` (relative), and fine noise."""
    rng = np.random.default_rng(seed)
    h, w = depth.shape
    grid = (h // 4 + 1, w // 4 + 1)
    off = np.where(rng.random(grid) < share, rng.choice([-step, step], grid), 0.0)
    blocks = np.kron(off, np.ones((4, 4)))[:h, :w]
    return (depth * np.exp(blocks + rng.normal(0.0, 0.0015, (h, w)))).astype(np.float32)


def _bumpy(depth: np.ndarray, seed: int) -> np.ndarray:
    """`depth` with a trained sparse capture's bumps (kermit's): half its 4-px blocks offset by +-4%. The
    median noise (depth_noise, ~0.6%) stays under DEPTH_EDGE while a quarter of the pixels step by more than it."""
    return _blocks(depth, seed, 0.04, 0.5)


def test_bumpy_trained_depth_does_not_wall_the_object_into_specks(monkeypatch):
    """A rough field (a few photos of a real room) has bumps just under DEPTH_EDGE everywhere: at that fixed level
    they wall the patch's region into a speck (kermit: 1.3% of the pixels). Each view's level rises until its
    edges are outlines (`edge_level`), and the box's silhouette, a real step, still stops the mask."""
    import repaint_nerf.core.select.geometry as geometry
    from repaint_nerf.core.select.geometry import DEPTH_EDGE, depth_noise, edge_budget, edge_level, inverse_depth

    cams, depths, ids = _two_view_scene(size=128)
    depths = [_bumpy(d, k) for k, d in enumerate(depths)]
    ones = np.ones(depths[0].shape, bool)
    for d in depths:
        assert depth_noise(*inverse_depth(d)) < DEPTH_EDGE  # not rough by the noise: the 2D parts stay on
        assert depth_edges(d, rel=DEPTH_EDGE)[ones].mean() > 2 * edge_budget(d.size)
        assert edge_level(d) > DEPTH_EDGE
    gts = [i == 2 for i in ids]
    sims = [np.where(g, 0.95, 0.9).astype(np.float32) for g in gts]
    ops = [np.ones_like(d) for d in depths]
    ys, xs = np.nonzero(gts[0])
    seed = np.zeros_like(gts[0])
    seed[int(np.median(ys)) - 2:int(np.median(ys)) + 3, int(np.median(xs)) - 2:int(np.median(xs)) + 3] = True
    shaped = geometric_masks(sims, depths, ops, cams, [(0, seed)], 0.5, GeometryParts())
    for m, g in zip(shaped, gts):
        assert _iou(m, g) > 0.95, _iou(m, g)
    monkeypatch.setattr(geometry, "EDGE_LINES", 1e9)  # no budget: the fixed level DEPTH_EDGE walls it in
    walled = geometric_masks(sims, depths, ops, cams, [(0, seed)], 0.5, GeometryParts())
    assert all(_iou(m, g) < 0.7 for m, g in zip(walled, gts)), [_iou(m, g) for m, g in zip(walled, gts)]


def test_edge_level_is_the_fixed_level_on_clean_depth_and_fits_the_budget_on_rough_depth():
    """edge_level against a plain count: DEPTH_EDGE where the edges are few; on rough depth, the least level at
    which at most `edge_budget` of the surface pixels are edges (EDGE_LINES lines' worth: a smaller share of a larger
    view). A map over NOISE_LINES px is read at that scale: its level is that of its every k-th pixel."""
    from repaint_nerf.core.select.geometry import DEPTH_EDGE, NOISE_LINES, edge_budget, edge_level

    cams, depths, _ = _two_view_scene()
    assert edge_level(depths[0]) == DEPTH_EDGE
    rng = np.random.default_rng(5)
    for h, w in ((64, 64), (97, 131), (600, 340)):  # the last read at every 3rd pixel
        z = (3.0 * np.exp(rng.normal(0.0, 0.02, (h, w)))).astype(np.float32)
        o = np.where(rng.random((h, w)) < 0.03, 0.0, 1.0).astype(np.float32)
        level = edge_level(z, o)
        assert level > DEPTH_EDGE
        k = int(np.ceil(max(h, w) / NOISE_LINES))
        zk, ok = z[::k, ::k], o[::k, ::k]
        surface = ((ok > 0.5) & (zk > 0))[1:-1, 1:-1]
        budget = edge_budget(surface.mean() * h * w / k ** 2)

        def share(rel: float) -> float:  # edge pixels among the surface pixels off the image's border
            return float(_depth_edges_reference(zk, ok, rel)[1:-1, 1:-1][surface].mean())
        assert share(level) <= budget + 0.002  # float32 against the float64 reference: a pixel or two
        assert share(level * 0.98) > budget


def test_a_larger_render_of_the_same_bumps_keeps_its_level():
    """The same rough surface rendered at 2.5x (bilinear: each step spread over more pixels, as a field renders it)
    still reads as rough, so a patch in the editor's large view is not walled in where the 256-px maps of `select`
    are not (kermit's view 0: 3.3x DEPTH_EDGE read pixel to pixel at 878 px against 4.2-10x). Read pixel to pixel,
    this large map's level was 2.2x, under ROUGH_LEVEL; at the 256-px scale it is 4.4x against the small map's 8.1x."""
    import cv2
    from repaint_nerf.core.select.geometry import DEPTH_EDGE, ROUGH_LEVEL, edge_level

    small = _bumpy(np.full((200, 256), 3.0, np.float32), 3)
    large = cv2.resize(small, (640, 500), interpolation=cv2.INTER_LINEAR)
    a, b = edge_level(small), edge_level(large)
    assert a >= ROUGH_LEVEL * DEPTH_EDGE and b >= ROUGH_LEVEL * DEPTH_EDGE
    assert 0.5 < b / a < 2.0, (a, b)


def test_a_cluttered_views_many_weak_steps_keep_the_fixed_level(monkeypatch):
    """Many small steps (1.2%, every 4-px block: a cluttered scene's objects side by side) are true edges: their
    budget level is under ROUGH_LEVEL x DEPTH_EDGE, and the level stays DEPTH_EDGE (raising it cost the toys preset
    0.17 IoU). Strong steps (4%) of the same pattern are a rough field's bumps, and the level rises."""
    import repaint_nerf.core.select.geometry as geometry
    from repaint_nerf.core.select.geometry import DEPTH_EDGE, ROUGH_LEVEL, edge_budget, edge_level

    flat = np.full((128, 128), 3.0, np.float32)
    weak, strong = _blocks(flat, 1, 0.012, 1.0), _blocks(flat, 1, 0.04, 1.0)
    for d in (weak, strong):
        assert depth_edges(d, rel=DEPTH_EDGE).mean() > 2 * edge_budget(d.size)
    assert edge_level(weak) == DEPTH_EDGE
    assert edge_level(strong) >= ROUGH_LEVEL * DEPTH_EDGE
    monkeypatch.setattr(geometry, "ROUGH_LEVEL", 0.0)  # ungated, the weak steps' level would rise too
    assert DEPTH_EDGE < edge_level(weak) < ROUGH_LEVEL * DEPTH_EDGE


@pytest.fixture(scope="module")
def bread_views(tmp_path_factory):
    """The bread preset (a loaf on a board of its colour, on a wooden table) in 8 views at 96 px: default-
    teacher similarity to the automatic patch, ground-truth depth, the loaf's masks and the cameras."""
    from repaint_nerf.core.bench.teacher import place_patch
    from repaint_nerf.core.scene.loaders.detect import load_scene
    from repaint_nerf.core.select.query import Patch
    from repaint_nerf.core.select.selection import Selection
    from repaint_nerf.core.synth.generate import make_scene
    from repaint_nerf.core.teachers.feature_default import DefaultFeatureTeacher

    import cv2

    root = make_scene("bread", tmp_path_factory.mktemp("bread8"), size=96, views=8, seed=0, test_views=1)
    scene = load_scene(root, splits=("train",))
    obj = json.loads((root / "gt" / "objects.json").read_text())["edited_object_id"]
    stems = [Path(n).stem for n in scene.train.names]
    gts = [cv2.imread(str(root / "gt" / "train" / f"{s}_mask.png"), cv2.IMREAD_UNCHANGED) == obj for s in stems]
    depths = [np.load(root / "gt" / "train" / f"{s}_depth.npy").astype(np.float32) for s in stems]
    teacher = DefaultFeatureTeacher()
    feats = [torch.from_numpy(teacher(im) * (d > 0)[..., None]) for im, d in zip(scene.train.images, depths)]
    v, (y0, y1, x0, x1) = place_patch(gts)
    p = Patch(v, x0, y0, x1, y1)
    sel = Selection()
    sel.add_patch(feats[v], p)
    sims = [sel.similarity(f).numpy() for f in feats]
    return sims, depths, gts, scene.train.cameras, p  # world units, as the ground-truth depth


def test_masks_across_views_stop_at_the_loaf_on_a_board_of_its_colour(bread_views):
    """Across 8 views, at the patch's automatic threshold: the board and the table pass the threshold in
    every view, and the geometry (seeds carried between views from the masks' interiors, depth edges,
    creases, the views' vote) keeps the loaf alone."""
    sims, depths, gts, cams, p = bread_views
    ops = [(d > 0).astype(np.float32) for d in depths]
    t = patch_auto_threshold(sims[p.view], p, depths[p.view], ops[p.view])
    seed = patch_pixels(sims[p.view].shape, p)

    def iou_all(parts):
        ms = geometric_masks(sims, depths, ops, cams, [(p.view, seed)], t, parts)
        return sum(int((m & g).sum()) for m, g in zip(ms, gts)) / sum(int((m | g).sum()) for m, g in zip(ms, gts))

    assert iou_all(GeometryParts.none()) < 0.5
    assert iou_all(GeometryParts(cleanup3d=False)) > 0.9


def test_creases_mark_a_concave_fold_and_not_a_convex_one_or_a_plane():
    """Against the written rule: a V-shaped valley (two planes meeting at 90 degrees, concave towards the
    camera) has crease pixels along its fold only; the same fold turned into a ridge, and a tilted plane,
    have none."""
    from repaint_nerf.core.select.geometry import creases

    h = w = 40
    x = np.arange(w, dtype=np.float64)[None, :].repeat(h, 0) + 0.5 - w / 2
    f = 40.0
    # two planes through the line x = 0 at depth 4: inverse depth (1 - a |x| / f) / 4 is affine on each side
    for sign, expect in ((-1, True), (+1, False)):
        a = 1.0 * sign  # a valley (the sides nearer than the fold) or a ridge (the fold nearest)
        z = 4.0 / (1.0 - a * np.abs(x) / f)
        z = z.astype(np.float32)
        c = creases(z, np.ones((h, w), bool), (f, f, w / 2, h / 2))
        fold = np.abs(x) < 3
        if expect:
            assert c[5:-5][fold[5:-5]].mean() > 0.5 and not c[5:-5][~fold[5:-5]].any()
        else:
            assert not c.any()
    plane = (4.0 / (1.0 - 0.5 * x / f)).astype(np.float32)
    assert not creases(plane, np.ones((h, w), bool), (f, f, w / 2, h / 2)).any()


def test_views_outvote_a_leak_seen_by_one_view():
    """View 0's mask has the box and a patch of ground; views 1 and 2 see that ground outside their masks,
    so it is dropped; the box, inside the other views' masks, stays, and with one view there is no vote."""
    from repaint_nerf.core.select.geometry import vote

    cams, depths, ids = _two_view_scene(eyes=((0.3, -3.0, 1.5), (-1.2, -2.7, 1.4), (1.0, -2.8, 1.6)))
    box = [i == 2 for i in ids]
    surface = [np.ones(d.shape, bool) for d in depths]
    leak = np.zeros_like(box[0])
    ys, xs = np.nonzero(box[0])
    leak[ys.max() + 3:ys.max() + 8, xs.min():xs.max()] = True  # ground in front of the box
    assert not (leak & box[0]).any() and leak.sum() > 20
    out = vote([box[0] | leak, box[1], box[2]], depths, surface, cams)
    assert not (out[0] & leak).any()
    assert (out[0] == box[0]).mean() > 0.99 and (out[1] == box[1]).all()
    alone = vote([box[0] | leak, np.zeros_like(box[1]), np.zeros_like(box[2])], depths, surface, cams)
    assert (alone[0] == (box[0] | leak)).all()


def test_one_view_that_has_not_grown_a_part_does_not_outvote_a_view_that_has():
    """The box's lower half is in views 0 and 1's masks but not yet in view 2's (its growth stopped at a groove):
    one view against one for keeps it in view 0 (a tie used to drop it); two views against none drop it."""
    from repaint_nerf.core.select.geometry import vote

    cams, depths, ids = _two_view_scene(eyes=((0.3, -3.0, 1.5), (-1.2, -2.7, 1.4), (1.0, -2.8, 1.6)))
    box = [i == 2 for i in ids]
    surface = [np.ones(d.shape, bool) for d in depths]
    ys, _ = np.nonzero(box[2])
    upper2 = box[2].copy()
    upper2[(ys.min() + ys.max()) // 2:] = False
    lower0 = box[0].copy()
    ys0, _ = np.nonzero(box[0])
    lower0[:(ys0.min() + ys0.max()) // 2 + 2] = False  # the lower half in view 0, clear of its middle row
    assert lower0.sum() > 20
    kept = vote([box[0], box[1], upper2], depths, surface, cams)
    assert (kept[0] & lower0).sum() > 0.9 * lower0.sum()
    upper1 = box[1].copy()
    ys1, _ = np.nonzero(box[1])
    upper1[(ys1.min() + ys1.max()) // 2:] = False
    dropped = vote([box[0], upper1, upper2], depths, surface, cams)
    assert (dropped[0] & lower0).sum() < 0.2 * lower0.sum()


def _plain_vote(masks, depths, surface, cams, tol):
    """The vote one view pair at a time (the reference the batched `vote` is checked against)."""
    from repaint_nerf.core.select.geometry import VOTE_MARGIN, surface_points

    out = []
    for i, m in enumerate(masks):
        pts = torch.from_numpy(surface_points(m, depths[i], cams, i))
        pro, against = np.zeros(len(pts), int), np.zeros(len(pts), int)
        for j, mj in enumerate(masks):
            if j == i or not mj.any() or not len(pts):
                continue
            uv, z = cams.project(pts, j)
            h, w = depths[j].shape
            u, v = np.floor(uv[:, 0].numpy()).astype(int), np.floor(uv[:, 1].numpy()).astype(int)
            inside = (z.numpy() > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
            u, v = np.where(inside, u, 0), np.where(inside, v, 0)
            seen = inside & surface[j][v, u] & (np.abs(depths[j][v, u] - z.numpy()) < tol * z.numpy())
            pro += seen & mj[v, u]
            against += seen & ~mj[v, u]
        keep = m.copy().reshape(-1)
        keep[np.flatnonzero(m)[against > VOTE_MARGIN * pro]] = False
        out.append(keep.reshape(m.shape))
    return out


def test_batched_projection_and_vote_match_one_view_at_a_time_across_view_sizes(monkeypatch):
    """Seeds and votes project every point into all views at once (a padded stack of their depth maps, in chunks);
    with views of different sizes and chunks of a few points they give what one view at a time gives."""
    from repaint_nerf.core.select import geometry
    from repaint_nerf.core.select.geometry import SEED_DEPTH_TOL, project_seeds, surface_points, vote

    cams, depths, ids = _two_view_scene(eyes=((0.3, -3.0, 1.5), (-1.2, -2.7, 1.4), (1.0, -2.8, 1.6)))
    depths[1] = depths[1][:50, :40].copy()  # view 1 cropped: its pixels keep their rays (same cx, cy)
    ids[1] = ids[1][:50, :40]
    cams.width[1], cams.height[1] = 40, 50
    surface = [np.ones(d.shape, bool) for d in depths]
    surface[2][:, :20] = False
    box = [i == 2 for i in ids]
    leak = np.zeros_like(box[0])
    ys, xs = np.nonzero(box[0])
    leak[ys.max() + 3:ys.max() + 8, xs.min():xs.max()] = True
    masks = [box[0] | leak, box[1], box[2]]
    monkeypatch.setattr(geometry, "PROJECT_CHUNK", 7)  # a few points per chunk, split unevenly
    for got, want in zip(vote(masks, depths, surface, cams), _plain_vote(masks, depths, surface, cams,
                                                                           SEED_DEPTH_TOL)):
        assert got.shape == want.shape and (got == want).all()
    pts = surface_points(box[0], depths[0], cams, 0)
    seeds = project_seeds(pts, depths, cams)
    for j, d in enumerate(depths):
        uv, z = cams.project(torch.from_numpy(pts), j)
        seen, u, v = geometry.seen_pixels(uv.numpy(), z.numpy(), d)
        want = np.zeros(d.shape, bool)
        want[v[seen], u[seen]] = True
        assert seeds[j].shape == d.shape and (seeds[j] == want).all() and want.any()


def _four_views_view0_leaking(monkeypatch):
    """The box-above-ground scene seen by four cameras, the box's similarity a little above the ground's, with
    view 0's depth edges and creases switched off (as a trained field's noisy depth can lose them): (cameras,
    depths, opacities, box masks, similarity maps)."""
    import repaint_nerf.core.select.geometry as geometry

    eyes = ((0.3, -3.0, 1.5), (-1.2, -2.7, 1.4), (1.0, -2.8, 1.6), (-0.4, -3.1, 1.8))
    cams, depths, ids = _two_view_scene(eyes=eyes)
    box = [i == 2 for i in ids]
    sims = [np.where(b, 0.95, 0.9).astype(np.float32) for b in box]
    real = geometry.view_barriers

    def view0_without_edges(depths, surface, cameras, parts):
        barriers, bands = real(depths, surface, cameras, parts)
        barriers[0] = ~surface[0]
        bands[0] = None if bands[0] is None else np.zeros_like(bands[0])
        return barriers, bands

    monkeypatch.setattr(geometry, "view_barriers", view0_without_edges)
    return cams, depths, [np.ones_like(d) for d in depths], box, sims


def _centre_pixels(mask: np.ndarray) -> np.ndarray:
    """A 3x3 patch of pixels at the median pixel of `mask`, inside it."""
    ys, xs = np.nonzero(mask)
    cy, cx = int(np.median(ys)), int(np.median(xs))
    px = np.zeros_like(mask)
    px[cy - 1:cy + 2, cx - 1:cx + 2] = True
    return px & mask


def test_one_seeded_views_leak_does_not_spread_to_the_other_views(monkeypatch):
    """A free-view patch seeds every view through its surface points; in view 0 the depth edges fail (as a trained
    field's noisy depth can), so its mask takes the ground, which has the box's colour. The views vote on the
    first masks before they seed each other: the ground stays out of the other views (view 0 keeps the ground that
    only it sees: no view votes on that)."""
    cams, depths, ops, box, sims = _four_views_view0_leaking(monkeypatch)
    seeds = [(i, _centre_pixels(b)) for i, b in enumerate(box)]
    first = geometric_masks(sims, depths, ops, cams, seeds, 0.5, GeometryParts(), rounds=0)
    assert _iou(first[0], box[0]) < 0.3  # view 0 alone has leaked
    out = geometric_masks(sims, depths, ops, cams, seeds, 0.5, GeometryParts())
    assert all(_iou(m, b) > 0.9 for m, b in zip(out[1:], box[1:])), [_iou(m, b) for m, b in zip(out, box)]


def test_a_training_view_patch_seeds_the_views_that_see_it_so_its_views_leak_is_outvoted(monkeypatch):
    """A patch drawn in training view 0, whose depth edges fail there (as at a trained lemon field's low tray):
    seeded by its own pixels alone, view 0's mask takes the ground and its surface points grow the ground in every
    view. `patch_seeds` also seeds the views that see the patch's surface points, and the views vote on those
    first masks, so the ground stays out of the other views."""
    from repaint_nerf.core.select.masks import ViewMaps, patch_seeds

    cams, depths, ops, box, sims = _four_views_view0_leaking(monkeypatch)
    maps = [ViewMaps(torch.zeros(*d.shape, 4), torch.from_numpy(d), torch.from_numpy(o)) for d, o in zip(depths, ops)]
    px = _centre_pixels(box[0])
    own = patch_seeds(0, px, maps, cams)  # no similarity given: the patch's own pixels only
    assert [v for v, _ in own] == [0]
    alone = geometric_masks(sims, depths, ops, cams, own, 0.5, GeometryParts())
    assert max(_iou(m, b) for m, b in zip(alone[1:], box[1:])) < 0.5  # the leak spread to every view
    seeds = patch_seeds(0, px, maps, cams, [torch.from_numpy(s) for s in sims], 0.5)
    assert sorted(v for v, _ in seeds) == [0, 1, 2, 3]
    assert all(int((p & ~box[v]).sum()) == 0 for v, p in seeds)  # on the box in every view
    out = geometric_masks(sims, depths, ops, cams, seeds, 0.5, GeometryParts())
    assert all(_iou(m, b) > 0.9 for m, b in zip(out[1:], box[1:])), [_iou(m, b) for m, b in zip(out, box)]


@pytest.fixture(scope="module")
def teacher_views(tmp_path_factory):
    """Per preset: default-teacher similarity to the auto patch, ground-truth depth and object mask in the
    patch's view (the field learns these features; its depth stands in for the ground truth)."""
    from repaint_nerf.core.bench.teacher import place_patch
    from repaint_nerf.core.scene.loaders.detect import load_scene
    from repaint_nerf.core.select.query import Patch
    from repaint_nerf.core.select.selection import Selection
    from repaint_nerf.core.synth.generate import make_scene
    from repaint_nerf.core.teachers.feature_default import DefaultFeatureTeacher

    import cv2

    out = {}
    teacher = DefaultFeatureTeacher()
    for name in ("demo", "bread"):
        root = make_scene(name, tmp_path_factory.mktemp(name), size=96, views=3, seed=0, test_views=1)
        scene = load_scene(root, splits=("train",))
        obj = json.loads((root / "gt" / "objects.json").read_text())["edited_object_id"]
        gts = [cv2.imread(str(root / "gt" / "train" / f"r_{i}_mask.png"), cv2.IMREAD_UNCHANGED) == obj
               for i in range(3)]
        v, (y0, y1, x0, x1) = place_patch(gts)
        depth = np.load(root / "gt" / "train" / f"r_{v}_depth.npy")
        feats = torch.from_numpy(teacher(scene.train.images[v]) * (depth > 0)[..., None])
        sel = Selection()
        p = Patch(v, x0, y0, x1, y1)
        sel.add_patch(feats, p)
        out[name] = (sel.similarity(feats).numpy(), p, depth, gts[v])
    return out


def test_auto_threshold_on_a_preset_with_two_clear_modes(teacher_views):
    sim, p, depth, gt = teacher_views["demo"]
    t = patch_auto_threshold(sim, p, depth, (depth > 0).astype(np.float32))
    assert _iou((sim > t) & (depth > 0), gt) > 0.9


def test_auto_threshold_and_depth_edges_on_a_loaf_on_a_board_of_its_colour(teacher_views):
    sim, p, depth, gt = teacher_views["bread"]
    seeds = patch_pixels(sim.shape, p)
    barrier = depth_edges(depth)
    t = patch_auto_threshold(sim, p, depth, (depth > 0).astype(np.float32))
    assert _iou((sim > 0.5) & (depth > 0), gt) < 0.5, "the board and the table look like the loaf"
    assert _iou(fill_holes(grow(sim > t, seeds, barrier), barrier), gt) > 0.9


def test_selection_saves_its_automatic_threshold(tmp_path):
    from repaint_nerf.core.select.query import Patch
    from repaint_nerf.core.select.selection import Selection
    from repaint_nerf.core.workspace.workspace import Workspace

    ws = Workspace.create(tmp_path / "ws")
    feats = torch.zeros(16, 16, 4)
    feats[..., 0] = 1.0
    feats[4:12, 4:12] = torch.tensor([0.0, 1.0, 0.0, 0.0])
    sel = Selection()
    sel.add_patch(feats, Patch(0, 6, 6, 9, 9))
    sel.auto_threshold = patch_auto_threshold(sel.similarity(feats), Patch(0, 6, 6, 9, 9))
    sel.threshold = sel.auto_threshold
    sel.save(ws)
    back = Selection.load(ws)
    assert back.auto_threshold == pytest.approx(sel.auto_threshold) and back.threshold == pytest.approx(sel.threshold)
    assert 0.0 < back.auto_threshold < 1.0
    assert (back.mask(feats) == (feats[..., 1] > 0)).all()


def test_text_query_threshold_splits_two_modes_and_ignores_empty_space():
    """A text query has no patch: its threshold splits the similarities of every view's surface pixels
    (an object near 0.8 among clutter near 0.3: between them), ignores pixels without a surface, and is
    0.5 on a constant map."""
    from repaint_nerf.core.select.autothreshold import FALLBACK, text_auto_threshold

    rng = np.random.default_rng(0)
    sims, surf = [], []
    for _ in range(3):
        s = rng.normal(0.3, 0.05, (32, 32))
        s[8:16, 8:16] = rng.normal(0.8, 0.03, (8, 8))
        s[:, :4] = 0.99  # empty space (no surface) that happens to score high
        m = np.ones((32, 32), bool)
        m[:, :4] = False
        sims.append(s.astype(np.float32))
        surf.append(m)
    t = text_auto_threshold(sims, surf)
    assert 0.45 < t < 0.7
    assert all(((s > t) & m).sum() == 64 for s, m in zip(sims, surf))
    assert text_auto_threshold([np.full((8, 8), 0.7, np.float32)]) == FALLBACK
    # a barely trained field: every pixel within a few float32 steps of 1 (numpy's float32 bins raised here)
    near_one = (1.0 - rng.integers(0, 40, (16, 16)) * np.float32(6e-8)).astype(np.float32)
    assert 0.99 <= text_auto_threshold([near_one]) <= 1.0


def test_attach_gives_border_pixels_to_the_surface_whose_depth_they_share():
    """A disc at depth 2 before a plane at depth 3, its silhouette rendered as two blended one-pixel rings: the
    inner ring (z 2.2, nearer the disc) joins the disc's mask, the outer ring (z 2.8, nearer the plane) and the
    plane stay out; a ring pixel below the threshold is not a candidate and stays out; with no surface behind
    (background), the blended ring joins."""
    import cv2

    from repaint_nerf.core.select.geometry import attach

    h = w = 48
    yy, xx = np.mgrid[0:h, 0:w]
    disc = np.hypot(yy - 24 + 0.5, xx - 24 + 0.5) < 10

    def outer_ring(m, kernel):
        return (cv2.dilate(m.astype(np.uint8), np.array(kernel, np.uint8)) > 0) & ~m

    ring1 = outer_ring(disc, [[0, 1, 0], [1, 1, 1], [0, 1, 0]])  # the pixels straddling the silhouette
    ring2 = outer_ring(disc | ring1, np.ones((3, 3)))
    depth = np.where(disc, 2.0, np.where(ring1, 2.2, np.where(ring2, 2.8, 3.0))).astype(np.float32)
    opacity = np.ones((h, w), np.float32)
    cand = np.ones((h, w), bool)
    cand[24, 30:40] = False  # a few ring pixels the similarity does not pick
    out = attach(disc, cand, depth, opacity)
    assert (out == (disc | (ring1 & cand))).all()
    # the same rings before empty space: the blend pixels join, nothing else
    opacity_bg = np.where(disc | ring1, 1.0, 0.0).astype(np.float32)
    assert (attach(disc, np.ones((h, w), bool), depth, opacity_bg) == (disc | ring1)).all()
    # nothing to attach: the mask comes back as it was
    assert (attach(disc, disc, depth, opacity) == disc).all()


def test_region_areas_equal_the_plain_labelling_on_random_maps():
    """The bounding-box form labels less but must give the plain per-threshold labelling's areas exactly:
    smooth random maps of many sizes, one or two seed patches, with and without barrier pixels."""
    import cv2

    from repaint_nerf.core.select.autothreshold import region_areas, region_areas_reference

    rng = np.random.default_rng(0)
    for trial in range(40):
        h, w = (int(v) for v in rng.integers(3, 100, 2))
        s = cv2.GaussianBlur(rng.random((h, w)).astype(np.float32), (0, 0), float(rng.uniform(0.5, 4)))
        s = (s - s.min()) / (s.max() - s.min() + 1e-9)
        seeds = np.zeros((h, w), bool)
        y, x = int(rng.integers(0, h)), int(rng.integers(0, w))
        seeds[y:y + int(rng.integers(1, 8)), x:x + int(rng.integers(1, 8))] = True
        if trial % 3 == 0:
            seeds[int(rng.integers(0, h)), int(rng.integers(0, w))] = True
        barrier = rng.random((h, w)) < rng.uniform(0, 0.3) if trial % 2 else None
        np.testing.assert_array_equal(region_areas(s, seeds, barrier), region_areas_reference(s, seeds, barrier))
    empty = np.zeros((8, 8), bool)
    assert not region_areas(np.ones((8, 8)), empty).any()


def test_a_walled_object_of_two_colours_keeps_both_under_the_views_floor():
    """A free view walls a printed can in with depth edges (its patch's colour fades 0.98 -> 0.55, its other
    colour 0.42); the room around it is bright (0.8) and dim (0.45), so the view's split of similarities lies above
    the can's second colour. The floor stops below the top of the walled plateau: both colours stay (the
    floor alone kept only the patch's colour)."""
    from repaint_nerf.core.select.autothreshold import patch_auto_threshold_px, view_split, walled_top

    rng = np.random.default_rng(5)
    h = w = 96
    yy, xx = np.mgrid[:h, :w]
    can = _disc(h, w, 48, 48, 18)
    printed = can & (xx < 52)  # the patch's colour, a gradient
    sim = np.where(yy < 70, 0.8, 0.45) + rng.normal(0.0, 0.01, (h, w))
    sim[can] = 0.42
    sim[printed] = np.linspace(0.98, 0.55, w)[xx[printed]]
    depth = np.where(can, 2.0, 4.0).astype(np.float32)
    opacity = np.ones((h, w), np.float32)
    seeds = patch_pixels((h, w), (0.36, 0.45, 0.46, 0.55))
    assert view_split(sim) > 0.45  # the floor alone cuts the can's second colour
    a = patch_auto_threshold_px(sim, seeds, depth, opacity)
    assert a.jump is None and walled_top(a.thresholds, a.areas, int(seeds.sum())) is not None
    assert a.value < 0.42, a.value
    assert _iou(grow(sim > a.value, seeds, depth_edges(depth, opacity)), can) > 0.95


def test_walled_top_is_none_without_a_plateau_from_the_lowest_threshold():
    from repaint_nerf.core.select.autothreshold import GRID, walled_top

    # flat (within the +-0.02 window) to 0.47, less WALL_MARGIN steps
    assert walled_top(GRID, np.where(GRID < 0.5, 800, 300), 100) == pytest.approx(0.45)
    assert walled_top(GRID, np.maximum(8000 * np.exp(-10 * GRID), 300), 100) is None  # shrinking from 0.02
    # flat at first, but the region is most of the view's surface: nothing walls it in
    assert walled_top(GRID, np.where(GRID < 0.5, 800, 300), 100, room=1000) is None
    assert walled_top(GRID, np.where(GRID < 0.5, 800, 300), 100, room=4000) == pytest.approx(0.45)


def test_the_views_vote_only_where_their_region_leaks():
    """views_threshold: the free view's own value and the leaking training views' take the median; a walled
    view (no jump) does not vote, and with no leak the free view's value stands."""
    from repaint_nerf.core.select.autothreshold import AutoThreshold, views_threshold

    def view(value, jump):
        return AutoThreshold(value, np.zeros(0), np.zeros(0), jump)

    assert views_threshold(0.46, [view(0.75, 0.4), view(0.78, 0.5), view(0.2, None), view(0.3, None)]) == 0.75
    assert views_threshold(0.42, [view(0.33, 0.2), view(0.73, 0.18), view(0.6, None)]) == 0.42
    assert views_threshold(0.42, [view(0.9, None)]) == 0.42
    assert views_threshold(0.42, []) == 0.42


def test_one_leaking_view_among_walled_ones_does_not_vote():
    """A free-view patch on a fox: one of eight training views leaked at 0.80, the rest were walled in; its vote
    alone moved 0.55 to 0.68. Two leaking views, or one of two, still vote."""
    from repaint_nerf.core.select.autothreshold import AutoThreshold, views_threshold

    def view(value, jump):
        return AutoThreshold(value, np.zeros(0), np.zeros(0), jump)

    walled = [view(v, None) for v in (0.54, 0.55, 0.57, 0.58, 0.59, 0.56, 0.57)]
    assert views_threshold(0.551, walled + [view(0.80, 0.68)]) == 0.551
    assert views_threshold(0.551, walled + [view(0.80, 0.68), view(0.76, 0.6)]) == pytest.approx(0.76)
    assert views_threshold(0.551, [view(0.57, None), view(0.80, 0.68)]) == pytest.approx(0.6755)
    assert views_threshold(0.551, [view(0.80, 0.68)]) == pytest.approx(0.6755)


def test_a_training_view_patch_that_leaks_nowhere_takes_the_walled_views_median():
    """walled_views_threshold: a training-view patch whose own view shows no leak takes the median of its value
    and every other view's where none of them leaks either; one leaking view leaves its own value standing."""
    from repaint_nerf.core.select.autothreshold import AutoThreshold, walled_views_threshold

    def view(value, jump):
        return AutoThreshold(value, np.zeros(0), np.zeros(0), jump)

    walled = [view(0.48, None), view(0.45, None), view(0.47, None), view(0.62, None)]
    assert walled_views_threshold(0.64, walled) == pytest.approx(0.48)
    assert walled_views_threshold(0.64, walled + [view(0.96, 0.3)]) == 0.64
    assert walled_views_threshold(0.64, []) == 0.64


def test_anchor_views_are_the_views_that_frame_the_points_best():
    """geometry.anchor_views: views with the points behind or outside the image are left out; of the rest, the
    ones that see them nearest their centre come first, at most `limit`."""
    from repaint_nerf.core.select.geometry import anchor_views

    target = np.array([0.0, 0.0, 0.0])
    eyes = [(0, -4, 0), (0.0, -4, 0), (4, 0, 0), (0, 4, 0), (0, -4, 0)]
    looks = [(0, 0, 0), (1.2, 0, 0), (0, 0, 0), (0, 8, 0), (6, 0, 0)]  # 3 looks away, 4 past the points
    c2w = np.stack([look_at(e, t) for e, t in zip(eyes, looks)])
    cams = Cameras.create(c2w, 40.0, 40.0, 32.0, 32.0, 64, 64)
    pts = target + np.random.default_rng(0).normal(0.0, 0.05, (50, 3))
    best = anchor_views(pts, cams, 8)
    assert sorted(best[:2]) == [0, 2] and best[2:] == [1]  # 0 and 2 frame the points in their centre, 1 off it
    assert anchor_views(pts, cams, 2) == best[:2]
    assert anchor_views(np.zeros((0, 3)), cams, 8) == []


def _walled_pair(band: float, neighbour: bool):
    """A free view (96x96) whose depth edges wall in a region: a can whose two red ends (0.85) a label band of
    similarity `band` cuts apart, or (with `neighbour`) one red block touching a neighbour of similarity `band`
    with no depth edge between them. The walled region is 1.87x the upper part, as measured on the occluded
    preset (under the jump that would read as a leak). The room around is 0.1. Returns (similarity, seeds, depth, the
    object's pixels)."""
    rng = np.random.default_rng(7)
    h = w = 96
    yy, xx = np.mgrid[:h, :w]
    walled = (xx >= 30) & (xx < 66) & (yy >= 14) & (yy < 70)
    sim = 0.1 + rng.normal(0.0, 0.01, (h, w))
    sim[walled] = 0.85 + rng.normal(0.0, 0.01, int(walled.sum()))
    if neighbour:
        other = walled & (yy >= 44)  # the lower part is another object of another colour
        obj = walled & ~other
    else:
        other = walled & (yy >= 44) & (yy < 54)  # the label, between the can's ends
        obj = walled
    sim[other] = band + rng.normal(0.0, 0.01, int(other.sum()))
    depth = np.where(walled, 2.0, 4.0).astype(np.float32)
    seeds = np.zeros((h, w), bool)
    seeds[20:28, 40:56] = True
    return sim.astype(np.float32), seeds, depth, obj


def test_a_band_of_lower_similarity_does_not_cut_the_object():
    """whole_object: the upper plateau keeps one red end of the can (the longer one); the label band's plateau
    below it joins the other end, whose pixels are as like the patch as the kept ones, so the whole can is
    chosen. A neighbour of the same lower similarity holds no such pixels: the red block alone stays."""
    from repaint_nerf.core.select.autothreshold import GRID, choose_threshold, patch_auto_threshold_px, region_areas

    sim, seeds, depth, can = _walled_pair(0.25, neighbour=False)
    opacity = np.ones(sim.shape, np.float32)
    barrier = depth_edges(depth, opacity)
    areas = region_areas(sim, seeds, barrier)
    assert choose_threshold(GRID, areas, int(seeds.sum()))[0] > 0.3  # the curve alone keeps one end
    a = patch_auto_threshold_px(sim, seeds, depth, opacity)
    assert a.value < 0.25, a.value
    assert _iou(grow(sim > a.value, seeds, barrier), can) > 0.95

    sim, seeds, depth, block = _walled_pair(0.25, neighbour=True)
    a = patch_auto_threshold_px(sim, seeds, depth, opacity)
    assert a.value > 0.3, a.value
    assert _iou(grow(sim > a.value, seeds, depth_edges(depth, opacity)), block) > 0.95


def test_region_levels_hold_every_thresholds_region():
    """region_levels >= k is the region `region_areas_reference` grows at thresholds[k], pixel for pixel, and
    region_similarity's map above t is that region (to a grid step) at the map's full size, seeded by scattered
    single pixels as projected anchors are."""
    from repaint_nerf.core.select.autothreshold import GRID, region_levels, region_similarity

    rng = np.random.default_rng(3)
    import cv2

    sim = cv2.GaussianBlur(rng.random((40, 56)).astype(np.float32), (7, 7), 2.0)
    seeds = np.zeros(sim.shape, bool)
    seeds[18:22, 25:30] = True
    barrier = np.zeros(sim.shape, bool)
    barrier[:, 40] = True
    levels = region_levels(sim, seeds, barrier)
    for k in (0, 20, 45, 70):
        allowed = ((sim > GRID[k]) | seeds) & ~barrier
        np.testing.assert_array_equal(levels >= k, grow(allowed, seeds & ~barrier))
    assert (levels[:, 40:] < 0).all()

    # two discs of one similarity, walled apart by depth; two scattered seed pixels on the left one
    h, w = 200, 256
    left, right = _disc(h, w, 100, 70, 40), _disc(h, w, 100, 190, 40)
    sim = np.where(left | right, 0.8, 0.1).astype(np.float32)
    depth = np.where(left, 2.0, np.where(right, 3.0, 6.0)).astype(np.float32)
    seeds = np.zeros((h, w), bool)
    seeds[95, 61], seeds[108, 77] = True, True
    region = region_similarity(sim, seeds, depth, np.ones((h, w), np.float32))
    assert region.shape == sim.shape and (region <= sim)[~left].all()  # inside, the seeds show at any threshold
    for t in (0.3, 0.5, 0.75):
        assert (region > t)[left].mean() > 0.95 and not (region > t)[right].any()
    assert not (region > 0.85)[~_disc(h, w, 100, 70, 12)].any()


def test_a_cut_out_object_is_walled_in_by_empty_space():
    """A cut-out capture (ethiopian_head: the object trains on its masks): the object is the view's only surface and
    a quarter of its pixels, empty space all round. Its similarities to a patch fade from 0.95 at the top to 0.55 at
    the bottom, so the view's split of them cuts it in two. Walled in by the empty space, the region is the whole
    object up to the top of its flat start; counted against the view's surface rather than its pixels it read as
    walled in by nothing, and the split kept the upper half."""
    from repaint_nerf.core.select.autothreshold import patch_auto_threshold_px, view_split

    h = w = 96
    yy, _ = np.mgrid[:h, :w]
    obj = _disc(h, w, 48, 48, 27)
    sim = np.where(obj, 0.95 - 0.4 * (yy - 21) / 54.0, 0.0).astype(np.float32)
    opacity = obj.astype(np.float32)
    depth = np.where(obj, 2.0, 0.0).astype(np.float32)
    seeds = patch_pixels((h, w), (0.45, 0.30, 0.55, 0.40))
    assert 0.25 > obj.mean() and view_split(sim, obj) > 0.65  # the split alone halves it
    a = patch_auto_threshold_px(sim, seeds, depth, opacity)
    assert a.jump is None and a.value < 0.62, a.value
    barrier = depth_edges(depth, opacity)
    assert _iou(grow(sim > a.value, seeds, barrier), obj) > 0.9 > 0.7 > _iou(grow(sim > view_split(sim, obj), seeds,
                                                                                    barrier), obj)


def test_a_region_that_fills_the_view_is_not_walled_in():
    """No depth edge (the rough depth of a real capture): the region grown at the lowest thresholds is the whole
    view, flat until the background's similarities (0.2-0.45, a slow gradient) start to fall away, with no jump,
    and the object's (0.5-0.95) fall away slowly too. That flat start is not a wall, so the view's split is the
    floor, not the flat start's top (the fox capture: 0.26, the overlay on 70% of the view)."""
    from repaint_nerf.core.select.autothreshold import walled_top

    h = w = 96
    yy, xx = np.mgrid[:h, :w]
    sim = (0.2 + 0.25 * xx / (w - 1)).astype(np.float32)
    obj = _disc(h, w, 48, 74, 22)
    sim[obj] = (0.5 + 0.45 * yy / (h - 1))[obj]  # the object's similarities spread too: no long plateau of its own
    seeds = _disc(h, w, 60, 74, 5)
    a = auto_threshold(sim, seeds)
    top = walled_top(a.thresholds, a.areas, int(seeds.sum()))
    assert a.jump is None and top is not None and top < 0.2  # the old reading: a wall, and the floor stopped there
    assert 0.45 < a.value < 0.6, a.value
    assert _iou(grow(sim > a.value, seeds), obj) > 0.9 > 0.5 > _iou(grow(sim > top, seeds), obj)


def _fill_level_holes_reference(levels: np.ndarray) -> np.ndarray:
    """Per threshold: the region `levels >= k` with the 4-connected components of its complement filled that touch
    neither the image border nor a patch of pixels no threshold reaches over SPECK of the reached area."""
    import cv2

    from repaint_nerf.core.select.geometry import SPECK

    out = levels.copy()
    n, lab, stats, _ = cv2.connectedComponentsWithStats((levels < 0).astype(np.uint8), connectivity=8)
    walls = (levels < 0) & (stats[lab, cv2.CC_STAT_AREA] > SPECK * (levels >= 0).sum())
    for k in range(int(levels.max()) + 1):
        region = levels >= k
        n, lab = cv2.connectedComponents((~region).astype(np.uint8), connectivity=4)
        outside = walls.copy()
        outside[0, :] = outside[-1, :] = outside[:, 0] = outside[:, -1] = True
        open_ = np.unique(lab[outside & ~region])
        hole = ~region & ~np.isin(lab, open_)
        out[hole] = np.maximum(out[hole], k)
    return out


def test_filled_levels_match_each_thresholds_filled_region():
    """fill_level_holes (one reconstruction by erosion) fills, at every threshold, the holes that a per-threshold
    labelling fills, on random blurred maps with walls."""
    import cv2

    from repaint_nerf.core.select.autothreshold import fill_level_holes, region_levels

    rng = np.random.default_rng(5)
    for trial in range(4):
        sim = cv2.GaussianBlur(rng.random((48, 64)).astype(np.float32), (5, 5), 1.5)
        sim = (sim - sim.min()) / (sim.max() - sim.min())
        seeds = np.zeros(sim.shape, bool)
        seeds[22:26, 30:34] = True
        barrier = rng.random(sim.shape) < 0.02 if trial % 2 else None
        levels = region_levels(sim, seeds, barrier)
        filled = fill_level_holes(levels)
        np.testing.assert_array_equal(filled, _fill_level_holes_reference(levels))
        assert (filled >= levels).all()
    assert (fill_level_holes(np.full((5, 5), -1, np.int16)) == -1).all()


def test_the_overlay_fills_similarity_speckles_but_not_a_walled_hole():
    """A disc whose similarity dips under the threshold in scattered specks (a head whose hair and face differ) and
    whose depth has a speck of noise shows whole above that threshold, as its masks are filled; a ring's hole,
    walled off by a depth edge and showing the floor behind, stays a hole."""
    from repaint_nerf.core.select.autothreshold import region_similarity

    h, w = 120, 160
    rng = np.random.default_rng(0)
    disc = _disc(h, w, 60, 50, 35)
    specks = disc & (rng.random((h, w)) < 0.15)
    specks[58:63, 48:53] = False  # the patch
    sim = np.where(disc, np.where(specks, 0.55, 0.8), 0.1).astype(np.float32)
    seeds = np.zeros((h, w), bool)
    seeds[58:63, 48:53] = True
    depth = np.where(disc, 2.0, 6.0).astype(np.float32)
    depth[40:42, 40:42] = 2.3  # depth noise: a speck of depth edges inside the disc
    region = region_similarity(sim, seeds, depth, np.ones((h, w), np.float32))
    inner = _disc(h, w, 60, 50, 30)
    assert (region > 0.7)[inner].all()  # no speck left
    assert not (region > 0.7)[~_disc(h, w, 60, 50, 37)].any()
    assert not (region > 0.85)[~_disc(h, w, 60, 50, 10)].any()  # above every similarity: the patch alone

    ring = _disc(h, w, 60, 110, 40) & ~_disc(h, w, 60, 110, 15)
    hole = _disc(h, w, 60, 110, 12)
    sim = np.where(ring, 0.8, np.where(hole, 0.5, 0.1)).astype(np.float32)  # the floor in the hole: similar enough
    depth = np.where(ring, 2.0, 6.0).astype(np.float32)  # to join at 0.4, but behind a depth edge
    seeds = np.zeros((h, w), bool)
    seeds[60, 75:80] = True
    region = region_similarity(sim, seeds, depth, np.ones((h, w), np.float32))
    assert (region > 0.7)[_disc(h, w, 60, 110, 37) & ~_disc(h, w, 60, 110, 18)].mean() > 0.95
    assert not (region > 0.7)[hole].any()


def test_otsu_threshold_matches_skimage_reference():
    """Our Otsu split (kept here so the first patch does not import scipy.ndimage through skimage.filters) equals
    skimage's threshold_otsu, the reference, on one-, two- and three-mode samples, uniform noise and values with
    many ties."""
    from skimage.filters import threshold_otsu

    from repaint_nerf.core.select.autothreshold import otsu_threshold

    rng = np.random.default_rng(1)
    for i in range(60):
        n = int(rng.integers(2, 3000))
        v = np.concatenate([rng.normal(rng.uniform(0, 1), rng.uniform(0.01, 0.2), n)
                            for _ in range(1 + i % 3)])
        if i % 5 == 0:
            v = rng.uniform(0, 1, n)
        if i % 7 == 0:
            v = np.round(v, 1)
        assert otsu_threshold(v) == threshold_otsu(v)


def test_a_view_rough_only_once_downsampled_takes_its_edges_at_its_own_size():
    """A disc in front of a wall of nearly its colour, at 512 px: the wall's inverse depth ripples gently (smooth at
    512 px, rough at the 128 px the region grows at, as a real capture's wallpaper read on the fox). The region
    stops at the disc's edge found at 512 px; the downsampled depth alone has no usable edges and let it over the
    wall."""
    from repaint_nerf.core.select.autothreshold import region_similarity
    from repaint_nerf.core.select.geometry import rough_depth

    rng = np.random.default_rng(5)
    n = 512
    yy, xx = np.mgrid[:n, :n].astype(np.float64)
    disc = _disc(n, n, 256, 256, 100)
    ripple = 1.0 + 0.05 * np.sin(2 * np.pi * xx / 32) * np.sin(2 * np.pi * yy / 32)
    depth = np.where(disc, 3.0, 4.0 / ripple).astype(np.float32)
    opacity = np.ones((n, n), np.float32)
    small = depth[::4, ::4]
    assert rough_depth([small], [opacity[::4, ::4]]) and not rough_depth([depth], [opacity])
    sim = (np.where(disc, 0.8, 0.7) + rng.normal(0.0, 0.01, (n, n))).astype(np.float32)
    seeds = _disc(n, n, 256, 256, 20)
    region = region_similarity(sim, seeds, depth, opacity) > 0.5
    assert _iou(region, disc) > 0.95, _iou(region, disc)


def test_pooled_edges_keep_a_one_pixel_line_wherever_it_falls():
    """A 1-px edge line at any column of a 500-px map walls every row of the 128-px barrier (nearest sampling
    keeps one column in four and misses most of them)."""
    from repaint_nerf.core.select.autothreshold import pooled_edges

    for x in range(100, 120):
        e = np.zeros((500, 500), bool)
        e[:, x] = True
        b = pooled_edges(e, (128, 128))
        assert b.any(axis=1).all(), x
        assert b.sum() <= 2 * 128, x


def _depth_edges_reference(depth: np.ndarray, opacity: np.ndarray, rel: float) -> np.ndarray:
    """depth_edges as first written: float64, np.roll per side, the rolled-in border lines cleared."""
    from repaint_nerf.core.select.geometry import MIN_OPACITY

    z = np.asarray(depth, np.float64)
    surface = (opacity > MIN_OPACITY) & (z > 0)
    w = np.where(surface, 1.0 / np.maximum(z, 1e-9), 0.0)
    edge = np.zeros(w.shape, bool)
    for axis in (0, 1):
        for step in (1, -1):
            near, far = np.roll(w, -step, axis), np.roll(w, step, axis)
            e = (near - (2.0 * w - far) > rel * w) & (near - w > 0.5 * rel * w)
            sl = [slice(None)] * 2
            sl[axis] = slice(-1, None)
            e[tuple(sl)] = False
            sl[axis] = slice(0, 1)
            e[tuple(sl)] = False
            edge |= e
    return edge | ~surface


def _depth_noise_reference(depth: np.ndarray) -> float:
    """depth_noise as first written, on every row and column (float64, every pixel a surface pixel)."""
    w = 1.0 / np.asarray(depth, np.float64)
    vals = [(np.abs(np.roll(w, -1, a) - 2.0 * w + np.roll(w, 1, a)) / w)[(slice(1, -1), slice(None)) if a == 0
                                                                            else (slice(None), slice(1, -1))].ravel()
            for a in (0, 1)]
    return 1.4826 * float(np.median(np.concatenate(vals)))


def test_depth_edges_and_noise_match_the_plain_reference():
    """The sliced float32 depth_edges equals the rolled float64 one on noisy maps with steps and holes; depth_noise,
    which reads every k-th line of a large map, stays within 5% of the full reading."""
    from repaint_nerf.core.select.geometry import DEPTH_EDGE, depth_noise, inverse_depth

    rng = np.random.default_rng(11)
    for h, w in ((64, 64), (97, 131), (600, 340)):
        steps = np.where(rng.random((h // 8 + 1, w // 8 + 1)) < 0.3, 1.5, 1.0)
        z = (3.0 * np.kron(steps, np.ones((8, 8)))[:h, :w] * np.exp(rng.normal(0, 0.004, (h, w)))).astype(np.float32)
        o = np.where(rng.random((h, w)) < 0.02, 0.0, 1.0).astype(np.float32)
        np.testing.assert_array_equal(depth_edges(z, o, DEPTH_EDGE), _depth_edges_reference(z, o, DEPTH_EDGE))
        smooth = (3.0 * np.exp(rng.normal(0, 0.004, (h, w)))).astype(np.float32)
        got, ref = depth_noise(*inverse_depth(smooth)), _depth_noise_reference(smooth)
        assert abs(got - ref) < 0.05 * ref, (h, w, got, ref)
