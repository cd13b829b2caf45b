"""Similarity maps and masks (paper's mask equation: M = cos(q, F(x)) > alpha) for one view or every
training view from one selection, with a per-view cache of rendered feature maps so a new query or a
new threshold costs one matrix product per view, not a render.

Masks on disk (what the repaint reads): WS/masks/mask_0000.png ... (uint8, 255 = selected, one per
training view in order) and WS/masks/index.json naming the view of each file.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable

import cv2
import numpy as np
import torch
from torch import Tensor

from repaint_nerf.core.errors import UserError, WorkspaceError
from repaint_nerf.core.select.similarity import cosine_similarity
from repaint_nerf.core.teachers.feature_default import DEFAULT_THRESHOLD
from repaint_nerf.core.workspace import atomic, integrity

# DEFAULT_THRESHOLD, alpha of the mask equation, is the one the default teacher's kernel is tuned for
# (bench mask, demo preset, 600 steps: IoU 0.964 at 0.5, best 0.972 at 0.6; 0.945 at 0.35, 0.717 at 0.9).
MASK_INDEX = "index.json"
# A view's features for a selection are the first surface's (RenderOptions.feature_first_surface): a nearer object
# that covers the selected one is not blended with the object behind it where it is only partly opaque on the ray
# (its silhouette, a soft surface). Measured on trained 128-px fields (24 views, 600 steps, default teacher), same
# field before/after: 'occluded' with the patch on the can's red body auto 0.919 -> 0.920, best 0.937 -> 0.940, the
# nearer toys' pixels in the masks 80 -> 68 (of 6438 can pixels); toys auto 0.916 -> 0.917; demo 0.990 -> 0.990. No
# extra samples or render: the same compositing with a mask on the weights.
FIRST_SURFACE = True
# The views' masks are shaped on maps whose long side is at most MAP_SIDE px (0: the views' own size), then brought
# to each view's size and their outline re-decided on its photo (`shaped_masks`). The geometry's pixel constants
# (crease stencil, closing, attach rounds) were tuned on 128-px views, and rendering a view's maps is most of a
# selection's cost: snowmiku (81 views, 512x384, contracted) rendered 4.35 s a view, 352 of select's 423 s.
MAP_SIDE = 256


def check_threshold(threshold: float) -> float:
    """The threshold as a float in [0, 1], else a UserError."""
    try:
        t = float(threshold)
    except (TypeError, ValueError):
        raise UserError(f"threshold '{threshold}' is not a number", hint="give a value in [0, 1]") from None
    if not 0.0 <= t <= 1.0 or t != t:
        raise UserError(f"threshold {threshold} is outside [0, 1]",
                        hint=f"cosine similarity thresholds lie in [0, 1]; the default is {DEFAULT_THRESHOLD}")
    return t


def similarity_map(features: Tensor, positives: Tensor, negatives: Tensor | None = None) -> Tensor:
    """Similarity (H, W) of a feature map (H, W, F) to a selection's queries.

    One query: its cosine similarity. Several positives: the best of them (a union of matches). With
    negatives: a pixel at least as similar to some negative as to every positive gets min(s, 0), so it is
    never selected at a threshold >= 0. All queries go through one matrix product.
    """
    pos = positives.reshape(-1, positives.shape[-1]) if positives.dim() > 1 else positives[None]
    n_pos = pos.shape[0]
    if n_pos == 0:
        raise UserError("the selection has no positive patch", hint="select a patch on the object first")
    qs = pos if negatives is None or negatives.numel() == 0 else torch.cat(
        [pos, negatives.reshape(-1, pos.shape[-1]).to(pos)], 0)
    if features.shape[-1] != qs.shape[-1]:
        raise UserError(f"the query has {qs.shape[-1]} feature dimensions but the field renders "
                        f"{features.shape[-1]}", hint="make a new selection with this workspace's field")
    sims = cosine_similarity(features, qs)
    s = sims[..., :n_pos].amax(-1)
    if qs.shape[0] > n_pos:
        neg = sims[..., n_pos:].amax(-1)
        s = torch.where(neg >= s, s.clamp(max=0.0), s)
    return s


def threshold_mask(similarity: Tensor, threshold: float) -> Tensor:
    """The paper's mask equation: similarity > threshold (bool, same shape)."""
    return similarity > check_threshold(threshold)


