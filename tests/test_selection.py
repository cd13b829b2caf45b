"""Selection: cosine similarity, patch queries, the mask equation with several queries, the Selection
record, masks on disk, the 3D clean-up on an analytic field, and end-to-end masks and `select` on a tiny
trained synthetic scene against its ground-truth object masks."""
from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from torch import nn

from repaint_nerf.core.errors import UserError, WorkspaceError
from repaint_nerf.core.select import (Patch, Selection, ViewCache, cosine_similarity, load_masks,
                         masks_for_views, patch_query, similarity_map, threshold_mask, write_masks)
from repaint_nerf.core.workspace.workspace import Workspace


# -- similarity ---------------------------------------------------------------------------------------
def test_cosine_of_zero_vector_is_zero_not_nan():
    f = torch.zeros(3, 4, 8)
    f[0, 0] = torch.arange(8.0)
    q = torch.arange(8.0)
    s = cosine_similarity(f, q)
    assert torch.isfinite(s).all()
    assert s[0, 0] == pytest.approx(1.0, abs=1e-6)
    assert (s.reshape(-1)[1:] == 0).all()
    assert cosine_similarity(f, torch.zeros(8)).eq(0).all()  # a zero query, too


@pytest.mark.parametrize("mag", [1e20, 1e30, 3e38])
def test_cosine_of_huge_vectors_is_finite_and_right(mag):
    a = torch.tensor([[mag, mag, 0.0], [mag, -mag, 0.0], [0.0, 0.0, -mag]])
    s = cosine_similarity(a, torch.tensor([mag, mag, 0.0]))
    assert torch.isfinite(s).all()
    assert s.tolist() == pytest.approx([1.0, 0.0, 0.0], abs=1e-5)


def test_cosine_matches_reference_for_several_queries():
    g = torch.Generator().manual_seed(0)
    f, q = torch.randn(5, 7, 16, generator=g), torch.randn(3, 16, generator=g)
    ref = torch.nn.functional.cosine_similarity(f[..., None, :], q, dim=-1)
    assert torch.allclose(cosine_similarity(f, q), ref, atol=1e-5)
    assert torch.allclose(cosine_similarity(f.half(), q), ref, atol=3e-3)


# -- queries and the mask equation ------------------------------------------------------------------
def test_query_is_mean_of_patch_features():
    g = torch.Generator().manual_seed(1)
    f = torch.randn(10, 12, 6, generator=g)
    p = Patch(0, x0=3, y0=2, x1=7, y1=5)
    ref = torch.stack([f[y, x] for y in range(2, 5) for x in range(3, 7)]).mean(0)
    assert torch.allclose(patch_query(f, p), ref, atol=1e-6)
    sel = Selection()
    sel.add_patch(f, p)
    assert torch.allclose(sel.positives[0], ref, atol=1e-6)


def test_normalized_patch_from_editor_drag():
    f = torch.randn(20, 40, 4)
    sel = Selection()
    p = sel.add_patch(f, (0.25, 0.5, 0.5, 0.75))  # fractions of the image, as the editor passes them
    assert (p.x0, p.y0, p.x1, p.y1, p.view) == (10, 10, 20, 15, -1)
    assert torch.allclose(sel.positives[0], f[10:15, 10:20].reshape(-1, 4).mean(0))


def _regions() -> tuple[torch.Tensor, dict]:
    """A 4-region map: A = e1, B = e3, D = 0.6 e1 + 0.8 e2 (cos 0.6 to A), E = e2."""
    f = torch.zeros(8, 8, 4)
    e = torch.eye(4)
    f[:4, :4], f[:4, 4:], f[4:, :4], f[4:, 4:] = e[0], e[2], 0.6 * e[0] + 0.8 * e[1], e[1]
    boxes = {"A": Patch(0, 0, 0, 4, 4), "B": Patch(0, 4, 0, 8, 4), "D": Patch(0, 0, 4, 4, 8),
             "E": Patch(0, 4, 4, 8, 8, positive=False)}
    return f, boxes


def _region_mask(names: str) -> torch.Tensor:
    m = torch.zeros(8, 8, dtype=torch.bool)
    where = {"A": (slice(0, 4), slice(0, 4)), "B": (slice(0, 4), slice(4, 8)), "D": (slice(4, 8), slice(0, 4)),
             "E": (slice(4, 8), slice(4, 8))}
    for n in names:
        m[where[n]] = True
    return m


def test_several_positive_and_negative_patches():
    f, b = _regions()
    sel = Selection(threshold=0.5)
    sel.add_patch(f, b["A"])
    assert torch.equal(sel.mask(f), _region_mask("AD"))  # D is a look-alike (cos 0.6 > 0.5)
    sel.add_patch(f, b["B"])  # a second positive: union of matches
    assert torch.equal(sel.mask(f), _region_mask("ABD"))
    sel.add_patch(f, b["E"])  # a negative: D is nearer E (0.8) than any positive (0.6) -> dropped
    assert torch.equal(sel.mask(f), _region_mask("AB"))
    assert len(sel.negatives) == 1 and sel.patches[-1].positive is False
    assert float(sel.similarity(f)[6, 1]) <= 0.0  # never selected at any threshold >= 0
    sel2 = Selection()
    sel2.add_patch(f, b["A"])
    sel2.add_patch(f, Patch(0, 4, 4, 8, 8), subtract=True)  # subtract= flips a positive patch
    assert torch.equal(sel2.mask(f, 0.5), _region_mask("A"))


def test_thresholds_zero_and_one_and_bad_thresholds():
    f, b = _regions()
    sel = Selection()
    sel.add_patch(f, b["A"])
    assert not sel.mask(f, 1.0).any()  # cos <= 1 and the equation is strict
    assert torch.equal(sel.mask(f, 0.0), sel.similarity(f) > 0)
    assert torch.equal(sel.mask(f, 0.0), _region_mask("AD"))
    for bad in (-0.1, 1.5, float("nan"), "x"):
        with pytest.raises(UserError):
            threshold_mask(sel.similarity(f), bad)


