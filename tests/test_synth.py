"""Synthetic scenes: layout, determinism, ground truth consistent with the camera model, the edited variant."""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from repaint_nerf.core.errors import UserError
from repaint_nerf.core.scene.cameras import Cameras
from repaint_nerf.core.synth.generate import list_presets, make_scene

PRESETS = list(list_presets())
SIZE, VIEWS, TEST_VIEWS = 48, 3, 2


@pytest.fixture(scope="module")
def scenes(tmp_path_factory) -> dict[str, Path]:
    """Every preset, generated once for this module at 48 px."""
    root = tmp_path_factory.mktemp("synth")
    return {p: make_scene(p, root / p, size=SIZE, views=VIEWS, seed=3, test_views=TEST_VIEWS) for p in PRESETS}


def _read(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert img is not None, path
    if img.ndim == 3:
        img = img[..., [2, 1, 0, 3]] if img.shape[2] == 4 else img[..., ::-1]
    return img


def _cameras(meta: dict) -> Cameras:
    w, h = meta["w"], meta["h"]
    f = 0.5 * w / np.tan(0.5 * meta["camera_angle_x"])
    c2w = np.array([fr["transform_matrix"] for fr in meta["frames"]])
    return Cameras.create(c2w, f, f, w / 2, h / 2, w, h)


def _frames(scene: Path):
    """(split, i, image, depth, mask) for every view."""
    for split in ("train", "test"):
        meta = json.loads((scene / f"transforms_{split}.json").read_text())
        for i, fr in enumerate(meta["frames"]):
            assert fr["file_path"] == f"./{split}/r_{i}"
            yield (split, i, _read(scene / split / f"r_{i}.png"),
                   np.load(scene / "gt" / split / f"r_{i}_depth.npy"),
                   _read(scene / "gt" / split / f"r_{i}_mask.png"))


@pytest.mark.parametrize("preset", PRESETS)
def test_layout_and_ground_truth_agree(scenes, preset):
    scene = scenes[preset]
    objects = json.loads((scene / "gt" / "objects.json").read_text())
    ids = [o["id"] for o in objects["objects"]]
    assert ids == list(range(1, len(ids) + 1))
    assert objects["edited_object_id"] in ids
    assert all({"id", "name", "color", "bbox"} <= set(o) for o in objects["objects"])
    edit = json.loads((scene / "edited" / "edit.json").read_text())
    assert edit["object_id"] == objects["edited_object_id"] and edit["kind"] in ("recolor", "replace")
    opaque = objects["opaque"]
    for split, n in (("train", VIEWS), ("test", TEST_VIEWS)):
        meta = json.loads((scene / f"transforms_{split}.json").read_text())
        assert len(meta["frames"]) == n and meta["scene_kind"] in ("bounded", "forward", "unbounded")
        assert np.array(meta["aabb"]).shape == (2, 3)
        edited_meta = json.loads((scene / "edited" / f"transforms_{split}.json").read_text())
        assert edited_meta["frames"] == meta["frames"]
    seen_edited = 0
    for split, i, img, depth, mask in _frames(scene):
        assert img.shape == (SIZE, SIZE, 3 if opaque else 4) and img.dtype == np.uint8
        assert depth.shape == (SIZE, SIZE) and depth.dtype == np.float32
        assert mask.shape == (SIZE, SIZE) and mask.dtype == np.uint8
        assert _read(scene / "edited" / split / f"r_{i}.png").shape == img.shape
        assert set(np.unique(mask)) <= {0, *ids}
        np.testing.assert_array_equal(depth > 0, mask > 0)
        if opaque:
            assert (mask > 0).all(), "an opaque preset has a surface behind every pixel"
        else:
            alpha = img[..., 3]
            assert (alpha[mask > 0] > 0).all() and (alpha[mask == 0] < 255).all()
            assert (mask == 0).any() and (alpha == 0).any()
        seen_edited += int((mask == objects["edited_object_id"]).sum())
    assert seen_edited > 0


def test_pixel_centres_reproject_through_cameras_project(scenes):
    """3D point = ray through the pixel centre at the stored z-depth; it projects back onto that centre,
    it lies on the flat floor (z = 0) where the mask says floor, and on the sphere where it says sphere."""
    scene = scenes["demo"]
    objects = {o["name"]: o for o in json.loads((scene / "gt" / "objects.json").read_text())["objects"]}
    sphere = objects["sphere"]
    centre = np.mean(sphere["bbox"], axis=0)
    radius = sphere["params"]["radius"]
    meta = json.loads((scene / "transforms_train.json").read_text())
    cams = _cameras(meta)
    for i in range(len(cams)):
        depth = torch.from_numpy(np.load(scene / "gt" / "train" / f"r_{i}_depth.npy")).reshape(-1).double()
        mask = _read(scene / "gt" / "train" / f"r_{i}_mask.png").reshape(-1)
        origins, dirs, dz = cams.image_rays(i)
        hit = depth > 0
        pts = origins.double()[hit] + dirs.double()[hit] * (depth[hit] / dz.double()[hit])[:, None]
        uv, z = cams.project(pts.float(), i)
        vv, uu = np.divmod(np.nonzero(hit.numpy())[0], SIZE)
        expected = torch.from_numpy(np.stack([uu + 0.5, vv + 0.5], -1)).float()
        assert (uv - expected).abs().max() < 2e-3
        torch.testing.assert_close(z, depth[hit].float(), rtol=1e-5, atol=1e-5)
        ids = mask[hit.numpy()]
        floor_z = pts[torch.from_numpy(ids == objects["floor"]["id"]), 2]
        assert floor_z.numel() > 20 and floor_z.abs().max() < 1e-4
        on_sphere = pts[torch.from_numpy(ids == sphere["id"])].numpy()
        dist = np.linalg.norm(on_sphere - centre, axis=1)
        assert len(dist) > 5 and dist.min() > radius * 0.99 and dist.max() < radius * 1.0001


def test_deterministic_from_seed(tmp_path):
    a = make_scene("thin", tmp_path / "a", size=24, views=2, test_views=1, seed=5)
    b = make_scene("thin", tmp_path / "b", size=24, views=2, test_views=1, seed=5)
    c = make_scene("thin", tmp_path / "c", size=24, views=2, test_views=1, seed=6)
    files = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file())
    assert len(files) == 3 * 4 + 6  # per view: image, depth, mask, edited image; plus 6 JSON files
    for f in files:
        assert (a / f).read_bytes() == (b / f).read_bytes(), f
    assert (a / "train" / "r_0.png").read_bytes() != (c / "train" / "r_0.png").read_bytes()