@dataclass
class ViewMaps:
    """What a view's masks need from the field: feature map (H, W, F) fp16, z-depth and opacity (H, W).

    `depth` is the median depth (where the ray's transmittance falls through 0.5): the geometry's surface
    points and barriers read it. On a trained toys can (128 px, 100 views, 2000 steps) the expected depth steps
    by up to 7% between neighbouring pixels below the label's band, where rays go on through a thin surface, and
    its creases and steps walled that part off (can 0.837 with it, 0.929 with the median). `expected_depth` (the
    renderer's 'depth') bounds the automatic threshold's region (`autothreshold.selection_auto_threshold`): its
    silhouette pixels blend the object with what lies behind and mark a two-pixel outline where the median's
    one-pixel step let the region of a torus through its hole at a lower threshold (0.50 for 0.78: 0.815 for
    0.928 on the same field); None: `depth` does both."""

    feature: Tensor
    depth: Tensor
    opacity: Tensor
    expected_depth: Tensor | None = None
    scale: float = 1.0  # of the view's camera the maps were rendered at (Cameras.scaled)

    def edge_depth(self) -> Tensor:
        """The depth the automatic threshold's region stops at (`expected_depth`, else `depth`)."""
        return self.depth if self.expected_depth is None else self.expected_depth


class ViewCache:
    """Rendered feature/depth/opacity maps per training view, kept while the field is unchanged.

    `token` identifies the field state (e.g. the training step or version id); a different token drops
    everything. Maps are stored in fp16 on the CPU (64x64x32 features: 0.26 MB a view). `get` renders a view at
    its own size (what a patch's pixels index); `mask_maps` at most `map_side` px on the long side (`MAP_SIDE`).
    """

    def __init__(self, field, grid, cameras, token=None, render_opts=None, map_side: int = MAP_SIDE):
        self.field, self.grid, self.cameras = field, grid, cameras
        self.token = token
        self.render_opts = render_opts
        self.map_side = int(map_side)
        self._maps: dict[int, ViewMaps] = {}
        self._small: dict[tuple[int, int], ViewMaps] = {}

    def reset(self, token=None) -> None:
        self.token = token
        self._maps.clear()
        self._small.clear()

    def __len__(self) -> int:
        return len(self._maps.keys() | {view for view, _ in self._small})

    def get(self, view: int) -> ViewMaps:
        """The maps of training view `view` at its own size, rendered on first use."""
        if view not in self._maps:
            self._maps[view] = render_view_maps(self.field, self.grid, self.cameras, view, self.render_opts)
        return self._maps[view]

    def mask_maps(self, view: int, side: int | None = None, held: bool = True) -> ViewMaps:
        """The maps view `view`'s mask is shaped on: its own size's when held (and `held`), else at `map_scale`
        for a long side of at most `side` px (default: the cache's `map_side`)."""
        if (held and view in self._maps) or not 0 <= int(view) < len(self.cameras):  # `get` says what is wrong
            return self.get(view)
        side = self.map_side if side is None else int(side)
        s = map_scale(int(self.cameras.width[view]), int(self.cameras.height[view]), side)
        if s >= 1.0:
            return self.get(view)
        if (view, side) not in self._small:
            self._small[view, side] = render_view_maps(self.field, self.grid, self.cameras, view, self.render_opts,
                                                       scale=s)
        return self._small[view, side]


def map_scale(width: int, height: int, side: int = MAP_SIDE) -> float:
    """The scale that brings a view's long side to at most `side` px (1 when it is smaller, or `side` is 0)."""
    long = max(int(width), int(height))
    return 1.0 if side <= 0 or long <= side else side / float(long)