def test_bad_patches_and_dims():
    f = torch.randn(10, 10, 4)
    with pytest.raises(UserError, match="empty"):
        patch_query(f, Patch(0, 5, 5, 5, 8))
    with pytest.raises(UserError, match="outside"):
        patch_query(f, Patch(0, 5, 5, 11, 8))
    with pytest.raises(UserError, match="outside"):
        patch_query(f, Patch(0, -1, 0, 3, 3))
    with pytest.raises(UserError, match="four numbers"):
        Patch.parse("1,2,3", 0)
    with pytest.raises(UserError, match="no positive"):
        Selection().similarity(f)
    sel = Selection()
    sel.add_patch(f, Patch(0, 0, 0, 2, 2))
    with pytest.raises(UserError, match="dimensions"):
        sel.similarity(torch.randn(10, 10, 5))
    with pytest.raises(UserError, match="text encoder"):
        sel.add_text("a red ball", object())


def test_text_query_through_teacher_and_codec():
    class ClipLike:
        name = "cliplike"

        def encode_text(self, text):
            return np.array([0.0, 1.0, 0.0, 0.0], np.float32)

    class Codec:  # keeps dims 1 and 2: the field learns 2-dim codes
        def encode(self, f):
            return f[..., 1:3]

    f = torch.zeros(4, 4, 2)
    f[:2, :, 0] = 1.0
    f[2:, :, 1] = 1.0
    sel = Selection()
    sel.add_text("a red ball", ClipLike(), Codec())
    assert torch.equal(sel.mask(f, 0.5), f[..., 0] > 0)
    assert sel.texts == ["a red ball"]


def test_patch_to_mask_is_vectorised():
    # correctness of the hot path on a 256x256 map (its speed is a benchmark figure, not checked here)
    g = torch.Generator().manual_seed(3)
    f = torch.randn(256, 256, 32, generator=g).half()
    sel = Selection()
    sel.add_patch(f, Patch(0, 100, 100, 116, 116))
    q = f[100:116, 100:116].float().reshape(-1, 32).mean(0)
    ref = (f.float() @ q) / (f.float().norm(dim=-1) * q.norm()).clamp_min(1e-8)
    assert torch.allclose(sel.similarity(f), ref, atol=1e-4)


# -- the record and the files -----------------------------------------------------------------------
def test_selection_round_trip_in_workspace(tmp_path):
    ws = Workspace.create(tmp_path / "ws")
    f, b = _regions()
    sel = Selection(threshold=0.3, cleanup=False, teacher="default")
    sel.add_patch(f, b["A"])
    sel.add_patch(f, b["E"])
    path = sel.save(ws)
    assert path.parent == ws.selections_dir and not list(ws.selections_dir.glob("*.tmp"))
    back = Selection.load(ws)
    assert back.patches == sel.patches and back.threshold == 0.3 and back.cleanup is False
    assert back.teacher == "default" and back.geometry == "full"  # the default
    assert torch.equal(back.mask(f), sel.mask(f))
    old = ws.selections_dir / "old.json"  # saved before the choice existed: the clean-up it was made with
    old.write_text(json.dumps({k: v for k, v in json.loads(path.read_text()).items() if k not in ("geometry", "sha256")}))
    assert Selection.load(ws, "old").geometry == "basic"
    sel.add_anchors(np.array([[0.1, -0.2, 0.3], [0.4, 0.5, -0.6]], np.float32))
    sel.save(ws, "full")
    back = Selection.load(ws, "full")
    assert back.geometry == "full" and np.allclose(back.anchor_points(), sel.anchor_points(), atol=1e-5)
    bad = ws.selections_dir / "bad_anchor.json"
    unsealed = {k: v for k, v in json.loads((ws.selections_dir / "full.json").read_text()).items() if k != "sha256"}
    bad.write_text(json.dumps({**unsealed, "anchors": [[1, 2]]}))  # as written before selections had a hash
    with pytest.raises(WorkspaceError, match="anchor"):
        Selection.load(ws, "bad_anchor")
    sel.save(ws, "odd")
    odd = ws.selections_dir / "odd.json"
    odd.write_text(json.dumps({**unsealed, "geometry": "wobbly"}))
    with pytest.raises(WorkspaceError, match="unknown geometry 'wobbly'"):
        Selection.load(ws, "odd")
    sealed = json.loads((ws.selections_dir / "full.json").read_text())
    (ws.selections_dir / "edited.json").write_text(json.dumps({**sealed, "threshold": 0.9}))
    with pytest.raises(WorkspaceError, match="content hash"):  # a sealed selection changed behind its back
        Selection.load(ws, "edited")
    (ws.selections_dir / "broken.json").write_text("{")
    with pytest.raises(WorkspaceError):
        Selection.load(ws, "broken")
    with pytest.raises(WorkspaceError):
        Selection.load(ws, "missing")


def test_masks_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    masks = [rng.random((6, 9)) > 0.5 for _ in range(3)]
    write_masks(tmp_path / "m", masks, ["a", "b", "c"], {"threshold": 0.5})
    back = load_masks(tmp_path / "m")
    assert all(np.array_equal(a, b) for a, b in zip(masks, back))
    index = json.loads((tmp_path / "m" / "index.json").read_text())
    assert [v["name"] for v in index["views"]] == ["a", "b", "c"] and index["threshold"] == 0.5
    assert cv2.imread(str(tmp_path / "m" / "mask_0001.png"), cv2.IMREAD_UNCHANGED).max() == 255
    with pytest.raises(WorkspaceError):
        load_masks(tmp_path / "none")


# -- 3D clean-up on an analytic field -------------------------------------------------------------
class Balls(nn.Module):
    """Opaque balls with a constant unit feature each (a stand-in for a trained field); `radius`: one for all, or
    one per ball."""

    def __init__(self, centers, radius, features):
        super().__init__()
        self.register_buffer("c", torch.tensor(centers, dtype=torch.float32))
        self.register_buffer("f", torch.tensor(features, dtype=torch.float32))
        self.register_buffer("r", torch.as_tensor(radius, dtype=torch.float32))
        self.bound = 1.0

    def _inside(self, x):
        return (torch.cdist(x, self.c) <= self.r)

    def density(self, x):
        return self._inside(x).any(-1).float() * 200.0

    def forward(self, x, d, outputs=("rgb",)):
        inside = self._inside(x)
        out = {"sigma": inside.any(-1).float() * 200.0}
        if "rgb" in outputs:
            out["rgb"] = torch.full((x.shape[0], 3), 0.5)
        if "feature" in outputs:
            out["feature"] = inside.float() @ self.f
        return out