@pytest.mark.parametrize("preset", ["demo", "similar", "thin", "forward", "room360", "replace"])
def test_edited_variant_changes_only_the_edited_object(tmp_path, preset):
    scene = make_scene(preset, tmp_path / preset, size=64, views=3, test_views=1, seed=1)
    k = json.loads((scene / "gt" / "objects.json").read_text())["edited_object_id"]
    edit = json.loads((scene / "edited" / "edit.json").read_text())
    kernel = np.ones((3, 3), np.uint8)
    changed_total = 0
    for split, i, img, _, mask in _frames(scene):
        edited = _read(scene / "edited" / split / f"r_{i}.png")
        region = mask == k
        if edit["kind"] == "replace":
            new_mask = _read(scene / "edited" / "gt" / split / f"r_{i}_mask.png")
            np.testing.assert_array_equal(new_mask[~region & (new_mask != k)], mask[~region & (new_mask != k)])
            region |= new_mask == k
        else:
            assert not (scene / "edited" / "gt").exists()
        differs = (edited != img).any(axis=-1)
        near = cv2.dilate(region.astype(np.uint8), kernel).astype(bool)
        assert not (differs & ~near).any(), f"{split}/r_{i}: pixels away from object {k} changed"
        inner = cv2.erode((mask == k).astype(np.uint8), kernel).astype(bool)
        if edit["kind"] == "recolor" and inner.any():
            assert differs[inner].mean() > 0.95
        changed_total += int(differs.sum())
    assert changed_total > 0


def test_bad_arguments_are_user_errors(tmp_path):
    with pytest.raises(UserError, match="unknown preset"):
        make_scene("nope", tmp_path / "x", size=16, views=1)
    with pytest.raises(UserError, match="size"):
        make_scene("demo", tmp_path / "x", size=2, views=1)
    with pytest.raises(UserError, match="view"):
        make_scene("demo", tmp_path / "x", size=16, views=0)
    (tmp_path / "busy").mkdir()
    (tmp_path / "busy" / "notes.txt").write_text("mine")
    with pytest.raises(UserError, match="not empty"):
        make_scene("demo", tmp_path / "busy", size=16, views=1)
    assert (tmp_path / "busy" / "notes.txt").read_text() == "mine"


def test_cli_make_scene(tmp_path, capsys):
    from repaint_nerf.app.cli import main

    assert main(["make-scene", "--list"]) == 0
    listed = capsys.readouterr().out
    assert all(p in listed for p in PRESETS)
    assert main(["make-scene", "--preset", "bogus", "--out", str(tmp_path / "s")]) == 2
    assert "unknown preset" in capsys.readouterr().err
    out = tmp_path / "s"
    assert main(["make-scene", "--preset", "forward", "--out", str(out), "--size", "16", "--views", "2",
                 "--test-views", "1", "--seed", "2"]) == 0
    meta = json.loads((out / "transforms_test.json").read_text())
    assert meta["scene_kind"] == "forward" and meta["w"] == 16 and len(meta["frames"]) == 1
    # Re-generating into a folder that holds a generated scene replaces it (no stale views remain).
    assert main(["make-scene", "--out", str(out), "--size", "16", "--views", "1", "--test-views", "1"]) == 0
    assert sorted(p.name for p in (out / "train").iterdir()) == ["r_0.png"]


