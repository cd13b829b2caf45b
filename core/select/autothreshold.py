"""The automatic threshold of one query (issue 15), chosen from that query's own evidence.

The paper's mask is `cos(F_patch, F(x)) > alpha` with one alpha for every scene; measured on photo-like
scenes the best alpha ran from 0.2 to 0.85. The evidence used here: the region grown from the patch's
pixels through `similarity > t` (and, given a barrier such as the field's depth edges, not across it),
as t falls. Its area stays nearly flat while t sweeps across the gap between the object and what
surrounds it (a plateau), and jumps where the region leaks into a neighbour or the surface the object
rests on. The threshold is the middle of a plateau right above the largest jump when there is one
(the area at least doubles within `JUMP_WINDOW`): the longest of the plateaus there that no step of
`PART_STEP` separates from the jump (`choose_threshold`); else the middle of the longest plateau. It moves down
to a lower plateau whose region rejoins pixels above it that a band of lower similarity cut off (`whole_object`).
The barrier is the one the masks will have: depth edges only where the selection's geometry uses them and
the view's depth is smooth enough to show them (`geometry.rough_depth`, as `geometry.fit_parts` decides).
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


EVAL_SIDE = 128  # px: a query's similarity map is evaluated at most this large (its long side), downsampled above
GRID = np.round(np.arange(0.02, 0.985, 0.01), 2)  # thresholds tried (similarities of one query)
JUMP_WINDOW = 2  # grid steps each side: a leak doubles the area within +-0.02
JUMP_RATIO = 2.0
PLATEAU_WINDOW = 2  # grid steps each side for the flatness test
PLATEAU_RATIO = 1.1  # flat: the area changes by under 10% across the window
WALL_MARGIN = 2  # grid steps below the top of a walled region that the view's floor may reach
FALLBACK = 0.5  # no usable evidence (an empty or constant map)
WALL_SHARE = 0.5  # a region holding this share of the view's pixels at the lowest threshold is walled in by nothing
# (measured at 600 steps as shares of the view's surface, which bound its share of the pixels: the presets' walled
# regions 0.5-17%, room360's slowly shrinking one 35%; on the fox capture, whose rough depth shows no edges, 99%:
# the floor stopped at 0.06-0.08, the threshold stayed at the curve's 0.26 and the overlay covered 70% of the view.
# Counted over the surface, a cut-out capture's object, the only surface there is, read as walled in by nothing:
# ethiopian_head's head, 87% of its view's surface and 25% of its pixels, flat from 0.02 to 0.68, took the view's
# split 0.87 and lost half of itself)
PART_STEP = 1.8  # plateaus above a leak whose areas step by this much: the object and a part of it (measured:
# a printed can's colours 1.9x; a toy and its neighbour, below the leak's, 1.67-1.74x)
CUT_FRACTION = 0.1  # pixels above the threshold that a lower band cut off, as a share of the kept region: the
# parts of one object (measured under both teachers: a printed can's ends 0.14-0.78; a neighbour that joins at a
# lower threshold 0.0, as in similar and room360)
MIN_REGION = 1.5  # a plateau is a region of at least 1.5x the patch's pixels: a patch may cover most of a small
# object (a 9x9 patch on a tin of ~100 px); at 2x a trained bread field's tin scored 0.01 (the table's plateau won)


@dataclass(frozen=True)
class AutoThreshold:
    """The chosen threshold and the evidence: the grid, the grown areas, the jump (or None), and the map the
    areas were counted from (`region_levels`, at the size the curve was evaluated; None where not kept)."""

    value: float
    thresholds: np.ndarray
    areas: np.ndarray
    jump: float | None
    levels: np.ndarray | None = None


def region_areas_reference(similarity: np.ndarray, seeds: np.ndarray, barrier: np.ndarray | None = None,
                           thresholds: np.ndarray = GRID) -> np.ndarray:
    """Pixels of the region grown from `seeds` through `similarity > t` (not across `barrier`), per t: one
    labelling of the whole map per threshold (the plain form `region_areas` is tested against)."""
    s = np.asarray(similarity, np.float32)
    seeds = np.asarray(seeds, bool)
    free = np.ones(s.shape, bool) if barrier is None else ~np.asarray(barrier, bool)
    seed_idx = np.flatnonzero(seeds & free)
    out = np.zeros(len(thresholds), np.int64)
    if not seed_idx.size:
        return out
    for k, t in enumerate(thresholds):  # as geometry.grow, with the areas read from the component stats
        allowed = (((s > t) | seeds) & free).astype(np.uint8)
        _, lab, stats, _ = cv2.connectedComponentsWithStats(allowed, connectivity=4)
        keep = np.unique(lab.reshape(-1)[seed_idx])
        out[k] = int(stats[keep[keep > 0], cv2.CC_STAT_AREA].sum())
    return out


def region_levels(similarity: np.ndarray, seeds: np.ndarray, barrier: np.ndarray | None = None,
                  thresholds: np.ndarray = GRID) -> np.ndarray:
    """Per pixel, the index of the highest of `thresholds` (ascending) whose region grown from `seeds` (as in
    `region_areas_reference`) holds it, -1 where none does: the region at thresholds[k] is `levels >= k`.
    As t rises the region only shrinks, so each threshold labels only the previous region's bounding box, within
    that region (the seed pixels are in every region)."""
    s = np.asarray(similarity, np.float32)
    seeds = np.asarray(seeds, bool)
    free = np.ones(s.shape, bool) if barrier is None else ~np.asarray(barrier, bool)
    start = seeds & free
    levels = np.full(s.shape, -1, np.int16)
    if not start.any():
        return levels
    # the pixels a region may hold at t: similarity above t, seeds always (their level is +inf), barrier never
    level = np.where(free, np.where(seeds, np.inf, s), -np.inf).astype(np.float32)
    region = np.ones(s.shape, bool)
    y0, y1, x0, x1 = 0, s.shape[0], 0, s.shape[1]
    for k, t in enumerate(np.asarray(thresholds)):
        lv, prev, st = level[y0:y1, x0:x1], region[y0:y1, x0:x1], start[y0:y1, x0:x1]
        allowed = (lv > t) & prev
        n, lab = cv2.connectedComponents(allowed.view(np.uint8), connectivity=4)
        keep = np.zeros(n, bool)
        keep[lab[st]] = True
        keep[0] = False
        sub = keep[lab]
        levels[y0:y1, x0:x1][sub] = k
        ys, xs = np.nonzero(sub.any(axis=1))[0], np.nonzero(sub.any(axis=0))[0]
        region = np.zeros(s.shape, bool)
        region[y0:y1, x0:x1] = sub
        y0, y1, x0, x1 = y0 + ys[0], y0 + ys[-1] + 1, x0 + xs[0], x0 + xs[-1] + 1
    return levels


def region_areas(similarity: np.ndarray, seeds: np.ndarray, barrier: np.ndarray | None = None,
                 thresholds: np.ndarray = GRID) -> np.ndarray:
    """`region_areas_reference`'s areas (thresholds ascending), counted from `region_levels`. On the editor's patch
    path this is most of the automatic threshold's cost."""
    return _level_areas(region_levels(similarity, seeds, barrier, thresholds), len(thresholds))