def _ring_cameras(n=4, size=32, dist=2.6):
    from repaint_nerf.core.scene.cameras import Cameras, look_at

    poses = [look_at((dist * math.cos(a), dist * math.sin(a), 1.2), (0, 0, 0)) for a in
             np.linspace(0, 2 * math.pi, n, endpoint=False) + 0.3]
    f = 0.5 * size / math.tan(0.5 * 0.9)
    return Cameras.create(np.stack(poses), f, f, size / 2, size / 2, size, size)


def _ball_gt(cams, i, center, radius):
    o, d, _ = cams.image_rays(i)
    oc = o - torch.tensor(center)
    b = (oc * d).sum(-1)
    disc = b * b - (oc * oc).sum(-1) + radius ** 2
    return (disc > 0).reshape(int(cams.height[i]), int(cams.width[i]))


def test_cleanup_drops_a_disconnected_look_alike(tmp_path):
    from repaint_nerf.core.render.renderer import RenderOptions

    # ball 0 is the object; ball 1 looks the same (same feature) but is elsewhere; ball 2 differs
    centers = [(0.35, 0.0, 0.0), (-0.4, -0.3, 0.0), (-0.2, 0.45, 0.0)]
    field = Balls(centers, 0.22, [[1, 0, 0], [1, 0, 0], [0, 1, 0]])
    cams = _ring_cameras()
    cache = ViewCache(field, None, cams, render_opts=RenderOptions(max_samples=96))
    gt0 = _ball_gt(cams, 0, centers[0], 0.22)
    ys, xs = np.nonzero(gt0.numpy())
    cy, cx = int(np.median(ys)), int(np.median(xs))
    sel = Selection(threshold=0.5)
    sel.add_patch(cache.get(0).feature, Patch(0, cx - 1, cy - 1, cx + 2, cy + 2))
    raw = masks_for_views(field, None, cams, sel, cleanup=False, cache=cache)
    ws = Workspace.create(tmp_path / "ws")
    clean = masks_for_views(field, None, cams, sel, cleanup=True, cache=cache, workspace=ws)
    assert len(cache) == len(cams)  # one render per view, shared by both calls

    gts = [_ball_gt(cams, i, centers[0], 0.22).numpy() for i in range(len(cams))]
    both = [g | _ball_gt(cams, i, centers[1], 0.22).numpy() for i, g in enumerate(gts)]
    assert _iou(raw, both) > 0.85  # the 2D mask takes the look-alike too
    assert _iou(raw, gts) < 0.75
    assert _iou(clean, gts) > 0.85  # the 3D clean-up keeps only the patch's ball
    saved = load_masks(ws.masks_dir)
    assert all(np.array_equal(a, b) for a, b in zip(saved, clean))


def test_masks_render_through_the_cache_they_are_given_even_an_empty_one(monkeypatch):
    """The editor hands `masks_for_views` a fresh ViewCache with the trained sample budget: its renders go through
    that cache and its options, not through a new cache at the renderer's default budget (an empty cache is falsy:
    on the fox capture every view then marched 4x the budget, 7.5 s a view instead of 2.3)."""
    from repaint_nerf.core.render import renderer
    from repaint_nerf.core.render.renderer import RenderOptions
    from repaint_nerf.core.select.masks import render_view_maps

    centers = [(0.35, 0.0, 0.0), (-0.4, -0.3, 0.0), (-0.2, 0.45, 0.0)]
    field = Balls(centers, 0.22, [[1, 0, 0], [1, 0, 0], [0, 1, 0]])
    cams, opts = _ring_cameras(), RenderOptions(max_samples=96)
    gt0 = _ball_gt(cams, 0, centers[0], 0.22).numpy()
    ys, xs = np.nonzero(gt0)
    cy, cx = int(np.median(ys)), int(np.median(xs))
    sel = Selection(threshold=0.5)
    sel.add_patch(render_view_maps(field, None, cams, 0, opts).feature, Patch(0, cx - 1, cy - 1, cx + 2, cy + 2))
    budgets = []
    real = renderer.render_camera
    monkeypatch.setattr(renderer, "render_camera",
                        lambda f, g, c, i, o=None, **k: (budgets.append(o.max_samples), real(f, g, c, i, o, **k))[1])
    cache = ViewCache(field, None, cams, render_opts=opts)
    masks_for_views(field, None, cams, sel, cache=cache)
    assert len(cache) == len(cams) and budgets == [96] * len(cams)


def test_masks_shaped_on_smaller_maps_come_out_at_the_views_size_and_keep_the_clean_up():
    """Views larger than the cache's `map_side` are shaped on maps of that size (the patch's view stays at its own,
    which its pixels index) and come out at the view's size: the 3D clean-up still drops the look-alike, which
    needs the cameras scaled to the maps (`map_cameras`), and the masks match those shaped at full size."""
    from repaint_nerf.core.render.renderer import RenderOptions
    from repaint_nerf.core.scene.cameras import Cameras
    from repaint_nerf.core.select.masks import map_cameras, map_scale

    centers = [(0.35, 0.0, 0.0), (-0.4, -0.3, 0.0), (-0.2, 0.45, 0.0)]
    field = Balls(centers, 0.22, [[1, 0, 0], [1, 0, 0], [0, 1, 0]])
    cams, opts = _ring_cameras(size=96), RenderOptions(max_samples=96)
    gts = [_ball_gt(cams, i, centers[0], 0.22).numpy() for i in range(len(cams))]
    ys, xs = np.nonzero(gts[0])
    cy, cx = int(np.median(ys)), int(np.median(xs))
    out = {}
    for side in (0, 48):
        cache = ViewCache(field, None, cams, render_opts=opts, map_side=side)
        sel = Selection(threshold=0.5)
        sel.add_patch(cache.get(0).feature, Patch(0, cx - 3, cy - 3, cx + 4, cy + 4))
        out[side] = masks_for_views(field, None, cams, sel, cleanup=True, cache=cache)
        maps = [cache.mask_maps(i) for i in range(len(cams))]
        assert [m.depth.shape[0] for m in maps] == ([96] * 4 if side == 0 else [96, 48, 48, 48])  # view 0: the patch's
        scaled = map_cameras(cams, maps)
        assert scaled.width.tolist() == [m.depth.shape[1] for m in maps]
    assert all(m.shape == (96, 96) for m in out[48])
    both = [g | _ball_gt(cams, i, centers[1], 0.22).numpy() for i, g in enumerate(gts)]
    # the ball is ~16 px across at 48 px: its outline moves by up to a map pixel (no photo to snap it to here)
    assert _iou(out[0], gts) > 0.95 and _iou(out[48], gts) > 0.85 and _iou(out[48], both) < 0.75
    assert _iou(out[48], out[0]) > 0.85
    assert map_scale(96, 48, 32) == pytest.approx(1 / 3) and map_scale(96, 48, 0) == 1.0 and map_scale(20, 30, 32) == 1.0
    two = Cameras.cat([cams[1], cams[0].scaled(0.5)])
    assert two.width.tolist() == [96, 48] and torch.equal(two.c2w[0], cams.c2w[1])


