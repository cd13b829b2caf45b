"""The field's geometry in a view's mask (issue 15): a 2D teacher sees one brown surface where the field
knows a loaf standing above a board. Depth discontinuities and concave creases of the rendered depth
become barriers, and a view's mask is the part of `similarity > threshold` connected to seed pixels
without crossing one; views then vote on each other's pixels through their surface points.

A barrier pixel is the far side of a depth edge: its inverse depth is below what its neighbours on a
line predict by more than `DEPTH_EDGE` of its own value (more in a view whose depth is rough: `edge_level`).
Inverse depth is affine in pixel coordinates on any plane, so a table seen at a grazing angle has no edge however
fast its depth grows; only the background side is marked, so the object keeps its silhouette pixels. Pixels without
a surface (opacity below 0.5) are barriers too.

A loaf resting on a board has no depth edge where they meet, but the surface bends there the other way
from any convex object: a concave crease. As in locally convex connected patches (LCCP, Stein et al.
2014), a crease pixel is one where the normals a few pixels apart turn towards each other by more than
`CREASE` ((n_b - n_a).(P_b - P_a)/|P_b - P_a| < -CREASE); the band of such pixels is a barrier, and
after growth each band pixel joins the side of its nearest non-band pixel.

A barrier belongs to neither side. On a trained field it also falls inside objects: a silhouette pixel
blends the object's depth with what lies behind, and texture and highlights leave grooves in the depth
of a printed label. So once the masks are grown, every candidate pixel on a mask's border joins it when
its inverse depth is nearer to its neighbours inside than to its other neighbours outside (`attach`);
the far side of a real depth edge stays out, as it lies at the depth of the surface behind.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np

DEPTH_EDGE = 0.01  # relative inverse-depth jump: a loaf 0.2 above its board at 4 units is ~0.05; a torus 0.1
# behind a cube ~0.015 (0.02 let the "similar" cube leak into it); planes 0 at any angle
MIN_OPACITY = 0.5
HOLE_DEPTH = 0.02  # a torus lying on the floor: its hole is ~2.5-5% deeper than its rim at 4 units
CLOSE = 5  # px: the closing that joins a label's stripes to the can (a 2-px gap)
SPECK = 0.01  # a walled hole under 1% of its mask's area is depth noise, not a hole through the object
CREASE = 0.25  # normals turning towards each other by ~15 degrees or more (2 sin(7.5 deg) = 0.26); a 90-degree
# contact line scores ~-1, a plane 0 and a convex object > 0. LCCP's default concavity tolerance is 10 degrees.
CONTINUOUS = 0.05  # inverse depth changing under 5% a pixel: one surface (a floor at a grazing angle ~1%)
CREASE_MIN = 2.0  # a crease component must span twice the band's width: a contact line is a line, not a speck
CREASE_STEP = 2  # pixels each side: the band is ~2 * CREASE_STEP + 1 wide, wide enough to have no diagonal gap
EDGE_LINES = 10.0  # a view's true depth edges are outlines, one pixel wide: as many pixels as about this many lines
# across the view (sqrt of its surface pixels), so their share falls as the view grows. Ground-truth depth of the
# presets at 128 px reaches 6.1% (toys, 7.8 lines); kermit's rough field flagged 9-28% of its 256-px views at
# DEPTH_EDGE, and its masks came out whole at a 5% share (4.5% at 10 lines), walled in again at 8%
ROUGH_LEVEL = 3.5  # the level rises only where the budget needs this many times DEPTH_EDGE: a cluttered scene's many
# weak steps are true edges between objects (trained 128-px presets: 1.35x median, toys, and 2.2x at most, occluded;
# raising toys' level lost 0.17 IoU; captures fox 2.9x and snowmiku 2.7x at most), a rough field's bumps are strong
# (kermit's 9 views: 4.2-10x)
NOISE_LINES = 256  # depth_noise and edge_level read about this many rows and columns at most (every k-th pixel)
ATTACH_ROUNDS = 8  # border pixels `attach` adds at most, one ring a round. Five trained 128-px presets (600 steps)
# gained from 1 to 6 rounds (toys 0.633 -> 0.728 -> 0.773), held from 8 to 12 and bread lost 0.007 at 20


def depth_noise(w: np.ndarray, surface: np.ndarray) -> float:
    """The inverse-depth map `w`'s noise relative to its value: 1.4826 x the median of |w(p+1) - 2 w(p) + w(p-1)| / w(p)
    along rows and columns on `surface` (a robust sigma of the second difference; 0 on planes and clean depth).
    Maps over `NOISE_LINES` px read every k-th row and column only (the spacing along a line stays 1 px): a
    781-px view took 20 ms in full, most of it the median."""
    every = max(1, int(np.ceil(max(w.shape) / float(NOISE_LINES))))
    vals = []
    for axis in (0, 1):
        across = (slice(None, None, every), slice(None)) if axis == 1 else (slice(None), slice(None, None, every))
        p, lo, hi = _neighbours(w[across], axis)
        sp, slo, shi = _neighbours(surface[across], axis)
        ok = sp & slo & shi
        vals.append((np.abs(hi - 2 * p + lo) / np.maximum(p, np.float32(1e-12)))[ok])
    v = np.concatenate(vals)
    return 1.4826 * float(np.median(v)) if v.size else 0.0


def _neighbours(a: np.ndarray, axis: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(interior pixels, their neighbours before, their neighbours after) of `a` along `axis`: views, no copies."""
    if axis == 0:
        return a[1:-1, :], a[:-2, :], a[2:, :]
    return a[:, 1:-1], a[:, :-2], a[:, 2:]