def _level_areas(levels: np.ndarray, n: int) -> np.ndarray:
    """The region's area at each of `n` thresholds from its `region_levels` map."""
    counts = np.bincount(levels[levels >= 0].ravel(), minlength=n)
    return counts[::-1].cumsum()[::-1].astype(np.int64)


def _runs(flags: np.ndarray) -> list[tuple[int, int]]:
    """[start, end) index ranges where `flags` is True."""
    out, start = [], None
    for i, f in enumerate(list(flags) + [False]):
        if f and start is None:
            start = i
        elif not f and start is not None:
            out.append((start, i))
            start = None
    return out


def _plateaus(a: np.ndarray, seed_area: int) -> list[tuple[int, int]]:
    """Index ranges of an area curve `a` (floats >= 1) where it is flat within `PLATEAU_WINDOW` and the region
    is more than the patch (`MIN_REGION` x `seed_area`)."""
    n = len(a)
    flat = np.array([a[max(i - PLATEAU_WINDOW, 0)] / a[min(i + PLATEAU_WINDOW, n - 1)] < PLATEAU_RATIO
                     for i in range(n)])
    return _runs(flat & (a >= MIN_REGION * max(int(seed_area), 1)))


def choose_threshold(thresholds: np.ndarray, areas: np.ndarray, seed_area: int = 1) -> tuple[float, float | None]:
    """(threshold, threshold of the leak or None) from an area curve (areas non-increasing in t).

    Plateaus count only where the region is more than the patch itself (`MIN_REGION` x `seed_area`): as t
    nears 1 only the patch is left, and the fall from the object to the patch is growth, not a leak. A
    jump counts as a leak only with a plateau above it and no other jump between (a whole object, then more).
    Above the leak, plateaus whose areas step by less than `PART_STEP` are one region: right above a leak the
    region can shrink slowly for a while (a shadow or contact zone whose similarity fades; on a trained
    room360 field the stretch ran 0.17-0.40 and the object's plateau 0.43-0.82, test IoU 0.48 at the former's
    middle and 0.98 at the latter's), and the object is that region's longest plateau. A step of `PART_STEP`
    or more between plateaus above the leak is a part of the object falling away (a printed can's two colours
    joined at 0.34 and leaked at 0.09 under the blended teacher: test IoU 0.52 on the longer, upper plateau,
    0.95 on the lower), so the region right above the leak is the object.
    """
    a = np.maximum(np.asarray(areas, np.float64), 1.0)
    n = len(a)
    if n < 2 * PLATEAU_WINDOW + 1:
        return FALLBACK, None
    lo = lambda i, k: a[max(i - k, 0)]  # noqa: E731  the area at a lower threshold (larger region)
    hi = lambda i, k: a[min(i + k, n - 1)]  # noqa: E731
    ratio = np.array([lo(i, JUMP_WINDOW) / hi(i, JUMP_WINDOW) for i in range(n)])
    runs = _plateaus(a, seed_area)
    middle = lambda r: (r[0] + r[1] - 1) // 2  # noqa: E731
    longest = lambda rs: max(rs, key=lambda r: (r[1] - r[0], -r[0]))  # noqa: E731
    for j in np.argsort(-ratio, kind="stable"):
        if ratio[j] < JUMP_RATIO:
            break
        above = [r for r in runs if r[0] > j]
        if above and (above[0][0] <= j + 2 * JUMP_WINDOW + 4 or ratio[j + 1:above[0][0]].max() < JUMP_RATIO):
            region = [above[0]]
            for r in above[1:]:
                if a[region[-1][1] - 1] / a[r[0]] >= PART_STEP:
                    break
                region.append(r)
            return float(thresholds[middle(longest(region))]), float(thresholds[j])
    if not runs:
        return FALLBACK, None
    return float(thresholds[middle(max(runs, key=lambda r: (r[1] - r[0], r[0])))]), None