class HazeBeforeWall(nn.Module):
    """A half-transparent sheet (x in [0.1, 0.15], optical thickness 1.2: 70% opaque) in front of an opaque wall
    (x >= 0.5): a thin surface a trained field's rays go on through."""

    def __init__(self):
        super().__init__()
        self.bound = 1.0

    def density(self, x):
        sheet = ((x[:, 0] >= 0.1) & (x[:, 0] <= 0.15)).float() * 24.0
        return sheet + (x[:, 0] >= 0.5).float() * 1000.0

    def forward(self, x, d, outputs=("rgb",)):
        out = {"sigma": self.density(x)}
        if "rgb" in outputs:
            out["rgb"] = torch.full((x.shape[0], 3), 0.5)
        if "feature" in outputs:
            out["feature"] = torch.ones(x.shape[0], 2)
        return out


def test_view_maps_put_the_surface_where_the_ray_turns_opaque_and_keep_the_expected_depth_for_edges():
    """The selection's surface points read the median depth: on a 70%-opaque sheet before a wall it is the
    sheet's, where the expected depth lies between the two (it blends them, as at a silhouette); the expected
    depth is kept for the automatic threshold's edges (ViewMaps.edge_depth)."""
    from repaint_nerf.core.render.renderer import RenderOptions
    from repaint_nerf.core.scene.cameras import Cameras, look_at
    from repaint_nerf.core.select.masks import render_view_maps

    cam = Cameras.create(look_at((-1.0, 0.0, 0.0), (1.0, 0.0, 0.0))[None], 20.0, 20.0, 4.0, 4.0, 8, 8)
    m = render_view_maps(HazeBeforeWall(), None, cam, 0, RenderOptions(max_samples=512))
    z, ez = m.depth.numpy(), m.expected_depth.numpy()
    assert np.all(np.abs(z - 1.1) < 0.05)  # median: inside the sheet (T falls through 0.5 at ~1.13)
    assert np.all(ez > 1.18) and np.all(ez < 1.3)  # expected: ~0.7 x 1.12 + 0.3 x 1.5 = 1.23 blends the two
    assert m.edge_depth() is m.expected_depth


def _free_camera(size=48):
    """A camera between the ring's views, as the editor's free camera (not a training view)."""
    from repaint_nerf.core.scene.cameras import Cameras, look_at

    f = 0.5 * size / math.tan(0.45)
    return Cameras.create(look_at((0.5, -2.4, 1.9), (0, 0, 0))[None], f, f, size / 2, size / 2, size, size)


def _editor_on_balls(scene_factory, tmp_path):
    """(engine, ball centres, free camera, patch) for the editor's way on the balls: ball 0 is the object, ball 1
    its look-alike (same feature), ball 2 differs; the patch (image fractions) lies on ball 0 in the free camera."""
    from types import SimpleNamespace

    from repaint_nerf.core.engine import Engine

    eng = Engine("cpu")
    eng.load(scene_factory("demo", size=24, views=6, test_views=2), workspace=tmp_path / "ws")
    centers = [(0.35, 0.0, 0.0), (-0.4, -0.3, 0.0), (-0.2, 0.45, 0.0)]
    eng.field, eng.grid = Balls(centers, 0.22, [[1, 0, 0], [1, 0, 0], [0, 1, 0]]), None
    eng.field.cfg = SimpleNamespace(feature_dim=3)
    free = _free_camera()
    ys, xs = np.nonzero(_ball_gt(free, 0, centers[0], 0.22).numpy())
    cy, cx = np.median(ys) / 48, np.median(xs) / 48
    return eng, centers, free, (cx - 0.05, cy - 0.05, cx + 0.05, cy + 0.05)


def test_the_overlay_shows_the_selected_ball_not_its_look_alike(scene_factory, tmp_path):
    """The editor's mask overlay thresholds Engine's 'region' map (Selection.region_map): in the patch's free
    view and after the camera moves to a training view, `region > t` holds the patch's ball and none of the
    look-alike ball of its feature that `similarity > t` also covers; a view that sees no anchor has none."""
    import cv2

    from repaint_nerf.core.scene.cameras import Cameras, look_at

    eng, centers, free, patch = _editor_on_balls(scene_factory, tmp_path)
    picked = eng.select(free, patch)
    t = picked.auto_threshold
    train = eng.scene.field_cameras("train").to("cpu")
    apart = []  # training views that see both balls apart (where they touch at 24 px no depth edge parts them)
    for i in range(6):
        a, b = (_ball_gt(train, i, c, 0.22).numpy().astype(np.uint8) for c in centers[:2])
        if a.sum() and b.sum() and not (cv2.dilate(a, np.ones((3, 3), np.uint8)) & b).any():
            apart.append(i)
    moved = train[torch.tensor(apart[:1])]
    frame = eng.render(moved, outputs=("rgb",), full=True)
    for cam, sim, region in ((free, picked.similarity, picked.region), (moved, frame["similarity"], frame["region"])):
        ball, look_alike = (_ball_gt(cam, 0, c, 0.22).numpy() for c in centers[:2])
        look_alike &= ~ball
        assert region is not None and region.shape == sim.shape and (region <= sim).all()
        assert (sim > t)[look_alike].mean() > 0.8  # the raw threshold covers the look-alike
        assert not (region > t)[look_alike].any()
        assert (region > t)[ball].mean() > 0.8
    away = Cameras.create(look_at((0.0, 2.4, 0.3), (0.0, 6.0, 0.0))[None], 40.0, 40.0, 24, 24, 48, 48)
    assert eng.render(away, outputs=("rgb",), full=True).get("region") is None  # no anchor in view: raw similarity