def map_cameras(cameras, maps: list[ViewMaps]):
    """The views' cameras (on the CPU) at the size of their maps (`ViewMaps.scale`): what the geometry projects with."""
    from repaint_nerf.core.scene.cameras import Cameras

    cams = cameras.to("cpu")
    if all(m.scale == 1.0 for m in maps):
        return cams
    return Cameras.cat([cams[i] if m.scale == 1.0 else cams[i].scaled(m.scale) for i, m in enumerate(maps)])


def render_view_maps(field, grid, cameras, view: int, opts=None, cancel: Callable[[], bool] | None = None,
                     scale: float = 1.0) -> ViewMaps | None:
    """Render view `view`'s feature map, z-depth and opacity (field space) with the one renderer, at `scale` times
    its size; None when `cancel()` turns true meanwhile."""
    from repaint_nerf.core.render.renderer import RenderOptions, render_camera

    n = len(cameras)
    if not 0 <= int(view) < n:
        raise UserError(f"view {view} does not exist; the scene has {n} training views",
                        hint=f"choose --view between 0 and {n - 1}")
    base = opts or RenderOptions()
    opts = replace(base, outputs=("feature", "depth", "median_depth", "opacity"), background=None, perturb=False,
                   feature_first_surface=FIRST_SURFACE)
    out = render_camera(field, grid, cameras, int(view), opts, scale=scale, cancel=cancel)
    if out is None:
        return None
    return ViewMaps(out["feature"].to("cpu", torch.float16), out["median_depth"].float().cpu(),
                    out["opacity"].float().cpu(), out["depth"].float().cpu(), float(scale))


def masks_for_views(field, grid, cameras, selection, threshold: float | None = None, workspace=None,
                    cleanup: bool | None = None, cache: ViewCache | None = None, names: list[str] | None = None,
                    progress: Callable[[int, int], None] | None = None, parts=None,
                    refine: Callable[[list[np.ndarray]], list[np.ndarray]] | None = None,
                    training_views: bool = True, images: list[np.ndarray] | None = None) -> list[np.ndarray]:
    """Masks (bool (H, W) numpy) of every view of `cameras` from one selection; saved into `workspace`
    (WS/masks) when given. `cameras` are the training views its patches index unless `training_views` is
    False (test views: only the selection's anchors seed them). `cleanup` (default: the selection's) applies
    the field's geometry (`parts`, a geometry.GeometryParts, default: the parts the selection's `geometry`
    names) seeded by the selection's positive patches in training views, with `images` (the views' photos, in
    the order of `cameras`) for the parts that read them; `refine` (e.g.
    core.teachers.sam_refine.refine_masks bound to the views' images) maps the final masks."""
    from repaint_nerf.core.select.geometry import GeometryParts, fit_parts, parts_named

    t = check_threshold(selection.threshold if threshold is None else threshold)
    cache = cache if cache is not None else ViewCache(field, grid, cameras)  # an empty cache is falsy (__len__)
    n = len(cameras)
    sims, maps = [], []
    patched = {p.view for p in selection.patches} if training_views else set()  # a patch's pixels index its view
    for i in range(n):
        m = cache.get(i) if i in patched else cache.mask_maps(i)
        maps.append(m)
        sims.append(selection.similarity(m.feature))
        if progress:
            progress(i + 1, n)
    do_cleanup = selection.cleanup if cleanup is None else cleanup
    cams = map_cameras(cameras, maps)
    seeds = selection_seeds(selection, maps, cams, training_views, sims, t) if do_cleanup else []
    asked = (parts or parts_named(selection.geometry)) if seeds else GeometryParts.none()
    parts = fit_parts(asked, [m.depth.numpy() for m in maps], [m.opacity.numpy() for m in maps])
    if images is None:  # what ran, for the index: the photo's edges need the photos
        parts = replace(parts, image=False)
    out = shaped_masks(sims, maps, cams, seeds, t, parts, images, cameras.sizes())
    if refine is not None:
        out = [np.asarray(m, bool) for m in refine(out)]
    if workspace is not None:
        write_masks(workspace.masks_dir, out, names, {"threshold": t, "cleanup": bool(do_cleanup),
                                                      "geometry": parts.names(), "geometry_asked": asked.names()})
    return out