def auto_threshold(similarity: np.ndarray, seeds: np.ndarray, barrier: np.ndarray | None = None,
                   thresholds: np.ndarray = GRID, surface: np.ndarray | None = None) -> AutoThreshold:
    """The automatic threshold of a query from its similarity map (H, W) in one view, the query's own
    pixels there (`seeds`, bool (H, W): the patch) and optional barrier pixels (depth edges, no surface).

    Without a leak the region's curve bounds the threshold only from above (a region walled in by depth edges
    keeps its area at every threshold); the view's split between the object's similarities and the rest's
    (`view_split` over `surface`, bool (H, W), default every pixel) is then its floor: under the blended
    teacher a thin pole walled in by its edges took 0.48 from the curve alone (test IoU 0.38), 0.64 with the
    floor (0.93)."""
    seeds = np.asarray(seeds, bool)
    levels = region_levels(similarity, seeds, barrier, thresholds)
    areas = _level_areas(levels, len(thresholds))
    free = seeds if barrier is None else seeds & ~np.asarray(barrier, bool)  # the pixels the region grows from
    value, jump = choose_threshold(thresholds, areas, int(free.sum()))
    value = whole_object(similarity, levels, thresholds, areas, value, jump, int(free.sum()))
    if jump is None:
        floor = view_split(similarity, surface)
        top = walled_top(thresholds, areas, int(free.sum()), int(np.size(seeds)))
        value = max(value, floor if top is None else min(floor, top))
    return AutoThreshold(value, np.asarray(thresholds), areas, jump, levels)