def test_a_free_view_patch_seeds_the_training_views(tmp_path):
    """The editor's patch is drawn in a camera that is not a training view: its surface points (anchors) carry it
    into the training views, so the 3D clean-up drops the look-alike there too; without them nothing is seeded."""
    from repaint_nerf.core.render.renderer import RenderOptions
    from repaint_nerf.core.select.autothreshold import patch_pixels
    from repaint_nerf.core.select.geometry import patch_anchors
    from repaint_nerf.core.select.masks import render_view_maps

    centers = [(0.35, 0.0, 0.0), (-0.4, -0.3, 0.0), (-0.2, 0.45, 0.0)]
    field = Balls(centers, 0.22, [[1, 0, 0], [1, 0, 0], [0, 1, 0]])
    cams = _ring_cameras()
    free = _free_camera()
    opts = RenderOptions(max_samples=96)
    fm = render_view_maps(field, None, free, 0, opts)
    gt = _ball_gt(free, 0, centers[0], 0.22).numpy()
    ys, xs = np.nonzero(gt)
    cy, cx = int(np.median(ys)), int(np.median(xs))
    patch = Patch(-1, cx - 2, cy - 2, cx + 3, cy + 3)
    sel = Selection(threshold=0.5)
    sel.add_patch(fm.feature, patch)
    sim = sel.similarity(fm.feature).numpy()
    pts = patch_anchors(patch_pixels(sim.shape, patch), sim, fm.depth.numpy(), fm.opacity.numpy(), free, 0.5)
    assert len(pts) and np.abs(np.linalg.norm(pts - np.array(centers[0]), axis=1) - 0.22).max() < 0.05  # on ball 0
    cache = ViewCache(field, None, cams, render_opts=opts)
    unseeded = masks_for_views(field, None, cams, sel, cleanup=True, cache=cache)
    sel.add_anchors(pts)
    seeded = masks_for_views(field, None, cams, sel, cleanup=True, cache=cache)

    gts = [_ball_gt(cams, i, centers[0], 0.22).numpy() for i in range(len(cams))]
    both = [g | _ball_gt(cams, i, centers[1], 0.22).numpy() for i, g in enumerate(gts)]
    assert _iou(unseeded, both) > 0.85 and _iou(unseeded, gts) < 0.75  # no seed: the look-alike stays
    assert _iou(seeded, gts) > 0.85


def test_a_training_view_patch_walled_in_everywhere_takes_the_views_median():
    """selection_auto_threshold: a patch drawn in a training view from above, which sees only the upper ball of a
    two-colour object (walled in at every threshold: no leak, so its value is its view's floor, split by a
    look-alike of the upper colour), is refined by the training views that see its surface points: none of them
    leaks either, so every one votes (autothreshold.walled_views_threshold) and their median, lower, stands."""
    from repaint_nerf.core.render.renderer import RenderOptions
    from repaint_nerf.core.scene.cameras import Cameras, look_at
    from repaint_nerf.core.select.autothreshold import (patch_auto_threshold_px, patch_pixels,
                                                        selection_auto_threshold, uses_edges)
    from repaint_nerf.core.select.geometry import anchor_views, patch_anchors

    a, b, c = [1.0, 0.0, 0.0], [0.55, math.sqrt(1 - 0.55 ** 2), 0.0], [0.8, 0.0, 0.6]
    centers = [(0.0, 0.0, 0.2), (0.0, 0.0, -0.2), (0.0, 0.9, 0.0)]  # the object's two parts, a look-alike of a
    field = Balls(centers, [0.3, 0.25, 0.25], [a, b, c])
    size = 48
    f = 0.5 * size / math.tan(0.45)
    poses = [look_at((0.3, 0.0, 3.0), (0, 0, 0))] + [look_at((2.6 * math.cos(t), 2.6 * math.sin(t), 1.2), (0, 0, 0))
                                                      for t in np.linspace(0, 2 * math.pi, 6, endpoint=False) + 0.3]
    cams = Cameras.create(np.stack(poses), f, f, size / 2, size / 2, size, size)
    lower = _ball_gt(cams, 0, centers[1], 0.25).numpy() & ~_ball_gt(cams, 0, centers[0], 0.3).numpy()
    assert not lower.any()  # the patch's view does not see the object's lower part
    cache = ViewCache(field, None, cams, render_opts=RenderOptions(max_samples=96))
    ys, xs = np.nonzero(_ball_gt(cams, 0, centers[0], 0.3).numpy())
    cx, cy = int(np.median(xs)), int(np.median(ys))
    sel = Selection()
    sel.add_patch(cache.get(0).feature, Patch(0, cx - 1, cy - 1, cx + 2, cy + 2))
    m = cache.get(0)
    sim = sel.similarity(m.feature).float().numpy()
    px = patch_pixels(sim.shape, sel.patches[0])
    own = patch_auto_threshold_px(sim, px, m.edge_depth(), m.opacity, edges=uses_edges(sel))
    assert own.jump is None and own.value > 0.7  # its view's floor splits the object's colour from the look-alike
    points = patch_anchors(px, sim, m.depth.numpy(), m.opacity.numpy(), cams[0:1], own.value)
    voters = [i for i in anchor_views(points, cams) if i != 0]
    others = sel._voters(points, [cache.get(i) for i in voters], cams[torch.tensor(voters)])
    assert len(others) >= 4 and all(o.jump is None for o in others)
    auto = selection_auto_threshold(sel, cache, 0)
    assert auto == pytest.approx(float(np.median([own.value] + [o.value for o in others])))
    assert auto < own.value - 0.2