def _step(p: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """A depth step's strength at interior pixels `p` along one line (inverse depth): the second difference, capped
    at twice the rise to the nearer neighbour (a step, not a bend). One rule for both readers: `depth_edges` marks p
    where it exceeds `rel` x w(p); `edge_level` reads each pixel's largest such `rel` from it."""
    return np.minimum(hi + lo - 2 * p, 2 * (np.maximum(hi, lo) - p))


def inverse_depth(depth: np.ndarray, opacity: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(inverse depth w (H, W) float32, 0 off the surface; surface (H, W) bool: opaque pixels with a depth).
    float32: the edges and the noise compare second differences with 1% of w, far above its rounding."""
    z = np.asarray(depth, np.float32)
    surface = z > 0 if opacity is None else (np.asarray(opacity) > MIN_OPACITY) & (z > 0)
    return np.where(surface, np.float32(1.0) / np.maximum(z, np.float32(1e-9)), np.float32(0.0)), surface


def edge_level(depth: np.ndarray, opacity: np.ndarray | None = None, budget: float | None = None) -> float:
    """The relative inverse-depth jump that makes a depth edge in this view: `DEPTH_EDGE`, raised until at most
    `budget` of the surface pixels are edges (default: `EDGE_LINES` lines' worth, `edge_budget`). True edges are
    outlines; where a rough field's depth flags more, its bumps wall every region into specks (kermit, 9 photos:
    its default mask kept 1.3% of the pixels, a piece of the plush's torso). A level under `ROUGH_LEVEL` x
    `DEPTH_EDGE` stays `DEPTH_EDGE`: such weak steps are a cluttered scene's true edges. A pixel's strength is the
    largest level at which `depth_edges` marks it, along its row or its column. A map over `NOISE_LINES` px is read
    at that scale, as its every k-th pixel with its k-th neighbours: a field resolves a bump's step over more pixels
    of a larger render, so steps read pixel to pixel shrink as the view grows (kermit's view 0 read 3.9x at 512 px
    and 3.3x at the editor's 878 px, under `ROUGH_LEVEL`, and its patch was walled in again)."""
    h, wd = np.shape(depth)
    k = max(1, int(np.ceil(max(h, wd) / float(NOISE_LINES))))
    w, surface = inverse_depth(np.asarray(depth)[::k, ::k], None if opacity is None else np.asarray(opacity)[::k, ::k])
    if min(w.shape) < 3:
        return DEPTH_EDGE
    p, surface = w[1:-1, 1:-1], surface[1:-1, 1:-1]  # the interior: pixels with both neighbours on both axes
    strength = np.full(p.shape, -np.inf, np.float32)
    for lo, hi in ((w[:-2, 1:-1], w[2:, 1:-1]), (w[1:-1, :-2], w[1:-1, 2:])):
        strength = np.maximum(strength, _step(p, lo, hi))
    s = (strength / np.maximum(p, np.float32(1e-12)))[surface]
    if budget is None:
        budget = edge_budget(surface.mean() * h * wd / (k * k) if surface.size else 0.0)
    n = int(np.floor(budget * s.size))
    if not s.size or n >= s.size:
        return DEPTH_EDGE
    level = float(np.partition(s, s.size - 1 - n)[s.size - 1 - n])
    return level if level >= ROUGH_LEVEL * DEPTH_EDGE else DEPTH_EDGE


def edge_budget(surface_pixels: float) -> float:
    """The share of a view's `surface_pixels` its outlines may take: `EDGE_LINES` lines across a square of that
    area (10% of a 128x128 view, 3.9% of 256x256, 2% of 512x512)."""
    return EDGE_LINES / max(float(np.sqrt(max(surface_pixels, 1.0))), 1.0)


def depth_edges(depth: np.ndarray, opacity: np.ndarray | None = None, rel: float | None = None) -> np.ndarray:
    """Barrier pixels (bool (H, W)) of a z-depth map: far sides of depth discontinuities, and no surface.
    A pixel p is an edge where, along a row or a column, a neighbour is nearer than the line through p and the
    other neighbour predicts (the second difference over `rel` x w(p)) and nearer than p itself by half that (a
    step, not a bend). The border lines have no neighbour on one side and are never edges along that axis.
    `rel` defaults to the view's `edge_level`. (On depth rougher than `DEPTH_EDGE` itself the 2D parts are off:
    see `fit_parts`.)"""
    w, surface = inverse_depth(depth, opacity)
    rel = edge_level(depth, opacity) if rel is None else rel
    edge = np.zeros(w.shape, bool)
    for axis in (0, 1):
        p, lo, hi = _neighbours(w, axis)
        e = _step(p, lo, hi) > rel * p
        if axis == 0:
            edge[1:-1, :] |= e
        else:
            edge[:, 1:-1] |= e
    return edge | ~surface


def depth_edges_within(where: np.ndarray, depth: np.ndarray, opacity: np.ndarray | None = None) -> np.ndarray:
    """`depth_edges` on the pixels `where` (bool (H, W)), False elsewhere, at the whole view's `edge_level`:
    evaluated on their bounding box and a 1-px margin, since an edge pixel depends on its 4 neighbours only (a
    patch's anchors need a fraction of a full-resolution view: 12 ms of a 32-ms patch on the fox capture's 781-px
    view)."""
    out = np.zeros(np.shape(depth), bool)
    ys, xs = np.nonzero(where)
    if len(ys):
        box = (slice(max(ys.min() - 1, 0), ys.max() + 2), slice(max(xs.min() - 1, 0), xs.max() + 2))
        out[box] = depth_edges(np.asarray(depth)[box], None if opacity is None else np.asarray(opacity)[box],
                               edge_level(depth, opacity))
    return out & where


def camera_points(depth: np.ndarray, fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """Camera-space points (H, W, 3) (x right, y down, z forward) of a z-depth map; pixel centres at +0.5."""
    z = np.asarray(depth, np.float64)
    h, w = z.shape
    u = (np.arange(w, dtype=np.float64)[None, :] + 0.5 - cx) / fx
    v = (np.arange(h, dtype=np.float64)[:, None] + 0.5 - cy) / fy
    return np.stack([u * z, v * z, z], -1)


def surface_normals(points: np.ndarray) -> np.ndarray:
    """Unit normals (H, W, 3) of camera-space points by central differences, turned to face the camera."""
    du = np.roll(points, -1, 1) - np.roll(points, 1, 1)
    dv = np.roll(points, -1, 0) - np.roll(points, 1, 0)
    n = np.cross(du, dv)
    n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
    n[(n * points).sum(-1) > 0] *= -1.0
    return n


def creases(depth: np.ndarray, surface: np.ndarray, intrinsics: tuple[float, float, float, float],
            tau: float = CREASE, step: int = CREASE_STEP) -> np.ndarray:
    """Concave-crease pixels (bool (H, W)) of a z-depth map: where the normals `step` pixels to each side
    (along a row or a column) turn towards each other by more than `tau` (module docstring)."""
    z = np.asarray(depth, np.float64)
    surface = np.asarray(surface, bool) & np.isfinite(z) & (z > 0)
    pts = camera_points(np.where(surface, z, 1.0), *intrinsics)
    n = surface_normals(pts)
    # a normal is only read where the surface is continuous across its stencil: a 2-px pole in front of
    # the floor has no usable normal, and its outline is a depth edge already
    w = np.where(surface, 1.0 / np.maximum(pts[..., 2], 1e-9), 0.0)
    valid = surface.copy()
    for axis in (0, 1):
        for sh in (1, -1):
            valid &= np.roll(surface, sh, axis) & (np.abs(np.roll(w, sh, axis) - w) < CONTINUOUS * w)
    out = np.zeros(surface.shape, bool)
    for axis in (0, 1):
        pa, pb = np.roll(pts, step, axis), np.roll(pts, -step, axis)
        na, nb = np.roll(n, step, axis), np.roll(n, -step, axis)
        d = pb - pa
        turn = ((nb - na) * d).sum(-1) / np.maximum(np.linalg.norm(d, axis=-1), 1e-12)
        ok = valid & np.roll(valid, step, axis) & np.roll(valid, -step, axis)
        out |= ok & (turn < -tau)
    b = step + 1  # rolled-in borders compare against the opposite side of the image
    out[:b], out[-b:], out[:, :b], out[:, -b:] = False, False, False, False
    _, lab, stats, _ = cv2.connectedComponentsWithStats(out.astype(np.uint8), connectivity=8)
    keep = np.maximum(stats[:, cv2.CC_STAT_WIDTH], stats[:, cv2.CC_STAT_HEIGHT]) >= CREASE_MIN * (2 * step + 1)
    keep[0] = False  # the background label
    return keep[lab]


def join_band(mask: np.ndarray, band: np.ndarray) -> np.ndarray:
    """`mask` plus the `band` pixels whose nearest non-band pixel is in it: a crease band splits down its
    middle between the surfaces it separates. OpenCV's labelled distance transform (5x5 Euclidean mask) finds the
    nearest pixels: scipy.ndimage's exact one agreed on 98.6% of the pixels of 50 random bands (ties differ), took 4x
    as long, and importing scipy.ndimage cost a session's first patch 430 ms."""
    band = np.asarray(band, bool)
    if not band.any():
        return mask
    _, nearest = cv2.distanceTransformWithLabels(band.astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_5,
                                                 labelType=cv2.DIST_LABEL_PIXEL)
    joins = np.zeros(int(nearest.max()) + 1, bool)  # per non-band pixel's label: whether it is in the mask
    joins[nearest[~band]] = np.asarray(mask, bool)[~band]
    return mask | (band & joins[nearest])


def grow(candidates: np.ndarray, seeds: np.ndarray, barrier: np.ndarray | None = None) -> np.ndarray:
    """The pixels of `candidates | seeds` (minus `barrier`) 4-connected to a seed pixel (a diagonal
    step would cross a one-pixel barrier line) (bool (H, W))."""
    allowed = (np.asarray(candidates, bool) | seeds)
    if barrier is not None:
        allowed &= ~barrier
    start = seeds & allowed
    if not start.any():
        return np.zeros_like(allowed)
    _, lab = cv2.connectedComponents(allowed.astype(np.uint8), connectivity=4)
    keep = np.unique(lab[start])
    return np.isin(lab, keep[keep > 0])


def fill_holes(mask: np.ndarray, barrier: np.ndarray | None = None, depth: np.ndarray | None = None) -> np.ndarray:
    """`mask` with its holes filled (regions of ~mask not touching the image border), except holes through
    the object: ones that hold a barrier pixel, are over `SPECK` of the mask's area and, given the z-depth,
    lie behind the mask around them by more than `HOLE_DEPTH` (relative inverse depth). A printed label's
    letters join the can, a torus's hole onto the floor does not, and a patch of depth noise on a trained
    surface (no deeper than its rim) is filled."""
    inv = (~np.asarray(mask, bool)).astype(np.uint8)
    n, lab, stats, _ = cv2.connectedComponentsWithStats(inv, connectivity=4)
    if n <= 1:
        return mask.copy()
    border = np.unique(np.concatenate([lab[0], lab[-1], lab[:, 0], lab[:, -1]]))
    bad = set(border.tolist())
    if barrier is not None:
        walled = np.unique(lab[barrier & (inv > 0)])
        walled = walled[stats[walled, cv2.CC_STAT_AREA] > SPECK * max(int(np.count_nonzero(mask)), 1)]
        for k in walled.tolist():
            if k in bad:
                continue
            if depth is None or _hole_behind(lab == k, mask, depth):
                bad.add(k)
    holes = np.setdiff1d(np.arange(1, n), np.array(sorted(bad), dtype=np.int64))
    return mask | np.isin(lab, holes)


def _hole_behind(hole: np.ndarray, mask: np.ndarray, depth: np.ndarray) -> bool:
    """Whether a hole's surface lies behind the mask's pixels around it (median inverse depths)."""
    rim = (cv2.dilate(hole.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0) & mask
    z = np.asarray(depth, np.float64)
    zh, zr = z[hole & (z > 0)], z[rim & (z > 0)]
    if not zh.size or not zr.size:
        return True
    wh, wr = float(np.median(1.0 / zh)), float(np.median(1.0 / zr))
    return wr - wh > HOLE_DEPTH * wr


_RING4 = np.array([[0, 1, 0], [1, 0, 1], [0, 1, 0]], np.float32)


def _neighbour_mean(values: np.ndarray, where: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(mean of `values` over each pixel's 4-neighbours in `where`, how many there are)."""
    total = cv2.filter2D(np.where(where, values, 0.0).astype(np.float32), -1, _RING4, borderType=cv2.BORDER_CONSTANT)
    count = cv2.filter2D(where.astype(np.float32), -1, _RING4, borderType=cv2.BORDER_CONSTANT)
    return total / np.maximum(count, 1.0), count


def attach(mask: np.ndarray, candidates: np.ndarray, depth: np.ndarray, opacity: np.ndarray,
           rounds: int = ATTACH_ROUNDS) -> np.ndarray:
    """`mask` with the candidate pixels on its border that belong to its surface (module docstring): a surface
    pixel 4-adjacent to the mask joins when its inverse depth is nearer to the mean of its neighbours in the mask
    than to the mean of its other surface neighbours outside (or it has none: the background); one ring a round."""
    out = np.asarray(mask, bool).copy()
    ys, xs = np.nonzero(out)
    if not ys.size:
        return out
    pad = rounds + 2  # what the rounds can reach, and the neighbours they read
    box = (slice(max(ys.min() - pad, 0), ys.max() + pad + 1), slice(max(xs.min() - pad, 0), xs.max() + pad + 1))
    w, surface = inverse_depth(np.asarray(depth)[box], np.asarray(opacity)[box])
    m = out[box]  # a view: rounds write into `out`
    ok = np.asarray(candidates, bool)[box] & surface
    for _ in range(rounds):
        inside, n_in = _neighbour_mean(w, m)
        ring = (n_in > 0) & ~m & ok
        if not ring.any():
            break
        outside, n_out = _neighbour_mean(w, ~m & ~ring & surface)
        take = ring & ((n_out == 0) | (np.abs(w - inside) < np.abs(w - outside)))
        if not take.any():
            break
        m |= take
    return out


@dataclass(frozen=True)
class GeometryParts:
    """Which geometry parts a mask uses (bench mask measures each): depth-edge barriers, seeded growth
    with seeds carried between views through the surface points, hole filling, the voxel 3D clean-up of
    cleanup3d (applied last), concave-crease barriers, the views' vote on each other's pixels, and the
    border pixels' attachment by depth (`attach`), and the band along the mask's border re-decided on the view's
    photo (core.select.image_edges; only where the views' images are given)."""

    edges: bool = True
    grow: bool = True
    holes: bool = True
    cleanup3d: bool = True
    creases: bool = True
    vote: bool = True
    attach: bool = True
    image: bool = True

    @staticmethod
    def none() -> "GeometryParts":
        return GeometryParts(False, False, False, False, False, False, False, False)

    def names(self) -> list[str]:
        return [k for k in ("edges", "grow", "holes", "cleanup3d", "creases", "vote", "attach", "image")
                if getattr(self, k)]


# 'basic' is the voxel clean-up only; 'full' (the default) adds every other part, where the depth allows it
# (fit_parts). At the patch's automatic threshold on trained 128-px fields of the photo-like presets (600 steps)
# basic gave bread 0.066, lemon 0.264, toys 0.149 and full 0.893, 0.820, 0.633 (0.936, 0.931, 0.776 with
# `attach`, which also took demo 0.965 -> 0.984 and thin 0.845 -> 0.930); on tests/test_selection.py's tiny
# 32-px field full gave 0.734 against basic's 0.944 (its rough depth cut the sphere with edges): fit_parts now
# turns the 2D parts off there.
BASIC_PARTS = GeometryParts(edges=False, grow=False, holes=False, cleanup3d=True, creases=False, vote=False,
                            attach=False, image=False)
FULL_PARTS = GeometryParts()
GEOMETRY_NAMES = ("basic", "full")
DEFAULT_GEOMETRY = "full"


def fit_parts(parts: GeometryParts, depths: list[np.ndarray], opacities: list[np.ndarray]) -> GeometryParts:
    """`parts` without the 2D geometry (edges, growth, holes, creases, vote, attach) when the views' depth is too rough
    for it: its median noise (`depth_noise`) reaches `DEPTH_EDGE`, so no depth step can be told from the
    roughness (a 32-px trained field: ~3%, where depth edges cut its objects into specks; 128-px fields ~0.7%).
    The voxel clean-up, which needs only surface points, stays."""
    clean_up_only = replace(GeometryParts.none(), cleanup3d=parts.cleanup3d)
    if parts == clean_up_only:  # no 2D part asked for
        return parts
    return clean_up_only if rough_depth(depths, opacities) else parts


def rough_depth(depths: list[np.ndarray], opacities: list[np.ndarray | None]) -> bool:
    """Whether the views' rendered depth is too rough for depth edges: its median noise (`depth_noise`) reaches
    `DEPTH_EDGE` (views with under 16 surface pixels do not count)."""
    noise = [depth_noise(w, surface) for w, surface in map(inverse_depth, depths, opacities) if surface.sum() >= 16]
    return bool(noise) and float(np.median(noise)) >= DEPTH_EDGE


def parts_named(name: str) -> GeometryParts:
    """The geometry parts a selection names: 'basic' (BASIC_PARTS) or 'full' (FULL_PARTS)."""
    from repaint_nerf.core.errors import UserError

    if name not in GEOMETRY_NAMES:
        raise UserError(f"unknown selection geometry {name!r}", hint="use 'basic' or 'full'")
    return FULL_PARTS if name == "full" else BASIC_PARTS


DEFAULT_PARTS = parts_named(DEFAULT_GEOMETRY)

VOTE_MARGIN = 2  # views against per view for: at 1 (a tie drops) the trained toys lost its can's lower half
# wherever two of 8 views had not grown it (128 px, 100 views, 2000 steps: 0.667 -> 0.784; 24 views, 600 steps:
# 0.776 -> 0.810); trained demo, thin, bread, lemon within +-0.003, ground-truth depth on 8 presets min 0.910
SEED_DEPTH_TOL = 0.015  # a projected seed point lands on a view's surface when its depth agrees this well (relative)
MAX_SEED_POINTS = 4000
SEED_MARGIN = 2  # pixels between a seed point's pixel and the mask's border or a barrier


def surface_points(mask: np.ndarray, depth: np.ndarray, cameras, view: int) -> np.ndarray:
    """Field-space points (N, 3) of the pixels of `mask` on view `view`'s rendered z-depth."""
    import torch

    idx = np.flatnonzero(mask)
    if not idx.size:
        return np.zeros((0, 3), np.float32)
    w = np.shape(mask)[1]
    ii = torch.from_numpy(idx)
    o, d, dz = cameras.rays(torch.full_like(ii, int(view)), ii % w, ii // w)  # only the masked pixels' rays
    t = torch.as_tensor(np.asarray(depth, np.float32).reshape(-1)[idx]).to(o) / dz
    return (o + d * t[:, None]).cpu().numpy().astype(np.float32)


def project_seeds(points: np.ndarray, depths: list[np.ndarray], cameras, tol: float = SEED_DEPTH_TOL
                  ) -> list[np.ndarray]:
    """Pixels of each view of `cameras` (bool (H, W) per view of `depths`) where one of `points` is seen: it
    projects inside the image and its depth agrees with the view's rendered depth (not hidden behind another
    surface). All views at once (`project_into`)."""
    out = [np.zeros(np.shape(d), bool) for d in depths]
    if len(points):
        stack = depth_stack(depths)
        for _, seen, u, v in project_into(points, stack, cameras, range(len(depths)), tol):
            for k in np.flatnonzero(seen.any(1)):
                out[k][v[k][seen[k]], u[k][seen[k]]] = True
    return out


def depth_stack(depths: list[np.ndarray], surface: list[np.ndarray] | None = None) -> np.ndarray:
    """The views' z-depth maps as one float32 (V, H, W) array, 0 off `surface` and where a smaller view is padded
    (views may differ in size): a depth of 0 sees no point in front of the camera (`seen_pixels`)."""
    h = max(np.shape(d)[0] for d in depths)
    w = max(np.shape(d)[1] for d in depths)
    out = np.zeros((len(depths), h, w), np.float32)
    for k, d in enumerate(depths):
        d = np.asarray(d, np.float32)
        out[k, :d.shape[0], :d.shape[1]] = d if surface is None else np.where(surface[k], d, 0.0)
    return out


PROJECT_CHUNK = 1 << 21  # (view, point) pairs projected at once: ~100 MB of temporaries


def project_into(points: np.ndarray, stack: np.ndarray, cameras, views, tol: float = SEED_DEPTH_TOL):
    """Project `points` (P, 3) into the views `views` (V indices of `cameras`) whose depth maps are `stack`
    (V, H, W), in chunks of points: yields (point indices, seen (V, p) bool, u, v (V, p)) per chunk (`seen_pixels`)."""
    import torch

    views = torch.as_tensor(list(views), dtype=torch.long)
    step = max(1, PROJECT_CHUNK // max(1, len(views)))
    pts = torch.from_numpy(np.ascontiguousarray(points, np.float32))
    for a in range(0, len(pts), step):
        uv, z = cameras.project_views(pts[a:a + step], views)
        seen, u, v = seen_pixels(uv.cpu().numpy(), z.cpu().numpy(), stack, tol)
        yield np.arange(a, min(a + step, len(pts))), seen, u, v


def seen_pixels(uv: np.ndarray, z: np.ndarray, depth: np.ndarray, tol: float = SEED_DEPTH_TOL
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Which of the points projected to pixels `uv` (P, 2) at depths `z` (P,) a view with z-depth map `depth`
    (H, W) sees: in front of the camera, inside the image, and at the depth the view renders there (not hidden
    behind another surface). Returns (seen (P,) bool, u, v) with u, v clipped to the image where not seen.
    With a stack of V views' maps (V, H, W) (`depth_stack`), `uv` (V, P, 2) and `z` (V, P) hold the points
    projected into each view, and so do the results."""
    h, w = depth.shape[-2:]
    ok = (z > 0) & np.isfinite(uv).all(-1)  # points behind the camera project nowhere
    u = np.floor(np.where(ok, uv[..., 0], -1)).astype(np.int64)
    v = np.floor(np.where(ok, uv[..., 1], -1)).astype(np.int64)
    ok &= (u >= 0) & (u < w) & (v >= 0) & (v < h)
    u, v = np.where(ok, u, 0), np.where(ok, v, 0)
    at = depth[v, u] if depth.ndim == 2 else depth[np.arange(len(depth))[:, None], v, u]
    return ok & (np.abs(at - z) < tol * np.maximum(z, 1e-9)), u, v


MAX_ANCHORS = 512  # surface points kept from a free-view patch (a saved selection holds them)
VOTE_VIEWS = 8  # training views rendered to vote on a free-view patch's threshold (Selection.refine_auto_threshold)


def patch_anchors(patch_px: np.ndarray, similarity: np.ndarray, depth: np.ndarray, opacity: np.ndarray, cameras,
                  threshold: float, rng_seed: int = 0) -> np.ndarray:
    """Field-space surface points (N, 3) of a patch drawn in a view that is not a training view (the editor's free
    camera, `cameras` holding that one view at the maps' size): the patch's pixels on the object (similarity above
    `threshold`, opaque, off depth edges and away from the object's border), at most `MAX_ANCHORS` of them.
    `anchor_seeds` carries them into the training views, where they seed the geometry as a training-view patch does."""
    depth = np.asarray(depth, np.float32)
    opacity = np.asarray(opacity, np.float32)
    on = np.asarray(patch_px, bool) & (np.asarray(similarity) > threshold) & (opacity > MIN_OPACITY)
    on &= ~depth_edges_within(on, depth, opacity)
    pts = surface_points(_interior(on), depth, cameras, 0)
    if len(pts) > MAX_ANCHORS:
        pts = pts[np.random.default_rng(rng_seed).choice(len(pts), MAX_ANCHORS, replace=False)]
    return pts


def anchor_views(points: np.ndarray, cameras, limit: int = VOTE_VIEWS) -> list[int]:
    """Up to `limit` views of `cameras` (indices, best first) in which most of `points` (field space, (P, 3)) project
    in front of the camera and inside the image, the points' centre nearest the image centre first. No depth is
    needed: the views' maps are rendered after they are chosen, and where another surface hides the points
    they seed nothing (`anchor_seeds`)."""
    import torch

    pts = np.asarray(points, np.float32).reshape(-1, 3)
    n = len(cameras)
    if not len(pts) or not n or limit < 1:
        return []
    cams = cameras.to("cpu")
    uv, z = cams.project_views(torch.from_numpy(pts), torch.arange(n))
    inside = cams.in_image(uv, z, torch.arange(n)).numpy()
    uv = uv.double().numpy()
    w, h = cams.width.double().numpy()[:, None], cams.height.double().numpy()[:, None]
    share = inside.mean(1)
    count = np.maximum(inside.sum(1), 1)
    cu = np.where(inside, uv[..., 0] / w, 0.0).sum(1) / count  # the points' centre in image fractions
    cv = np.where(inside, uv[..., 1] / h, 0.0).sum(1) / count
    off = np.hypot(cu - 0.5, cv - 0.5)
    order = sorted((i for i in range(n) if share[i] >= 0.5), key=lambda i: (-round(share[i], 2), off[i], i))
    return order[:limit]


def anchor_seeds(points: np.ndarray, depths: list[np.ndarray], cameras) -> list[tuple[int, np.ndarray]]:
    """(view, bool (H, W) pixels) of every view of `cameras` that sees one of `points` (`project_seeds`)."""
    px = project_seeds(np.asarray(points, np.float32), depths, cameras)
    return [(i, p) for i, p in enumerate(px) if p.any()]


def _region(sim: np.ndarray, t: float, seeds: np.ndarray, barrier: np.ndarray, band: np.ndarray | None,
            depth: np.ndarray, parts: GeometryParts) -> np.ndarray:
    region = grow(sim > t, seeds, barrier)
    if band is not None:
        region = join_band(region, band & ((sim > t) | seeds))
    if not parts.holes:
        return region
    walls = barrier if band is None else barrier & ~band
    # close notches as well as holes: a printed label's stripes that reach the silhouette are not enclosed
    closed = cv2.morphologyEx(region.astype(np.uint8), cv2.MORPH_CLOSE, np.ones((CLOSE, CLOSE), np.uint8)) > 0
    region = region | (closed & ~walls & (depth > 0))
    return fill_holes(region, walls, depth)


def _interior(mask: np.ndarray) -> np.ndarray:
    """`mask` eroded by up to `SEED_MARGIN` pixels: less where that would leave under a quarter of it (a pole
    two pixels wide keeps its own pixels)."""
    m = mask.astype(np.uint8)
    for r in range(SEED_MARGIN, 0, -1):
        e = cv2.erode(m, np.ones((2 * r + 1,) * 2, np.uint8)) > 0
        if 4 * int(e.sum()) >= int(m.sum()):
            return e
    return mask


def _interior_points(masks: list[np.ndarray], barriers: list[np.ndarray], depths: list[np.ndarray], cameras, rng,
                     limit: int) -> np.ndarray:
    """Surface points of the masks' pixels up to `SEED_MARGIN` pixels from the mask's border and from any
    barrier (a silhouette pixel's depth blends two surfaces; a contact-line pixel is where the object
    and its support meet, so it lands on the support in another view), at most `limit` of them."""
    pts = np.concatenate([surface_points(_interior(m & ~b), depths[i], cameras, i)
                          for i, (m, b) in enumerate(zip(masks, barriers))])
    if len(pts) > limit:
        pts = pts[rng.choice(len(pts), limit, replace=False)]
    return pts


def vote(masks: list[np.ndarray], depths: list[np.ndarray], surface: list[np.ndarray], cameras,
         tol: float = SEED_DEPTH_TOL) -> list[np.ndarray]:
    """The masks without the pixels that the other views outvote: a pixel's surface point, where another
    view with a mask sees it (projects onto that view's surface at the same depth), counts for it when it
    lands inside that view's mask and against it otherwise; it is dropped when more than `VOTE_MARGIN` times
    as many views count against as for.
    A leak across one view's contact line is outside the other views' masks; a part of the object seen
    by one view only has no votes and stays; a part that some views' masks have not reached yet (their growth
    stopped at a groove a texture left in the depth) is not outvoted by them alone."""
    voters = [i for i, m in enumerate(masks) if m.any()]
    if len(voters) < 2:
        return list(masks)
    stack = depth_stack([depths[j] for j in voters], [surface[j] for j in voters])
    inside = np.zeros(stack.shape, bool)
    for k, j in enumerate(voters):
        inside[k, :masks[j].shape[0], :masks[j].shape[1]] = masks[j]
    rows = np.arange(len(voters))[:, None]
    row_of = {j: k for k, j in enumerate(voters)}
    out = []
    for i, m in enumerate(masks):
        if i not in row_of:
            out.append(m)
            continue
        pts = surface_points(m, depths[i], cameras, i)
        pro = np.zeros(len(pts), np.int64)
        against = np.zeros(len(pts), np.int64)
        for at, seen, u, v in project_into(pts, stack, cameras, voters, tol):
            seen[row_of[i]] = False  # a view does not vote on itself
            hit = inside[rows, v, u]
            pro[at] = (seen & hit).sum(0)
            against[at] = (seen & ~hit).sum(0)
        keep = m.copy().reshape(-1)
        keep[np.flatnonzero(m)[against > VOTE_MARGIN * pro]] = False
        out.append(keep.reshape(m.shape))
    return out


def view_barriers(depths: list[np.ndarray], surface: list[np.ndarray], cameras, parts: GeometryParts
                  ) -> tuple[list[np.ndarray], list[np.ndarray | None]]:
    """Per view: the barrier pixels growth may not cross (depth edges, creases, no surface) and the crease
    band (None without creases), which the grown region later splits with its neighbour."""
    barriers, bands = [], []
    for i, (d, ok) in enumerate(zip(depths, surface)):
        b = depth_edges(d, ok.astype(np.float32)) if parts.edges else ~ok
        band = None
        if parts.creases:
            k = (float(cameras.fx[i]), float(cameras.fy[i]), float(cameras.cx[i]), float(cameras.cy[i]))
            band = creases(d, ok, k) & ~b
            b = b | band
        barriers.append(b)
        bands.append(band)
    return barriers, bands


def geometric_masks(sims: list[np.ndarray], depths: list[np.ndarray], opacities: list[np.ndarray], cameras,
                    seeds: list[tuple[int, np.ndarray]], threshold: float, parts: GeometryParts = GeometryParts(),
                    rounds: int = 3, rng_seed: int = 0) -> list[np.ndarray]:
    """Masks (bool (H, W) per view) of `similarity > threshold` shaped by the field's geometry.

    `seeds`: (view, bool (H, W) pixels) the user marked on the object (the patch). With `parts.grow`, a
    view's mask is the part of its candidates connected to seed pixels: first the marked views, then,
    `rounds` times, every view seeded by the surface points of all masks so far that it sees (so the
    far side of an object is reached through the views between); with `parts.vote` the views vote on
    each other's pixels after each round (`vote`), and on the first masks where several views are seeded (a
    free-view patch's anchors: on a trained bread field one view's first mask took the loaf's board, and its
    points grew the board in every view: the editor's way 0.07, with this vote 0.97). Without growth, every
    candidate is kept.
    """
    n = len(sims)
    depths = [np.asarray(d, np.float32) for d in depths]
    surface = [np.asarray(o) > MIN_OPACITY for o in opacities]
    barriers, bands = view_barriers(depths, surface, cameras, parts)
    if not parts.grow:
        masks = [(np.asarray(s) > threshold) & ok & ~b for s, ok, b in zip(sims, surface, barriers)]
        masks = [m if band is None else join_band(m, band & (np.asarray(s) > threshold))
                 for m, band, s in zip(masks, bands, sims)]
        return [fill_holes(m, b, d) for m, b, d in zip(masks, barriers, depths)] if parts.holes else masks
    seed_px = [np.zeros(np.shape(s), bool) for s in sims]
    for view, px in seeds:
        seed_px[view] |= np.asarray(px, bool) & surface[view]

    def voted(ms: list[np.ndarray]) -> list[np.ndarray]:  # the marked pixels stay whatever the other views say
        return [m | seed_px[i] for i, m in enumerate(vote(ms, depths, surface, cameras))] if parts.vote else ms

    masks = [_region(sims[i], threshold, seed_px[i], barriers[i], bands[i], depths[i], parts) if seed_px[i].any()
             else np.zeros(np.shape(sims[i]), bool) for i in range(n)]
    masks = voted(masks)  # several seeded views (a free-view patch's anchors): one view's leak must not seed the rest
    rng = np.random.default_rng(rng_seed)
    for _ in range(rounds):
        pts = _interior_points(masks, barriers, depths, cameras, rng, MAX_SEED_POINTS)
        new = []
        for i, carried in enumerate(project_seeds(pts, depths, cameras)):
            s = (seed_px[i] | carried) & ((np.asarray(sims[i]) > threshold) | seed_px[i])
            new.append(_region(sims[i], threshold, s, barriers[i], bands[i], depths[i], parts))
        new = voted(new)
        if all((a == b).all() for a, b in zip(new, masks)):
            break
        masks = new
    return masks