def selection_seeds(selection, maps: list[ViewMaps], cameras, training_views: bool = True,
                    sims: list[Tensor] | None = None, threshold: float | None = None) -> list[tuple[int, np.ndarray]]:
    """(view, bool (H, W)) seed pixels of a selection in the views of `cameras`: its positive patches drawn in
    those views (when they are the training views: a patch's `view` indexes those) and, given the views'
    similarity maps and the threshold, where the other views see those patches' surface points (`patch_seeds`),
    and the surface points of patches drawn elsewhere (the editor's free camera) where a view sees them
    (core.select.geometry.anchor_seeds)."""
    from repaint_nerf.core.select.autothreshold import patch_pixels
    from repaint_nerf.core.select.geometry import anchor_seeds

    n = len(maps)
    seeds = []
    for p in selection.patches:
        if training_views and p.positive and 0 <= p.view < n:
            seeds += patch_seeds(p.view, patch_pixels(tuple(maps[p.view].depth.shape), p), maps, cameras, sims,
                                 threshold)
    anchors = selection.anchor_points()
    if len(anchors):
        seeds += anchor_seeds(anchors, [m.depth.numpy() for m in maps], cameras.to("cpu"))
    return seeds


def patch_seeds(view: int, pixels: np.ndarray, maps: list[ViewMaps], cameras, sims: list[Tensor] | None = None,
                threshold: float | None = None) -> list[tuple[int, np.ndarray]]:
    """Seeds of a patch drawn in view `view` (its `pixels`, bool (H, W)): those pixels and, given the views'
    similarity maps and the threshold, the pixels where the other views see the patch's surface points (as a
    free-view patch's anchors seed them). Every view that sees the patch then grows its own first mask and the
    views vote on them (geometry.geometric_masks), so one view's leak does not seed the rest: on a trained lemon
    field the tray's patch view leaked onto the table through a gap in its contact line, and its points grew the
    table in every view (tray 0.155 on the median depth; 0.814 seeded this way)."""
    from repaint_nerf.core.select.geometry import anchor_seeds, patch_anchors

    seeds = [(view, pixels)]
    if sims is None or threshold is None:
        return seeds
    m = maps[view]
    points = patch_anchors(pixels, sims[view].float().cpu().numpy(), m.depth.numpy(), m.opacity.numpy(),
                           cameras.to("cpu")[view], threshold)
    return seeds + [(i, px) for i, px in anchor_seeds(points, [v.depth.numpy() for v in maps], cameras.to("cpu"))
                    if i != view]


def shaped_masks(sims: list[Tensor], maps: list[ViewMaps], cameras, seeds: list, threshold: float,
                 parts, images: list[np.ndarray] | None = None,
                 sizes: list[tuple[int, int]] | None = None) -> list[np.ndarray]:
    """`similarity > threshold` per view, shaped by the geometry `parts` (core.select.geometry) from seed
    pixels [(view, bool (H, W))] (`selection_seeds`), brought to the views' `sizes` ((H, W) each; None: the maps')
    and, given the views' photos, re-decided along their edges (core.select.image_edges); the one path the CLI,
    the editor and bench mask share. `cameras` are the views' at their maps' size (`map_cameras`)."""
    from repaint_nerf.core.scene.loaders.images import resize_image
    from repaint_nerf.core.select.cleanup3d import cleanup_masks
    from repaint_nerf.core.select.geometry import MIN_OPACITY, attach, geometric_masks

    cams = cameras.to("cpu")
    np_sims = [s.float().cpu().numpy() for s in sims]
    if parts.edges or parts.grow or parts.holes:
        masks = [torch.from_numpy(m) for m in geometric_masks(
            np_sims, [m.depth.numpy() for m in maps],
            [m.opacity.numpy() for m in maps], cams, seeds, threshold, parts)]
    else:
        masks = [s.cpu() > threshold for s in sims]
    if parts.cleanup3d and seeds:
        masks = cleanup_masks(masks, [m.depth for m in maps], [m.opacity for m in maps], cams, seeds)
    out = [m.cpu().numpy().astype(bool) for m in masks]
    if parts.attach and seeds:  # last: the clean-up drops silhouette pixels, whose depth blends two surfaces
        out = [attach(m, s > threshold, v.depth.numpy(), v.opacity.numpy()) for m, s, v in zip(out, np_sims, maps)]
    if sizes is not None:  # bilinear, as the maps are never larger than their views
        out = [m if m.shape == (h, w) else resize_image(m.astype(np.float32), w, h) > 0.5
               for m, (h, w) in zip(out, sizes)]
    if parts.image and seeds and images is not None:  # last: the photo decides the outline the geometry left
        from repaint_nerf.core.select.image_edges import snap_masks

        opacity = [v.opacity.numpy() for v in maps]
        if sizes is not None:
            opacity = [resize_image(o, w, h) for o, (h, w) in zip(opacity, sizes)]
        out = snap_masks(images, out, [o > MIN_OPACITY for o in opacity])
    return out