def test_views_outside_the_training_set_take_a_training_patch_only_through_its_surface_points(tmp_path):
    """A patch's `view` indexes the training views: masks of other cameras (test views) must not read it as their
    own view's pixels, which here lie on the look-alike ball; the patch's surface points seed them instead."""
    from repaint_nerf.core.render.renderer import RenderOptions
    from repaint_nerf.core.select.autothreshold import patch_pixels
    from repaint_nerf.core.select.geometry import patch_anchors
    from repaint_nerf.core.select.masks import render_view_maps

    centers = [(0.35, 0.0, 0.0), (-0.4, -0.3, 0.0), (-0.2, 0.45, 0.0)]
    field = Balls(centers, 0.22, [[1, 0, 0], [1, 0, 0], [0, 1, 0]])
    cams = _ring_cameras()
    others = cams[[2, 3, 0, 1]]  # the same ring in another order: view 1 there is training view 3
    opts = RenderOptions(max_samples=96)
    m = render_view_maps(field, None, cams, 1, opts)
    ys, xs = np.nonzero(_ball_gt(cams, 1, centers[0], 0.22).numpy())
    cy, cx = int(np.median(ys)), int(np.median(xs))
    patch = Patch(1, cx - 2, cy - 2, cx + 3, cy + 3)
    sel = Selection(threshold=0.5)
    sel.add_patch(m.feature, patch)
    cache = ViewCache(field, None, others, render_opts=opts)
    gts = [_ball_gt(others, i, centers[0], 0.22).numpy() for i in range(len(others))]
    misread = masks_for_views(field, None, others, sel, cleanup=True, cache=cache)  # as if they were training views
    unseeded = masks_for_views(field, None, others, sel, cleanup=True, cache=cache, training_views=False)
    sim = sel.similarity(m.feature).numpy()
    sel.add_anchors(patch_anchors(patch_pixels(sim.shape, patch), sim, m.depth.numpy(), m.opacity.numpy(),
                                  cams[1:2], 0.5))
    seeded = masks_for_views(field, None, others, sel, cleanup=True, cache=cache, training_views=False)
    assert _iou(misread, gts) < 0.1  # the patch's pixels in the other set's view 1 grew the look-alike
    assert 0.3 < _iou(unseeded, gts) < 0.75  # no seed: both look-alikes
    assert _iou(seeded, gts) > 0.9


def test_the_editors_patch_shapes_every_training_views_mask(scene_factory, tmp_path):
    """Engine.select in a free camera keeps the patch's surface points, and the masks it then applies to the
    training views (what the repaint reads) leave out the look-alike ball."""
    eng, centers, free, patch = _editor_on_balls(scene_factory, tmp_path)
    own = eng.select(free, patch).auto_threshold
    pts = eng.selection.anchor_points()
    assert eng.selection.cleanup and len(pts)
    assert np.abs(np.linalg.norm(pts - np.array(centers[0]), axis=1) - 0.22).max() < 0.05
    cams = eng.scene.field_cameras("train").to("cpu")
    gts = [_ball_gt(cams, i, centers[0], 0.22).numpy() for i in range(6)]
    look_alike = [_ball_gt(cams, i, centers[1], 0.22).numpy() & ~g for i, g in enumerate(gts)]
    assert sum(int(g.sum()) for g in look_alike) > 20  # the training views do see the look-alike
    # the training views that see the patch's points vote on its threshold (the editor asks a frame later)
    assert eng.refine_threshold(own, cancel=lambda: True) is None  # the user moved on: nothing voted
    assert eng.selection.auto_threshold == own
    refined = eng.refine_threshold(own)
    assert 0.0 < refined < 1.0 and eng.selection.auto_threshold == refined
    for threshold in (0.5, refined):
        assert eng.masks_for_all_views(threshold) == 6
        assert sum(int((m & a).sum()) for m, a in zip(eng.masks, look_alike)) == 0
        assert sum(int((m & g).sum()) for m, g in zip(eng.masks, gts)) > 0.85 * sum(int(g.sum()) for g in gts)
    assert len(Selection.load(eng.workspace).anchors) == len(pts)
    with pytest.raises(UserError, match="unknown selection geometry"):
        eng.masks_for_all_views(0.5, "wobbly")
    assert eng.masks_for_all_views(0.5, "basic") == 6 and Selection.load(eng.workspace).geometry == "basic"
    eng.clear_selection()
    assert eng.refine_threshold(own) is None  # nothing selected: nothing to refine


# -- end to end on a tiny trained scene -----------------------------------------------------------
E2E_STEPS = 800
# 32x32, 12 views, a shrunk field, measured over seeds 0-3: 400 steps gave IoU 0.29-0.87 (the field had not
# separated the objects in every run), 800 steps 0.908-0.952 with every view's IoU at least 0.51. The 0.9
# target belongs to bench mask.
E2E_IOU = 0.8


def _tiny_field_config():
    """A real NGPField, shrunk so a test trains it in seconds (4 levels, 2^12 table, small feature grid)."""
    from repaint_nerf.core.field.field import default_field_config

    return default_field_config("cpu", 32, levels=4, log2_table=12, finest_res=64, hidden=32, feature_levels=4,
                                feature_log2_table=12, feature_finest_res=32, compile=False)


@pytest.fixture(scope="module")
def trained_ws(scene_factory, tmp_path_factory):
    from repaint_nerf.core.scene.loaders.detect import load_scene
    from repaint_nerf.core.teachers.cache import build_feature_store
    from repaint_nerf.core.teachers.depth_sparse import depth_for_scene
    from repaint_nerf.core.teachers.feature_default import DefaultFeatureTeacher
    from repaint_nerf.core.train.stage1 import Stage1Trainer, TrainConfig

    root = scene_factory("demo", size=32, views=12)
    scene = load_scene(root)
    ws = Workspace.create(tmp_path_factory.mktemp("sel") / "ws", {"scene": str(root), "downscale": 1.0})
    store = build_feature_store(scene.train.images, DefaultFeatureTeacher(), ws.teachers_dir)
    cfg = TrainConfig(seed=0, rays_per_batch=512, max_samples=96, grid_resolution=32)
    trainer = Stage1Trainer(scene, ws, cfg, field_cfg=_tiny_field_config(), feature_targets=store.codes,
                            depth_priors=depth_for_scene(scene))
    trainer.plan(E2E_STEPS)
    trainer.train(steps=E2E_STEPS)
    trainer.save_version("reconstruction")
    meta = json.loads((root / "gt" / "objects.json").read_text())
    obj = meta["edited_object_id"]
    gts = [cv2.imread(str(root / "gt" / "train" / f"{Path(n).stem}_mask.png"), cv2.IMREAD_UNCHANGED) == obj
           for n in scene.train.names]
    return ws, trainer, scene, gts