def whole_object(similarity: np.ndarray, levels: np.ndarray, thresholds: np.ndarray, areas: np.ndarray,
                 value: float, jump: float | None, seed_area: int = 1) -> float:
    """`value` (from `choose_threshold`) lowered, plateau by plateau downwards (above the leak, if any), to each
    whose region joins pixels above the current threshold that the current region lost: at least `CUT_FRACTION`
    of it. Those pixels are as like the patch as the kept ones, so a band of lower similarity cut one object
    (a printed can's label between its red ends: under the blended teacher the area curve stepped 1.8x at 0.4,
    a step that a can and a neighbour of another colour also make, and the longer, upper plateau kept one end,
    IoU 0.52 against 0.95 at 0.3); a neighbour that joins lower holds none of them. The regions are read from
    the curve's own `region_levels` map (`levels`): the region at thresholds[k] is `levels >= k`."""
    t = np.asarray(thresholds)
    runs = _plateaus(np.maximum(np.asarray(areas, np.float64), 1.0), seed_area)
    floor = -1 if jump is None else int(np.argmin(np.abs(t - jump)))
    s = np.asarray(similarity, np.float32)
    lost = None
    for r in sorted(runs, key=lambda r: -r[0]):
        if r[0] <= floor:
            break
        if t[r[1] - 1] >= value:
            continue
        if lost is None:
            kept = levels >= int(np.argmin(np.abs(t - value)))  # value is a grid threshold
            lost = (s > value) & ~kept
        if np.count_nonzero(lost & (levels >= r[1] - 1)) >= CUT_FRACTION * max(int(kept.sum()), 1):
            value, lost = float(t[(r[0] + r[1] - 1) // 2]), None
    return value


def walled_top(thresholds: np.ndarray, areas: np.ndarray, seed_area: int = 1, room: int | None = None
               ) -> float | None:
    """Where a region walled in from the lowest threshold up starts to shrink, `WALL_MARGIN` grid steps below
    it; None when the lowest threshold's region is not flat, or holds `WALL_SHARE` of the `room` (the view's
    pixels) or more: walled in by nothing. The floor of `auto_threshold` stops there: a
    floor above it cuts the walled region, which is the whole object in that view (a printed can walled in by
    the depth edges of a free view: flat 0.02-0.44 under the blended teacher; the floor's 0.57 kept one of its
    colours, editor's-way IoU 0.54, against 0.95 at 0.42)."""
    a = np.maximum(np.asarray(areas, np.float64), 1.0)
    if len(a) < 2 * PLATEAU_WINDOW + 1 or (room is not None and a[0] >= WALL_SHARE * max(room, 1)):
        return None
    runs = _plateaus(a, seed_area)
    if not runs or runs[0][0] != 0:
        return None
    return float(thresholds[max(runs[0][1] - 1 - WALL_MARGIN, 0)])


def views_threshold(own: float, others: list[AutoThreshold]) -> float:
    """The automatic threshold of a patch drawn outside the training views (`own`, from its view's curve) once
    the training views that see its surface points have grown their own regions from them (`others`): the
    median of `own` and the thresholds of those views whose region leaks (`AutoThreshold.jump`). A view whose
    region is walled in by depth edges bounds the threshold only from above, so it does not vote; with no leak
    anywhere `own` stands. Measured in the editor's way (bench mask): the blended teacher's thin pole, walled in
    the free view, took 0.46 (IoU 0.14); the views' vote 0.76 (0.93), six of its eight views leaking.
    One leaking view among walled ones is one view's guess and does not vote: on a fox capture one of eight
    leaked, at 0.80, and its vote moved the patch's 0.55 to 0.68, which lost the head."""
    leaks = [float(o.value) for o in others if o.jump is not None]
    if len(leaks) < 2 and 2 * len(leaks) < len(others):
        return float(own)
    return float(np.median([float(own)] + leaks))


def walled_views_threshold(own: float, others: list[AutoThreshold]) -> float:
    """The automatic threshold of a patch drawn in a training view whose region there leaks nowhere (`own`: that
    view's floor or walled top, one view's guess) once the training views that see its surface points have grown
    their own regions from them (`others`): where none of those leaks either, the median of `own` and all of theirs
    (a view that sees one colour of a printed can: flat from 0.02 to 0.88, its floor 0.64 cut the label in the
    other views; theirs were 0.45-0.64, the median 0.48: IoU 0.571 -> 0.960); else `own` stands (letting the leaking
    views vote, as `views_threshold` counts them, cost 0.40 IoU on one of 24 recorded fields, the built-in teacher's
    can: 0.46 -> 0.66)."""
    if any(o.jump is not None for o in others):
        return float(own)
    return float(np.median([float(own)] + [float(o.value) for o in others]))


def view_split(similarity: np.ndarray, surface: np.ndarray | None = None) -> float:
    """Otsu's split of a similarity map's values on `surface` pixels (the object's mode against the rest);
    `FALLBACK` when they are constant."""
    return text_auto_threshold([np.asarray(similarity, np.float32)],
                               None if surface is None else [np.asarray(surface, bool)])


def patch_pixels(shape: tuple[int, int], rect) -> np.ndarray:
    """Bool (H, W) of a patch: a `Patch` in pixels, or (x0, y0, x1, y1) in image fractions (the editor's drag)."""
    h, w = int(shape[0]), int(shape[1])
    out = np.zeros((h, w), bool)
    if hasattr(rect, "x0"):
        out[max(rect.y0, 0):rect.y1, max(rect.x0, 0):rect.x1] = True
        return out
    x0, y0, x1, y1 = (float(v) for v in rect)
    x0, x1 = sorted((x0, x1))
    y0, y1 = sorted((y0, y1))
    px0, py0 = int(np.floor(x0 * w)), int(np.floor(y0 * h))
    out[py0:max(py0 + 1, int(np.ceil(y1 * h))), px0:max(px0 + 1, int(np.ceil(x1 * w)))] = True
    return out


def patch_auto_threshold(similarity, patch, depth=None, opacity=None, max_side: int = EVAL_SIDE,
                         edges: bool = True) -> float:
    """The automatic threshold of a patch query in the view it was drawn in: `similarity` (H, W), `patch`
    (a `Patch` in pixels, or image fractions), and, when given, that view's rendered z-depth and opacity,
    whose depth edges bound the grown region when `edges` (the selection's geometry uses them) and the depth
    is smooth enough to show them. Maps larger than `max_side` are evaluated downsampled (the areas only
    need their shape: ~10 ms at 128 px)."""
    s = np.asarray(similarity.cpu() if hasattr(similarity, "cpu") else similarity, np.float32)
    return patch_auto_threshold_px(s, patch_pixels(s.shape, patch), depth, opacity, max_side, edges).value


def patch_auto_threshold_px(similarity, seeds: np.ndarray, depth=None, opacity=None, max_side: int = EVAL_SIDE,
                            edges: bool = True):
    """`patch_auto_threshold` with the seed pixels given as a bool (H, W) mask; returns the AutoThreshold."""
    s, seeds, barrier, surface = _query_maps(similarity, seeds, depth, opacity, max_side, edges)
    return auto_threshold(s, seeds, barrier, surface=surface)


def region_similarity(similarity, seeds: np.ndarray, depth=None, opacity=None, max_side: int = EVAL_SIDE,
                      edges: bool = True) -> np.ndarray:
    """The similarity map (H, W) kept only where the region grown from `seeds` through it reaches (as
    `patch_auto_threshold_px` grows it, at most `max_side` px, not across depth edges): float32 (H, W) whose
    `> t` is that region at threshold t with its holes filled (`fill_level_holes`), to a grid step; -1 where no
    threshold's region reaches. The editor's overlay shows this, so that the slider shows the object the masks will
    hold, not every pixel of its colour."""
    full = np.asarray(similarity.cpu() if hasattr(similarity, "cpu") else similarity, np.float32)
    seeds = np.asarray(seeds, bool)
    step = int(np.ceil(max(full.shape) / float(max_side)))
    if step > 1:  # scattered seed pixels (projected anchors) must survive the nearest-pixel downsampling
        seeds = cv2.dilate(seeds.astype(np.uint8), np.ones((step, step), np.uint8)) > 0
    s, small, barrier, _ = _query_maps(full, seeds, depth, opacity, max_side, edges)
    return level_similarity(full, region_levels(s, small, barrier))


_CROSS = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))  # 4-neighbourhood