def test_demo_scene_is_cached_and_written_atomically(tmp_path, monkeypatch):
    import repaint_nerf.core.synth.demo as demo

    monkeypatch.setenv("REPAINT_NERF_CACHE", str(tmp_path))
    monkeypatch.setattr(demo, "DEMO_VIEWS", 2)
    real = demo.make_scene

    def interrupted(*args, **kwargs):
        real(*args, **kwargs)
        raise KeyboardInterrupt

    monkeypatch.setattr(demo, "make_scene", interrupted)
    with pytest.raises(KeyboardInterrupt):
        demo.demo_scene_path(16)
    assert list(tmp_path.iterdir()) == [], "an interrupted first run leaves nothing behind"
    monkeypatch.setattr(demo, "make_scene", real)
    path = demo.demo_scene_path(16)
    assert path == tmp_path / "demo-16" and (path / "gt" / "objects.json").is_file()
    stamp = (path / "train" / "r_0.png").stat().st_mtime_ns
    monkeypatch.setattr(demo, "make_scene", lambda *a, **k: pytest.fail("regenerated a cached scene"))
    assert demo.demo_scene_path(16) == path
    assert (path / "train" / "r_0.png").stat().st_mtime_ns == stamp
    assert [p.name for p in tmp_path.iterdir()] == ["demo-16"]


def _render_one(obj) -> np.ndarray:
    """One object seen from above at 64 px: its straight RGB where it covers the pixel."""
    from repaint_nerf.core.synth.raster import Rasterizer

    c2w = np.eye(4)
    c2w[:3, 3] = (0.0, 0.0, 2.0)  # OpenGL camera looking down -z at the origin
    with Rasterizer(64, 64) as ras:
        frame = ras.render([obj], c2w, 80.0, 80.0, 32.0, 32.0)
    return frame.rgba[..., :3].astype(np.float32)[frame.mask > 0]


def test_photo_like_materials_change_the_image_as_described():
    from dataclasses import replace

    from repaint_nerf.core.synth.presets import SceneObject

    base = SceneObject("slab", "box", {"sx": 1.0, "sy": 1.0, "sz": 0.1}, (0.0, 0.0, 0.0), (0.6, 0.5, 0.4))
    flat = _render_one(base)
    grainy = _render_one(replace(base, grain=0.3))
    shiny = _render_one(replace(base, specular=0.8))
    text = _render_one(replace(base, texture="label", texture_scale=8.0, color2=(0.1, 0.1, 0.1)))
    wood = _render_one(replace(base, texture="wood", texture_scale=4.0, color2=(0.3, 0.2, 0.1)))
    assert flat.std(0).max() < 1.0, "a flat plain slab lit by distant lights is one colour"
    assert grainy.std(0).max() > 5.0 and abs(grainy.mean() - flat.mean()) < 10.0  # zero-mean fine noise
    assert shiny.max() > flat.max() + 40.0  # the highlight (light 0 is near the view direction from above)
    assert (text.mean(1) < 60).mean() > 0.05 and (text.mean(1) > 100).mean() > 0.3  # dark print on a light base
    assert wood.std(0).max() > 10.0
    ell = _render_one(SceneObject("e", "ellipsoid", {"rx": 0.6, "ry": 0.3, "rz": 0.2}, (0.0, 0.0, 0.0),
                                  (0.6, 0.5, 0.4)))
    assert 0.3 < ell.shape[0] / flat.shape[0] < 0.7  # ellipse area pi*0.6*0.3 vs the slab's 1.0 (perspective)


def test_occluded_preset_hides_the_can_in_most_views_and_its_masks_hold_only_visible_pixels(tmp_path):
    """The 'occluded' preset (issue 35): the edited can is partly covered by a nearer object in most views, and the
    ground-truth mask holds the id of the surface each pixel sees: the can rendered alone covers every pixel the
    scene's mask gives the can, plus the ones a nearer object takes, which carry that object's id and a smaller depth."""
    from repaint_nerf.core.synth.presets import build_spec
    from repaint_nerf.core.synth.raster import Rasterizer

    size, views = 64, 12
    root = make_scene("occluded", tmp_path / "s", size=size, views=views, seed=0, test_views=1)
    spec = build_spec("occluded")
    k = spec.edited_id()
    meta = json.loads((root / "transforms_train.json").read_text())
    cams = _cameras(meta)
    hidden = []
    with Rasterizer(size, size, spec.near, spec.far) as ras:
        for i, fr in enumerate(meta["frames"]):
            alone = ras.render([spec.objects[k - 1]], np.array(fr["transform_matrix"]), float(cams.fx[i]),
                               float(cams.fy[i]), size / 2, size / 2, ids=[k])
            mask = _read(root / "gt" / "train" / f"r_{i}_mask.png")
            depth = np.load(root / "gt" / "train" / f"r_{i}_depth.npy")
            can, whole = mask == k, alone.mask == k
            assert not (can & ~whole).any()
            covered = whole & ~can
            assert np.all((mask[covered] != 0) & (depth[covered] < alone.depth[covered]))
            hidden.append(covered.sum() / max(whole.sum(), 1))
    assert np.mean(np.array(hidden) > 0.05) >= 0.6  # partly hidden in most views