def _patch_in(gts) -> Patch:
    from repaint_nerf.core.bench.teacher import place_patch

    view, (y0, y1, x0, x1) = place_patch(gts)
    return Patch(view, x0, y0, x1, y1)


def _iou(ms, gts) -> float:
    inter = sum(int(np.sum(m & g)) for m, g in zip(ms, gts))
    return inter / max(1, sum(int(np.sum(m | g)) for m, g in zip(ms, gts)))


@pytest.mark.slow
def test_masks_from_one_query_agree_across_views(trained_ws):
    ws, trainer, scene, gts = trained_ws
    cams = scene.field_cameras("train")
    p = _patch_in(gts)
    cache = ViewCache(trainer.field.eval(), trainer.grid, cams.to(trainer.device))
    sel = Selection()
    sel.add_patch(cache.get(p.view).feature, p)
    masks = masks_for_views(trainer.field, trainer.grid, cams.to(trainer.device), sel, cache=cache)
    assert _iou(masks, gts) > E2E_IOU
    per_view = [_iou([m], [g]) for m, g in zip(masks, gts) if g.sum() > 20]
    assert min(per_view) > 0.3  # every view, not just the patch's


@pytest.mark.slow
def test_select_cli_writes_masks_matching_ground_truth(trained_ws, tmp_path):
    from repaint_nerf.app.cli import main

    ws, trainer, scene, gts = trained_ws
    p = _patch_in(gts)
    out = tmp_path / "masks"
    rc = main(["select", str(ws.root), "--view", str(p.view), "--patch", f"{p.x0},{p.y0},{p.x1},{p.y1}",
               "--out", str(out)])
    assert rc == 0
    masks = load_masks(out)
    assert len(masks) == len(scene.train)
    assert _iou(masks, gts) > E2E_IOU
    assert all(np.array_equal(a, b) for a, b in zip(masks, load_masks(ws.masks_dir)))
    sel = Selection.load(ws)
    # without --threshold, select uses (and saves) the patch's automatic threshold
    assert sel.patches == [p] and sel.auto_threshold is not None and sel.threshold == sel.auto_threshold
    index = json.loads((ws.masks_dir / "index.json").read_text())
    assert index["geometry"] == ["cleanup3d"]
    # --geometry full: every geometry part shapes the saved masks
    assert main(["select", str(ws.root), "--view", str(p.view), "--patch", f"{p.x0},{p.y0},{p.x1},{p.y1}",
                 "--out", str(tmp_path / "full"), "--geometry", "full"]) == 0
    index = json.loads((ws.masks_dir / "index.json").read_text())
    # this 32-px field's depth is too rough for the 2D parts (fit_parts): asked for, and left out
    assert set(index["geometry_asked"]) == {"edges", "grow", "holes", "cleanup3d", "creases", "vote", "attach", "image"}
    assert index["geometry"] == ["cleanup3d"]
    assert Selection.load(ws).geometry == "full"  # saved with the selection, so a later mask pass uses it too
    assert len(load_masks(tmp_path / "full")) == len(scene.train)


@pytest.mark.slow
def test_select_cli_renders_at_the_trained_sample_budget(trained_ws, tmp_path, monkeypatch):
    """`select` renders the training views at the sample budget the field was trained with, as the editor renders it,
    not at the renderer's default 1024 steps (on the fox capture 4x the trained budget: 14.7 s a view, 3.3x the
    time, for masks that differ where the auto threshold does)."""
    import repaint_nerf.core.render.renderer as renderer
    from repaint_nerf.app.cli import main
    from repaint_nerf.core.session import open_trained

    ws, trainer, scene, gts = trained_ws
    budgets, real = [], renderer.render_camera
    monkeypatch.setattr(renderer, "render_camera",
                        lambda *a, **k: (budgets.append(a[4].max_samples), real(*a, **k))[1])
    p = _patch_in(gts)
    assert main(["select", str(ws.root), "--view", str(p.view), "--patch", f"{p.x0},{p.y0},{p.x1},{p.y1}",
                 "--out", str(tmp_path / "m")]) == 0
    trained = open_trained(ws.root).header.max_samples
    assert len(budgets) == len(scene.train) and set(budgets) == {trained} and trained < 1024


def test_select_cli_bad_inputs(trained_ws, tmp_path, capsys):
    from repaint_nerf.app.cli import main
    from repaint_nerf.core.train.checkpoint import Checkpoint
    from repaint_nerf.core.train.header import CheckpointHeader, GridFacts

    ws, trainer, scene, gts = trained_ws
    w = int(scene.train.cameras.width[0])
    base = ["select", str(ws.root), "--out", str(tmp_path / "o")]
    cases = {
        "outside": ["--view", "0", "--patch", f"0,0,{w + 5},4"],
        "empty": ["--view", "0", "--patch", "5,5,5,9"],
        "does not exist": ["--view", str(len(scene.train)), "--patch", "0,0,4,4"],
        "outside [0, 1]": ["--view", "0", "--patch", "0,0,4,4", "--threshold", "1.5"],
    }
    for msg, extra in cases.items():
        assert main(base + extra) == 2
        assert msg in capsys.readouterr().err
    nofeat = Workspace.create(tmp_path / "nofeat", {"scene": str(scene.root)})
    Checkpoint.of({"x": torch.zeros(1)}, CheckpointHeader(kind="stage1", field_config={"feature_dim": 0},
                                                          grid=GridFacts(16))).save(
        nofeat.checkpoints_dir / "stage1.safetensors")
    assert main(["select", str(nofeat.root), "--view", "0", "--patch", "0,0,4,4", "--out", str(tmp_path / "o")]) == 2
    assert "without a feature head" in capsys.readouterr().err