def level_similarity(similarity: np.ndarray, levels: np.ndarray) -> np.ndarray:
    """`region_similarity`'s map from a `region_levels` map over `GRID` (at most the similarity's size): the
    patch's own view reuses its automatic threshold's (`AutoThreshold.levels`)."""
    full = np.asarray(similarity, np.float32)
    top = np.append(GRID[1:], 1.0 + 1e-6) - 1e-6  # a pixel of level k leaves the region above GRID[k]
    reach = np.where(levels >= 0, top[np.maximum(levels, 0)], -1.0).astype(np.float32)
    # inside a region (its holes filled) the overlay is solid: a pixel whose cell and the cells around it are in
    # the region at level k shows above GRID[k] whatever its own similarity; at the region's edge the full-size
    # similarity draws the outline
    inner = cv2.erode(fill_level_holes(levels), _CROSS, borderType=cv2.BORDER_CONSTANT, borderValue=-1)
    inner = np.where(inner >= 0, top[np.maximum(inner, 0)], -1.0).astype(np.float32)
    if reach.shape != full.shape:
        size = (full.shape[1], full.shape[0])
        reach = cv2.resize(reach, size, interpolation=cv2.INTER_NEAREST)
        inner = cv2.resize(inner, size, interpolation=cv2.INTER_NEAREST)
    return np.maximum(np.minimum(full, reach), inner)