def mask_png(mask: np.ndarray) -> bytes:
    """A bool mask as PNG bytes (uint8, 255 = selected)."""
    ok, buf = cv2.imencode(".png", np.where(np.asarray(mask, bool), 255, 0).astype(np.uint8))
    if not ok:
        raise UserError("cannot encode a mask as PNG")
    return buf.tobytes()


def write_masks(folder: str | Path, masks: list[np.ndarray], names: list[str] | None = None,
                info: dict | None = None) -> list[Path]:
    """Write masks as mask_0000.png ... plus index.json into `folder` (atomically, file by file); the index holds
    each PNG's content hash and its own (core.workspace.integrity), so `load_masks` refuses a damaged mask."""
    folder = Path(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"cannot create the mask folder ({exc.strerror or exc})", folder,
                        hint="choose a folder you can write to") from exc
    paths = []
    views = []
    for i, m in enumerate(masks):
        p = folder / f"mask_{i:04d}.png"
        png = mask_png(m)
        atomic.write_bytes(p, png)
        paths.append(p)
        views.append({"view": i, "file": p.name, "name": names[i] if names else None,
                      "pixels": int(np.count_nonzero(m)), "sha256": integrity.bytes_digest(png)})
    atomic.write_sealed_json(folder / MASK_INDEX, {**(info or {}), "views": views})
    return paths


def load_masks(folder: str | Path) -> list[np.ndarray]:
    """Masks written by `write_masks` (e.g. WS/masks), in view order, as bool arrays."""
    folder = Path(folder)
    index = folder / MASK_INDEX
    if not index.is_file() and any(folder.glob("mask_*.png")):
        raise WorkspaceError("the masks index is missing (the mask files are here)", index,
                             hint=integrity.repair_hint(index, "run repaint-nerf select again"))
    if not index.is_file():
        raise WorkspaceError("no masks here (no index.json)", folder,
                             hint="make a selection first: repaint-nerf select WS --view I --patch x0,y0,x1,y1")
    import json

    again = "run repaint-nerf select again"
    try:
        text = index.read_text(encoding="utf-8")
        data = json.loads(text)
        if integrity.check_json_text(text, data) is False:
            raise ValueError("its content hash does not match: the file is damaged")
        views = data["views"]
        files = [(str(v["file"]), v.get("sha256")) for v in views]
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
        raise WorkspaceError(f"the mask index is unreadable ({exc})", index,
                             hint=integrity.repair_hint(index, again))
    out = []
    for name, digest in files:
        path = folder / name
        if Path(name).is_absolute() or not path.resolve().is_relative_to(folder.resolve()):
            raise WorkspaceError(f"the mask index names a file outside the masks folder ({name!r})", index,
                                 hint=integrity.repair_hint(index, again))
        data = path.read_bytes() if path.is_file() else b""
        img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE) if data else None
        if img is None or (digest is not None and integrity.bytes_digest(data) != digest):
            raise WorkspaceError("a mask file is missing or damaged", path, hint=integrity.repair_hint(path, again))
        out.append(img > 127)
    return out