class SheetBeforeObject(HazeBeforeWall):
    """A selected object (an opaque wall at x >= 0.5, feature (0, 1)) half covered by a nearer object that is 70%
    opaque on the ray (a sheet at x in [0.1, 0.15] over y > 0, feature (1, 0)): a silhouette or a soft surface in
    front of the selected one."""

    def density(self, x):
        return super().density(x) * torch.where((x[:, 0] < 0.3) & (x[:, 1] <= 0), 0.0, 1.0)

    def forward(self, x, d, outputs=("rgb",)):
        out = super().forward(x, d, outputs)
        if "feature" in outputs:
            near = (x[:, 0] < 0.3).float()[:, None]
            out["feature"] = near * torch.tensor([1.0, 0.0]) + (1 - near) * torch.tensor([0.0, 1.0])
        return out


def test_a_nearer_object_that_covers_the_selected_one_is_not_selected():
    """The occlusion rule (issue 35): a pixel whose first surface is a nearer object is not the selected object.
    Against the plain reference: the covered pixels' feature is the nearer object's alone, so their similarity to
    the selected object's query is cos((1, 0), (0, 1)) = 0 and no threshold selects them; the object's own pixels
    keep 1. Composited along the ray (the old feature) they read 0.7 (1, 0) + 0.3 (0, 1): similarity 0.39, which a
    threshold under it would select."""
    from repaint_nerf.core.render.renderer import RenderOptions
    from repaint_nerf.core.scene.cameras import Cameras, look_at
    from repaint_nerf.core.select import masks as masks_mod

    cam = Cameras.create(look_at((-1.0, 0.0, 0.0), (1.0, 0.0, 0.0))[None], 20.0, 20.0, 4.0, 4.0, 8, 8)
    field = SheetBeforeObject()
    m = masks_mod.render_view_maps(field, None, cam, 0, RenderOptions(max_samples=512))
    # which image rows see the sheet: the ones whose first surface (median depth) is at ~1.1, not the wall's 1.5
    covered = m.depth.numpy() < 1.3
    assert 0 < covered.sum() < covered.size
    ys, xs = np.nonzero(~covered)
    sel = Selection()
    sel.add_patch(m.feature.float(), Patch(0, int(xs.min()), int(ys.min()), int(xs.min()) + 2, int(ys.min()) + 2))
    sim = sel.similarity(m.feature.float()).numpy()
    reference = np.where(covered, 0.0, 1.0)  # cos of the first surface's feature with the object's
    assert np.abs(sim - reference).max() < 0.02
    assert not (sim[covered] > 0.1).any()
    old = render_camera_features(field, cam, first_surface=False)
    old_sim = sel.similarity(old).numpy()
    assert np.all(np.abs(old_sim[covered] - 0.3 / math.sqrt(0.58)) < 0.05)  # the blend the rule removes


def render_camera_features(field, cam, first_surface: bool):
    from repaint_nerf.core.render.renderer import RenderOptions, render_camera

    out = render_camera(field, None, cam, 0, RenderOptions(outputs=("feature",), max_samples=512,
                                                           feature_first_surface=first_surface))
    return out["feature"].float()


def test_masks_of_every_view_leave_out_a_nearer_object_over_the_selected_one():
    """Through `masks_for_views` on three views of the field above, with the mask equation alone (no geometry: what
    the viewport's overlay draws, similarity > threshold): a patch on the selected object, at threshold 0.3, selects
    none of the pixels where the nearer sheet covers it, in any view. With the features composited along the ray
    (the old way) every covered pixel read 0.39 and was selected (the voxel clean-up also drops them on this field,
    whose sheet is apart from the object)."""
    from repaint_nerf.core.scene.cameras import Cameras, look_at

    eyes = [(-1.0, 0.0, 0.0), (-1.0, 0.05, 0.05), (-1.0, -0.05, 0.02)]
    c2w = torch.stack([torch.as_tensor(look_at(e, (1.0, 0.0, 0.0)), dtype=torch.float32) for e in eyes])
    cams = Cameras.create(c2w, 20.0, 20.0, 4.0, 4.0, 8, 8)
    field = SheetBeforeObject()
    cache = ViewCache(field, None, cams)
    covered = [cache.get(i).depth.numpy() < 1.3 for i in range(len(cams))]
    ys, xs = np.nonzero(~covered[0])
    sel = Selection()
    sel.add_patch(cache.get(0).feature.float(), Patch(0, int(xs.min()), int(ys.min()), int(xs.min()) + 2,
                                                      int(ys.min()) + 2))
    masks = masks_for_views(field, None, cams, sel, threshold=0.3, cache=cache, cleanup=False)
    for m, c in zip(masks, covered):
        assert c.any() and not (m & c).any()
        assert m[~c].mean() > 0.9  # the visible part of the object stays selected
    old = [sel.similarity(render_camera_features(field, cams[i], first_surface=False)).numpy() > 0.3
           for i in range(len(cams))]
    assert all(o[c].all() for o, c in zip(old, covered))


def test_join_band_splits_a_crease_band_down_its_middle_as_the_exact_transform_does():
    """A band pixel joins the mask when its nearest non-band pixel is in it: a band straddling the mask's edge
    splits down its middle, and on random bands the result matches scipy's exact distance transform (the
    reference) but for ties."""
    from scipy import ndimage

    from repaint_nerf.core.select.geometry import join_band

    mask = np.zeros((20, 40), bool)
    mask[:, :20] = True
    band = np.zeros_like(mask)
    band[:, 17:23] = True
    out = join_band(mask & ~band, band)
    assert out[:, :20].all() and not out[:, 20:].any()
    rng = np.random.default_rng(3)
    agree = total = 0
    for _ in range(20):
        m = np.zeros((64, 96), bool)
        m[:, :48] = True
        m ^= rng.random(m.shape) < 0.05
        b = np.zeros_like(m)
        c = int(rng.integers(10, 86))
        b[:, c - 3:c + 4] = True
        b |= rng.random(m.shape) < 0.02
        _, (iy, ix) = ndimage.distance_transform_edt(b, return_indices=True)
        ref = m | (b & m[iy, ix])
        agree += int((join_band(m, b) == ref)[b].sum())
        total += int(b.sum())
    assert agree / total > 0.97