def fill_level_holes(levels: np.ndarray) -> np.ndarray:
    """`levels` (a `region_levels` map) with each threshold's region's holes filled: per pixel, the highest k at
    which it lies in `levels >= k` or in a hole of it. A hole is enclosed by the region and holds only pixels that
    regions of lower thresholds reach: the same surface, its similarity dipping under the threshold, which the masks
    fill as well (geometry.fill_holes). The image border counts as outside, and so do pixels no threshold reaches
    (-1: walled off by a depth edge, or under every threshold) where they form a patch over `geometry.SPECK` of the
    region's area: the masks fill smaller walled holes as depth noise. One grayscale reconstruction by erosion from
    the outside gives every threshold's fill at once (4-connected, as the regions' complements are labelled)."""
    from repaint_nerf.core.select.geometry import SPECK

    lv = np.asarray(levels, np.int16)
    if lv.size == 0 or lv.max() < 0:
        return lv.copy()
    unreached = (lv < 0).astype(np.uint8)
    _, lab, stats, _ = cv2.connectedComponentsWithStats(unreached, connectivity=8)
    big = stats[:, cv2.CC_STAT_AREA] > SPECK * max(int(np.count_nonzero(lv >= 0)), 1)
    outside = big[lab] & (unreached > 0)
    outside[0, :] = outside[-1, :] = outside[:, 0] = outside[:, -1] = True
    marker = np.where(outside, lv, lv.max()).astype(np.int16)
    for _ in range(lv.size):  # converges in about the longest path a hole's pixels take out; the bound never binds
        nxt = np.maximum(cv2.erode(marker, _CROSS, borderType=cv2.BORDER_REPLICATE), lv)
        if np.array_equal(nxt, marker):
            break
        marker = nxt
    return marker


def _query_maps(similarity, seeds: np.ndarray, depth, opacity, max_side: int, edges: bool
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]:
    """(similarity, seeds, barrier, surface) of a query in one view at most `max_side` px on a side: the barrier is
    the view's depth edges when `edges` and its depth is smooth enough to show them, else its empty pixels.
    A view whose depth is smooth at its own size but rough once downsampled takes its edges at its own size,
    pooled (`pooled_edges`), as the masks find them there (`geometry.fit_parts` judges the views' own size): a
    real capture's wall reads bumpy at 128 px (fox, 781-px view: noise 0.014 at 128 px, 0.0024 at its own size),
    and without a barrier the region of a patch on the fox leaked over the wallpaper."""
    from repaint_nerf.core.select.geometry import MIN_OPACITY, depth_edges, rough_depth

    s = np.asarray(similarity.cpu() if hasattr(similarity, "cpu") else similarity, np.float32)
    seeds = np.asarray(seeds, bool)
    z = z_full = None if depth is None else np.asarray(depth.cpu() if hasattr(depth, "cpu") else depth, np.float32)
    o = o_full = None if opacity is None else np.asarray(opacity.cpu() if hasattr(opacity, "cpu") else opacity,
                                                         np.float32)
    h, w = s.shape
    f = max_side / float(max(h, w))
    size = (w, h)
    if f < 1.0:
        size = (max(1, int(round(w * f))), max(1, int(round(h * f))))
        s = cv2.resize(s, size, interpolation=cv2.INTER_AREA)
        small = cv2.resize(seeds.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST) > 0
        if not small.any() and seeds.any():  # a patch thinner than a downsampled pixel: keep its centre
            ys, xs = np.nonzero(seeds)
            small[min(int(ys.mean() * f), size[1] - 1), min(int(xs.mean() * f), size[0] - 1)] = True
        seeds = small
        z = None if z is None else cv2.resize(z, size, interpolation=cv2.INTER_NEAREST)
        o = None if o is None else cv2.resize(o, size, interpolation=cv2.INTER_NEAREST)
    barrier = None
    if z is not None and edges:
        if not rough_depth([z], [o]):
            barrier = depth_edges(z, o)
        elif f < 1.0 and not rough_depth([z_full], [o_full]):
            barrier = pooled_edges(depth_edges(z_full, o_full), size)
    if barrier is None and o is not None:
        barrier = o <= MIN_OPACITY
    elif barrier is None:
        barrier = None if z is None else ~(z > 0)
    if o is not None:
        surface = o > MIN_OPACITY
    else:
        surface = None if z is None else z > 0
    return s, seeds, barrier, surface


