"""Scene-kind detection on the presets' camera layouts, and the bounded parametrisations (contraction, NDC)."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from repaint_nerf.core.field.contraction import NDCWarp, contract, make_warp, mean_pose, uncontract
from repaint_nerf.core.scene.kinds import choose_kind, kind_from_layout
from repaint_nerf.core.synth.presets import build_spec
from repaint_nerf.core.synth.raster import world_bbox


def _layout(preset: str, n: int = 24, seed: int = 0):
    spec = build_spec(preset)
    c2w = spec.rig(n, np.random.default_rng(seed))
    rng = np.random.default_rng(seed)
    pts = []
    for obj in spec.objects:  # points inside each object's box stand in for SfM points
        lo, hi = np.asarray(world_bbox(obj))
        pts.append(rng.uniform(lo, hi, size=(200, 3)))
    return spec, c2w, np.concatenate(pts)


@pytest.mark.parametrize("preset", ["demo", "similar", "thin", "replace", "forward", "room360"])
@pytest.mark.parametrize("seed", [0, 1])
def test_presets_layouts_give_their_kind(preset, seed):
    spec, c2w, pts = _layout(preset, seed=seed)
    kind, why = kind_from_layout(c2w, pts)
    assert kind == spec.kind, why


def test_in_opaque_photos_a_few_points_beyond_the_cameras_mean_unbounded():
    """Far surfaces give few SfM points, so in opaque photos 5% of them beyond the cameras stand for much of what the
    photos show (a forest behind a trunk: 4%; a bedroom around a plush: 10%); a cut-out needs none of it held."""
    _, c2w, pts = _layout("demo")
    o, d = c2w[:, :3, 3], -c2w[:, :3, 2]
    from repaint_nerf.core.scene.normalize import axes_centre

    centre = axes_centre(o, d)
    r_cam = float(np.median(np.linalg.norm(o - centre, axis=1)))
    rng = np.random.default_rng(0)
    n_far = len(pts) // 19  # 5% of the points
    dirs = rng.normal(size=(n_far, 3))
    far = centre + dirs / np.linalg.norm(dirs, axis=1, keepdims=True) * r_cam * rng.uniform(1.5, 3.0, (n_far, 1))
    with_far = np.concatenate([pts, far])
    assert kind_from_layout(c2w, with_far)[0] == "bounded"  # a cut-out: the 20% rule
    kind, why = kind_from_layout(c2w, with_far, opaque=True)
    assert kind == "unbounded" and "5% of the sparse points lie beyond the cameras" in why, why
    assert kind_from_layout(c2w, pts, opaque=True)[0] == "bounded"  # nothing beyond: an object on a plain backdrop


def _stub_scene(c2w, pts, focal: float, alpha: bool = False):
    """What detect_kind reads of a scene: 100-px training views at `focal`, opaque or cut-out images, points."""
    from repaint_nerf.core.scene.cameras import Cameras
    from repaint_nerf.core.scene.scene import SceneSplit

    class S:
        kind, extra = "bounded", {}

    s = S()
    s.points = pts
    image = np.full((100, 100, 4 if alpha else 3), 255, np.uint8)
    if alpha:
        image[:10, :10, 3] = 0
    s.splits = {"train": SceneSplit(Cameras.create(c2w, focal, focal, 50, 50, 100, 100), [image] * len(c2w),
                                    [f"{i}.png" for i in range(len(c2w))])}
    return s


def _pixels_past_box_reference(cams, lo, hi, grid):
    """One ray at a time, a plain slab test."""
    missed = 0
    for i in range(len(cams)):
        c2w = cams.c2w[i].double().numpy()
        fx, fy, cx, cy = (float(t[i]) for t in (cams.fx, cams.fy, cams.cx, cams.cy))
        w, h = float(cams.width[i]), float(cams.height[i])
        for r in range(grid):
            for c in range(grid):
                u, v = (c + 0.5) / grid * w, (r + 0.5) / grid * h
                d = c2w[:3, :3] @ np.array([(u - cx) / fx, -(v - cy) / fy, -1.0])
                o = c2w[:3, 3]
                t_near, t_far = -np.inf, np.inf
                for k in range(3):
                    if abs(d[k]) < 1e-12:
                        if not lo[k] <= o[k] <= hi[k]:
                            t_near, t_far = 1.0, 0.0
                        continue
                    a, b = sorted(((lo[k] - o[k]) / d[k], (hi[k] - o[k]) / d[k]))
                    t_near, t_far = max(t_near, a), min(t_far, b)
                missed += t_far <= t_near or t_far <= 0
    return missed / (len(cams) * grid * grid)


def test_opaque_photos_whose_pixels_look_past_the_points_box_are_unbounded():
    """Every pixel of a photo shows a surface; where a ray misses the box the points fill, the bounded field has
    nothing to learn it with. A wide lens around the demo's objects sees past their box: unbounded. A narrow one
    sees the box alone, and a cut-out (transparent background) needs none of what lies beyond: bounded."""
    from repaint_nerf.core.scene.kinds import MISS_FRACTION, detect_kind, pixels_past_box

    _, c2w, pts = _layout("demo")
    wide, narrow = _stub_scene(c2w, pts, 60.0), _stub_scene(c2w, pts, 400.0)
    lo, hi = pts.min(0), pts.max(0)
    for scene in (wide, narrow):
        cams = scene.splits["train"].cameras
        assert pixels_past_box(cams, lo, hi, grid=6) == pytest.approx(
            _pixels_past_box_reference(cams, lo, hi, 6), abs=1e-12)
    kind, why = detect_kind(wide)
    assert kind == "unbounded" and "of the photos' pixels look past the box the sparse points fill" in why, why
    kind, why = detect_kind(narrow)
    assert kind == "bounded" and "0% of the photos' pixels look past" in why, why
    assert pixels_past_box(narrow.splits["train"].cameras, lo, hi) <= MISS_FRACTION
    assert detect_kind(_stub_scene(c2w, pts, 60.0, alpha=True))[0] == "bounded"  # a cut-out


@pytest.mark.parametrize("preset,far,expected", [("demo", 5.5, "bounded"), ("room360", 7.5, "unbounded")])
def test_without_points_the_far_depth_decides(preset, far, expected):
    _, c2w, _ = _layout(preset)
    assert kind_from_layout(c2w, None, far)[0] == expected


def test_override_and_bad_override():
    from repaint_nerf.core.errors import UserError

    class S:  # the attributes choose_kind reads
        kind, extra, points = "bounded", {}, None

    _, c2w, _ = _layout("forward")
    from repaint_nerf.core.scene.cameras import Cameras
    from repaint_nerf.core.scene.scene import SceneSplit

    s = S()
    s.splits = {"train": SceneSplit(Cameras.create(c2w, 100, 100, 50, 50, 100, 100), [], [])}
    assert choose_kind(s) == "forward" and s.kind == "forward" and "look within" in s.extra["kind_reason"]
    assert choose_kind(s, "unbounded") == "unbounded" and s.kind == "unbounded"
    with pytest.raises(UserError, match="unknown scene kind"):
        choose_kind(s, "sphere")


# ---- contraction ----------------------------------------------------------------------------------

@pytest.mark.parametrize("norm", ["inf", "l2"])
def test_contraction_maps_space_into_the_unit_box_and_inverts(norm):
    g = torch.Generator().manual_seed(0)
    x = torch.randn(5000, 3, generator=g, dtype=torch.float64) * torch.logspace(-2, 4, 5000, dtype=torch.float64)[:, None]
    y = contract(x, norm)
    bound = y.abs().amax(-1) if norm == "inf" else y.norm(dim=-1)
    assert float(bound.max()) < 1.0
    inner = (x.abs().amax(-1) if norm == "inf" else x.norm(dim=-1)) <= 1
    assert torch.allclose(y[inner], 0.5 * x[inner])  # the unit region is kept (scaled by 1/2)
    assert torch.allclose(uncontract(y, norm), x, rtol=1e-6, atol=1e-9)
    far = contract(torch.tensor([[1e12, 0.0, 0.0]], dtype=torch.float64), norm)
    assert abs(float(far[0, 0]) - 1.0) < 1e-9  # infinity reaches the box's face


@pytest.mark.parametrize("norm", ["inf", "l2"])
def test_contraction_is_continuous_across_the_unit_boundary(norm):
    g = torch.Generator().manual_seed(1)
    d = torch.randn(500, 3, generator=g, dtype=torch.float64)
    d = d / (d.abs().amax(-1, keepdim=True) if norm == "inf" else d.norm(dim=-1, keepdim=True))
    eps = 1e-7
    inside, outside = contract(d * (1 - eps), norm), contract(d * (1 + eps), norm)
    assert float((inside - outside).norm(dim=-1).max()) < 1e-6
    # and Lipschitz everywhere: no jump anywhere along rays through the origin
    t = torch.linspace(0.01, 50, 20001, dtype=torch.float64)
    path = contract(d[:1] * t[:, None], norm)
    steps = (path[1:] - path[:-1]).norm(dim=-1)
    assert float(steps.max()) <= 0.5 * float(t[1] - t[0]) * float(d[0].norm()) + 1e-12


def test_ndc_maps_the_frustum_to_the_box():
    c2w = np.eye(4)
    c2w[:3, 3] = [0.3, -0.2, 0.5]
    w, h, f, near = 80.0, 60.0, 70.0, 0.5
    warp = NDCWarp(c2w, f, f, w, h, near)
    rng = np.random.default_rng(0)
    z = near * np.exp(rng.uniform(0, 8, 2000))  # depths from the near plane to ~1500 x near
    u, v = rng.uniform(0, w, 2000), rng.uniform(0, h, 2000)
    cam = np.stack([(u - w / 2) / f * z, -(v - h / 2) / f * z, -z], -1)
    world = cam + c2w[:3, 3]
    y = warp(torch.as_tensor(world, dtype=torch.float32))
    assert float(y.abs().max()) <= 1.0 + 1e-5
    assert np.allclose(y[:, 2].numpy(), 1 - 2 * near / z, atol=1e-5)  # -1 at the near plane, -> 1 at infinity
    assert np.allclose(y[:, 0].numpy(), (u - w / 2) / (w / 2), atol=1e-4)  # x' is the image coordinate


def test_mean_pose_is_a_rotation():
    _, c2w, _ = _layout("forward")
    m = mean_pose(c2w)
    assert np.allclose(m[:3, :3].T @ m[:3, :3], np.eye(3), atol=1e-9) and np.linalg.det(m[:3, :3]) > 0


def test_ndc_inverse_and_spec_round_trip():
    c2w = mean_pose(_layout("forward")[1])
    warp = NDCWarp(c2w, 60.0, 50.0, 64.0, 48.0, 0.3)
    back = make_warp(warp.to_dict())
    g = torch.Generator().manual_seed(0)
    y = torch.rand(2000, 3, generator=g) * 1.98 - 0.99
    assert torch.allclose(back(back.inverse(y)), y, atol=1e-4)
    x = torch.randn(100, 3, generator=g)
    assert torch.equal(back(x), warp(x))
    behind = torch.as_tensor(c2w[:3, 3] + 0.5 * c2w[:3, 2], dtype=torch.float32)[None]  # behind the camera
    assert float(warp(behind)[0, 2]) < -1.0  # maps outside the box: no density there


def test_contract_warp_inverse():
    w = make_warp({"kind": "contract", "extent": 16.0, "cone": 1 / 256})
    y = torch.rand(3000, 3, generator=torch.Generator().manual_seed(2)) * 1.99 - 0.995
    assert torch.allclose(w(w.inverse(y)), y, atol=1e-5)


def test_unknown_warp_is_a_clear_error():
    from repaint_nerf.core.errors import UserError

    with pytest.raises(UserError, match="unknown space warp"):
        make_warp({"kind": "sphere"})


def _tiny_field(warp=None):
    from repaint_nerf.core.field.field import FieldConfig, NGPField

    torch.manual_seed(0)
    return NGPField(FieldConfig(levels=2, log2_table=10, base_res=4, finest_res=8, hidden=16,
                                encoding_impl="reference", compile=False, warp=warp))


def test_warped_field_sees_far_points_inside_its_cube():
    plain, warped = _tiny_field(), _tiny_field({"kind": "contract", "extent": 16.0, "cone": 1 / 256})
    far = torch.tensor([[10.0, 3.0, -2.0], [100.0, 0.0, 0.0]])
    assert torch.all(plain.density(far) == 0)  # outside the plain field's cube
    assert torch.allclose(warped.density(far), plain.density(contract(far)))
    assert torch.all(warped.density(far) > 0)
    out = warped(far, torch.nn.functional.normalize(far, dim=-1), outputs=("rgb",))
    assert out["rgb"].shape == (2, 3) and torch.isfinite(out["rgb"]).all()
    assert warped.march() == (16.0, 1 / 256) and plain.march() == (1.0, 0.0)


def test_cone_steps_grow_with_distance_and_invert():
    from repaint_nerf.core.render.raymarch import _cone_steps, _cone_t

    t0 = torch.tensor([0.0, 0.5, 3.0])
    k = torch.arange(0, 400, dtype=torch.float32)[:, None].expand(-1, 3)
    t = _cone_t(t0.expand_as(k), k, 0.01, 0.02)
    dt = t[1:] - t[:-1]
    assert torch.all(dt > 0) and torch.allclose(t[0], t0)
    assert torch.allclose(dt[:, 2], 0.02 * t[:-1, 2], rtol=1e-3)  # past the knee (0.5): step = cone * t
    assert torch.allclose(dt[:20, 0], torch.full((20,), 0.01), atol=1e-6)  # before it: the base step
    back = _cone_steps(t0.expand_as(k), t, 0.01, 0.02)
    assert torch.allclose(back, k, atol=2e-3)


def test_warped_grid_skips_in_warped_space_and_renders_like_without_skipping():
    """A contracted field with density only in a far shell: the grid (in contracted space) learns where it
    is, rendering with it matches rendering without skipping, and rays reach the far shell."""
    from repaint_nerf.core.render.occupancy import grid_for_field
    from repaint_nerf.core.render.renderer import RenderOptions, render_rays

    class Shell(torch.nn.Module):  # far shell between |x|_inf 4 and 8 (two cells deep), coloured by position
        warp = make_warp({"kind": "contract", "extent": 16.0, "cone": 1 / 256})
        cfg = type("C", (), {"bound": 1.0})()

        def march(self):
            return 16.0, 1 / 256

        def density(self, x):
            m = x.abs().amax(-1)
            return torch.where((m > 4) & (m < 8), torch.full_like(m, 5.0), torch.zeros_like(m))

        def forward(self, x, d, outputs=("rgb",)):
            return {"sigma": self.density(x), "rgb": torch.sigmoid(x / 3.0)}

    f = Shell()
    grid = grid_for_field(f, 64, device="cpu", warmup_steps=10 ** 9)
    assert grid.extent == 16.0 and grid.warp is f.warp
    for step in range(0, 16 * 16, 16):  # jittered sweeps, as training makes them
        grid.update(step, f.density)
    assert 0.0 < grid.occupied_fraction() < 0.5
    g = torch.Generator().manual_seed(0)
    d = torch.nn.functional.normalize(torch.randn(300, 3, generator=g), dim=-1)
    o = torch.zeros(300, 3)
    opts = RenderOptions(outputs=("rgb", "opacity", "depth"), max_samples=256)
    with_grid = render_rays(f, grid, o, d, opts)
    without = render_rays(f, None, o, d, opts)
    assert torch.allclose(with_grid["rgb"], without["rgb"], atol=2e-3)
    assert float(with_grid["opacity"].min()) > 0.99  # every ray is stopped by the shell
    assert float(with_grid["depth"].min()) >= 4.0 - 1e-3 and float(with_grid["depth"].max()) <= 8.0 * 3 ** 0.5
    assert with_grid["stats"]["samples"] < without["stats"]["samples"]


@pytest.mark.parametrize("preset,kind", [("room360", "contract"), ("forward", "ndc")])
def test_warped_scene_trains_saves_and_renders(tmp_path, preset, kind):
    """Forward and 360 presets train with their warp (chosen from the scene kind), raise test PSNR,
    and a saved checkpoint restores the warp and renders identically."""
    from repaint_nerf.core.render.renderer import RenderOptions, render_camera
    from repaint_nerf.core.scene.loaders.detect import load_scene
    from repaint_nerf.core.synth.generate import make_scene
    from repaint_nerf.core.train.checkpoint import Checkpoint
    from repaint_nerf.core.train.stage1 import Stage1Trainer, TrainConfig, restore_field

    make_scene(preset, tmp_path / "s", size=32, views=16, test_views=3, seed=0)
    for split in ("train", "test"):  # a capture has no box around its content: that is what the warp is for
        meta_path = tmp_path / "s" / f"transforms_{split}.json"
        meta = json.loads(meta_path.read_text())
        meta.pop("aabb")
        meta_path.write_text(json.dumps(meta))
    scene = load_scene(tmp_path / "s")
    tr = Stage1Trainer(scene, train_cfg=TrainConfig(rays_per_batch=1024, grid_resolution=32, seed=0))
    assert tr.field_cfg.warp["kind"] == kind and tr.grid.warp is not None
    before = tr.evaluate()["psnr"]
    tr.train(steps=120)
    after = tr.evaluate()["psnr"]
    assert after > before + 3.0, (before, after)
    path = tmp_path / "ck.safetensors"
    tr.checkpoint().save(path)
    field, grid, _ = restore_field(Checkpoint.load(path, "cpu"), "cpu")
    assert field.cfg.warp == tr.field_cfg.warp and grid.extent == tr.grid.extent
    assert torch.equal(grid.visible, tr.grid.visible) and not bool(grid.visible.all())  # no camera sees it all
    cams = scene.field_cameras("test")
    opts = RenderOptions(outputs=("rgb",), max_samples=tr.cfg.max_samples)
    tr.field.eval()
    a = render_camera(tr.field, tr.grid, cams, 0, opts)["rgb"]
    b = render_camera(field, grid, cams, 0, opts)["rgb"]
    assert torch.equal(a, b)


@pytest.mark.parametrize("preset,kind", [("demo", "bounded"), ("room360", "unbounded"), ("forward", "forward")])
def test_a_dataset_without_a_kind_gets_it_from_its_camera_layout(tmp_path, preset, kind):
    from repaint_nerf.core.scene.loaders.detect import load_scene
    from repaint_nerf.core.synth.generate import make_scene

    make_scene(preset, tmp_path / "s", size=16, views=12, test_views=2, seed=0)
    for split in ("train", "test"):
        meta_path = tmp_path / "s" / f"transforms_{split}.json"
        meta = json.loads(meta_path.read_text())
        meta.pop("scene_kind")
        meta_path.write_text(json.dumps(meta))
    scene = load_scene(tmp_path / "s")
    assert scene.kind == kind and scene.extra["kind_reason"]
    assert load_scene(tmp_path / "s", kind="bounded").kind == "bounded"  # the override wins