def pooled_edges(edges: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """A barrier (bool (H, W)) at `size` (W, H) from edge pixels at a larger size: a pixel is a barrier where its
    block holds half a line's worth of edge pixels (a share 1 / (2 k) for blocks of side k), so that a 1-px edge
    line that straddles two blocks still walls one of them: nearest sampling keeps only every k-th pixel of a
    line and lets the region through the gaps."""
    e = np.asarray(edges, bool)
    k = max(e.shape[0] / float(size[1]), e.shape[1] / float(size[0]))
    share = cv2.resize(e.astype(np.float32), size, interpolation=cv2.INTER_AREA)
    return share >= 0.5 / k - 1e-6


def selection_auto_threshold(selection, cache, view: int) -> float:
    """The automatic threshold of a selection's positive patches drawn in training view `view` (their union seeds
    the region; `cache`: the training views' `masks.ViewCache`; the region stops at `ViewMaps.edge_depth`'s edges).
    Where the patch's own view shows no leak, its value is that view's floor, and the training views that see the
    patch's surface points vote (`Selection.training_views_threshold`): a view that sees only one colour of a
    printed can gave a flat region from 0.02 to 0.88 and its floor 0.64 cut the label elsewhere (IoU 0.57)."""
    maps = cache.get(view)
    sim = selection.similarity(maps.feature).float().cpu().numpy()
    seeds = np.zeros(sim.shape, bool)
    for p in selection.patches:
        if p.positive:
            seeds |= patch_pixels(sim.shape, p)
    own = patch_auto_threshold_px(sim, seeds, maps.edge_depth(), maps.opacity, edges=uses_edges(selection))
    if own.jump is not None:
        return own.value
    return selection.training_views_threshold(own.value, sim, seeds, cache, view)


def uses_edges(selection) -> bool:
    """Whether the masks of `selection` (its geometry name) are bounded by depth edges."""
    from repaint_nerf.core.select.geometry import parts_named

    return parts_named(selection.geometry).edges


def otsu_threshold(values: np.ndarray, bins: int = 256) -> float:
    """Otsu's threshold of 1-D `values`: the centre of the histogram bin (of `bins` over their range) after which a
    split maximises the between-class variance. Here and not skimage.filters': importing that module pulled in
    scipy.ndimage and cost the first patch of a session 450 ms."""
    counts, edges = np.histogram(values, bins=bins)
    centres = (edges[:-1] + edges[1:]) / 2.0
    counts = counts.astype(np.float64)
    weights, moments = np.cumsum(counts), np.cumsum(counts * centres)
    below, sums = weights[:-1], moments[:-1]  # the class up to and including bin i: its weight and first moment
    above = weights[-1] - below
    with np.errstate(divide="ignore", invalid="ignore"):
        gap = sums / below - (moments[-1] - sums) / above
    between = np.where((below > 0) & (above > 0), below * above * gap ** 2, -1.0)
    return float(centres[int(np.argmax(between))])


def text_auto_threshold(similarities: list[np.ndarray], surfaces: list[np.ndarray] | None = None) -> float:
    """The automatic threshold of a text query, which has no patch to grow from: Otsu's split of the
    similarities of every view's surface pixels (the object's mode against the rest), `FALLBACK` when the
    values are constant."""
    if surfaces is None:
        surfaces = [np.ones(np.shape(s), bool) for s in similarities]
    v = np.concatenate([np.asarray(s, np.float32)[np.asarray(m, bool)] for s, m in zip(similarities, surfaces)]
                       + [np.zeros(0, np.float32)])
    v = v[np.isfinite(v)].astype(np.float64)  # float32 bins of a narrow range near 1 are not distinct (numpy raises)
    if v.size < 2 or float(v.max() - v.min()) < 1e-6:
        return FALLBACK
    return float(np.clip(otsu_threshold(v), 0.0, 1.0))
