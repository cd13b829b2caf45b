"""Real-capture cost: photos loaded at the training resolution, a bounded evaluation, a foggy field's samples
capped, and `train --seconds` bounding the whole command (issue 18)."""
from __future__ import annotations

import dataclasses
import json
import time

import numpy as np
import pytest
import torch

from scene_writers import write_blender


def test_large_photos_are_downscaled_by_default_and_small_ones_kept(tmp_path):
    from repaint_nerf.core.scene.loaders.common import DEFAULT_MAX_SIZE
    from repaint_nerf.core.scene.loaders.detect import load_scene

    big = tmp_path / "big"
    write_blender(big, {"train": 3, "test": 1}, w=1024, h=768, fl=900.0)
    scene = load_scene(big)
    assert scene.train.images[0].shape[:2] == (384, 512) and DEFAULT_MAX_SIZE == 512
    cams = scene.train.cameras
    assert int(cams.width[0]) == 512 and int(cams.height[0]) == 384
    assert abs(float(cams.fx[0]) - 450.0) < 1e-3 and abs(float(cams.cx[0]) - 256.0) < 1e-3
    full = load_scene(big, max_size=0)
    assert full.train.images[0].shape[:2] == (768, 1024) and abs(float(full.train.cameras.fx[0]) - 900.0) < 1e-3
    mid = load_scene(big, max_size=300)  # the user's size: the long side fits it
    assert max(mid.train.images[0].shape[:2]) == 300
    small = tmp_path / "small"
    write_blender(small, {"train": 3, "test": 1}, w=96, h=64, fl=80.0)
    kept = load_scene(small)
    assert kept.train.images[0].shape[:2] == (64, 96) and abs(float(kept.train.cameras.fx[0]) - 80.0) < 1e-4


def test_downscaling_keeps_intrinsics_consistent(tmp_path):
    """A world point projects to the same place, in proportion, in the full-size and the downscaled camera; and
    the downscaled image is the full one resized (same colours there)."""
    from repaint_nerf.core.scene.loaders.detect import load_scene

    root = tmp_path / "s"
    write_blender(root, {"train": 2, "test": 1}, w=1000, h=600, fl=700.0, rgba=False)
    full, small = load_scene(root, max_size=0), load_scene(root, max_size=250)
    cf, cs = full.train.cameras, small.train.cameras
    sx, sy = int(cs.width[0]) / int(cf.width[0]), int(cs.height[0]) / int(cf.height[0])
    assert (int(cs.width[0]), int(cs.height[0])) == (250, 150)
    pts = torch.tensor([[0.1, -0.2, 0.05], [0.3, 0.2, -0.1], [0.0, 0.0, 0.0]])
    uv_f, z_f = cf.project(pts, 0)
    uv_s, z_s = cs.project(pts, 0)
    assert torch.allclose(uv_s[:, 0], uv_f[:, 0] * sx, atol=1e-3) and torch.allclose(uv_s[:, 1], uv_f[:, 1] * sy,
                                                                                          atol=1e-3)
    assert torch.allclose(z_s, z_f)
    # rays through matching pixel centres point the same way
    o_f, d_f, _ = cf.rays(torch.tensor([0]), torch.tensor([399.5 - 0.5]), torch.tensor([199.5 - 0.5]))
    o_s, d_s, _ = cs.rays(torch.tensor([0]), torch.tensor([399.5 * sx - 0.5]), torch.tensor([199.5 * sy - 0.5]))
    assert torch.allclose(d_f, d_s, atol=1e-5) and torch.allclose(o_f, o_s)
    a = full.train.images[0].astype(np.float32).reshape(150, 4, 250, 4, 3).mean((1, 3))
    assert np.abs(a - small.train.images[0].astype(np.float32)).mean() < 4.0


@pytest.fixture(scope="module")
def trainer_160(scene_factory):
    from repaint_nerf.core.scene.loaders.detect import load_scene
    from repaint_nerf.core.train.stage1 import Stage1Trainer, TrainConfig

    scene = load_scene(scene_factory("demo", size=160, views=6, test_views=12))
    return Stage1Trainer(scene, None, TrainConfig(seed=0, rays_per_batch=256, grid_resolution=32, max_samples=32))


def test_evaluation_is_bounded_and_full_only_when_asked(trainer_160, monkeypatch):
    from repaint_nerf.core.train import stage1

    # smaller bounds than the defaults keep the test quick; the rule is the same
    EVAL_VIEWS, EVAL_GRID, EVAL_SAMPLE_CAP = 5, 48, 16
    monkeypatch.setattr(stage1, "EVAL_VIEWS", EVAL_VIEWS)
    monkeypatch.setattr(stage1, "EVAL_GRID", EVAL_GRID)
    monkeypatch.setattr(stage1, "EVAL_SAMPLE_CAP", EVAL_SAMPLE_CAP)
    tr = trainer_160
    ev = tr.evaluate(with_ssim=True)
    assert ev["views"] == EVAL_VIEWS < ev["views_total"] == 12 and not ev["full"]
    assert ev["pixels"] == EVAL_VIEWS * EVAL_GRID * EVAL_GRID  # grids over the 160-px views
    assert ev["samples_per_ray"] <= EVAL_SAMPLE_CAP and np.isfinite(ev["ssim"])
    again = tr.evaluate()
    assert again["psnr"] == ev["psnr"]  # the same views and pixels every time: curves compare
    full = tr.evaluate(full=True, max_views=1)
    assert full["full"] and full["views"] == 1 and full["pixels"] == 160 * 160
    late = tr.evaluate(deadline=time.perf_counter() - 1.0)  # past the deadline: one view, the rest skipped
    assert late["views"] == 1 and late["skipped_views"] == EVAL_VIEWS - 1


def test_foggy_field_render_samples_are_bounded():
    """An untrained field (every grid cell occupied, nothing opaque) would march every ray to the far bound, and
    the far bound's step count grows with the image size; capped, the samples per ray do not grow."""
    from repaint_nerf.core.render.occupancy import grid_for_field
    from repaint_nerf.core.render.renderer import RenderOptions, render_camera
    from repaint_nerf.core.scene.cameras import Cameras, look_at
    from repaint_nerf.core.train.stage1 import EVAL_SAMPLE_CAP, make_field, sample_budget

    torch.manual_seed(0)
    field, _ = make_field(None, torch.device("cpu"), 64)
    grid = grid_for_field(field, 32)
    pose = look_at((0.0, -1.6, 0.8), (0.0, 0.0, 0.0))
    samples = {}
    for side in (32, 64):
        cams = Cameras.create(pose, side * 1.2, side * 1.2, side / 2, side / 2, side, side)
        for cap in (0, EVAL_SAMPLE_CAP // 4):
            opts = RenderOptions(outputs=("rgb",), max_samples=sample_budget(side * 4), sample_cap=cap)
            out = render_camera(field, grid, cams, 0, opts)
            samples[side, cap] = out["stats"]["samples"]
            assert out["rgb"].shape == (side, side, 3) and torch.isfinite(out["rgb"]).all()
    cap = EVAL_SAMPLE_CAP // 4
    assert samples[64, cap] / (64 * 64) <= cap
    assert samples[64, 0] > samples[64, cap] * 1.5  # uncapped, the fog is marched much further
    assert samples[64, cap] <= 4.0 * samples[32, cap]  # 4x the pixels, no more than 4x the work


def test_seconds_budget_skips_the_full_evaluation_with_a_message(capsys):
    """Budget accounting with a fake clock: the bounded evaluation runs, the full one would not fit and is
    skipped with a message that names it."""
    from repaint_nerf.app.commands.train import closing_evaluation
    from repaint_nerf.core.train.budget import CommandBudget

    now = [0.0]

    class Fake:
        scene = type("S", (), {"field_cameras": lambda self, split: type("C", (), {
            "width": torch.tensor([1000] * 20), "height": torch.tensor([1000] * 20)})()})()
        calls = []

        def evaluate(self, **kw):
            self.calls.append(kw)
            now[0] += 1.0
            return {"split": "test", "views": 8, "views_total": 20, "full": kw.get("full", False),
                    "pixels": 8 * 128 * 128, "skipped_views": 0, "seconds": 1.0, "psnr": 20.0, "ssim": 0.5}

    budget = CommandBudget(10.0, clock=lambda: now[0])
    now[0] = 8.0  # loading + training spent 8 of 10 s
    tr = Fake()
    ev = closing_evaluation(tr, budget, full=True)
    assert [c.get("full", False) for c in tr.calls] == [False] and ev["full"] is False
    assert tr.calls[0]["deadline"] == 10.0
    err = capsys.readouterr().err
    assert "skipped the full evaluation" in err and "--seconds" in err
    assert budget.skipped and "full evaluation" in budget.skipped[0]
    roomy = CommandBudget(None, clock=lambda: now[0])  # --steps: no budget, the full evaluation runs
    tr.calls.clear()
    closing_evaluation(tr, roomy, full=True)
    assert [c.get("full", False) for c in tr.calls] == [False, True]
    assert CommandBudget(10.0, clock=lambda: 0.0).training_seconds() == 9.0  # 10% kept for the closing work


def test_seconds_bounds_the_whole_train_command(scene_factory, tmp_path, capsys):
    from repaint_nerf.app.cli import main

    scene = scene_factory("demo", size=32, views=8, test_views=4)
    t0 = time.perf_counter()
    assert main(["train", str(scene), "--workspace", str(tmp_path / "ws"), "--seconds", "12", "--no-features",
                 "--no-depth", "--full-eval"]) == 0
    took = time.perf_counter() - t0
    out, err = capsys.readouterr()
    assert "--seconds 12" in out and "trained" in out
    assert "PSNR" in out or "skipped the closing evaluation" in err  # a loaded machine may leave no time
    assert took < 12.0 + 5.0, took  # one step and the saves may pass the line; the closing work does not


def test_closing_evaluation_of_a_short_train_keeps_to_its_share(scene_factory, monkeypatch, capsys):
    """`train`'s closing evaluation after a short training run is given EVAL_SHARE of the seconds trained (not
    what is left of --seconds); a view that would not end within it is skipped and said (views made to take
    0.4 of the allowance each: two fit)."""
    from repaint_nerf.app.commands.train import closing_evaluation
    from repaint_nerf.core.scene.loaders.detect import load_scene
    from repaint_nerf.core.train import stage1
    from repaint_nerf.core.train.budget import EVAL_SHARE, CommandBudget

    scene = load_scene(scene_factory("demo", size=32, views=4, test_views=12))
    tr = stage1.Stage1Trainer(scene, None, stage1.TrainConfig(seed=0, rays_per_batch=256, grid_resolution=16))
    tr.train(steps=3)
    budget = CommandBudget(3600.0)  # --seconds: plenty left, so the share is the limit
    trained = 20.0  # as if the run had trained 20 s
    allowed = EVAL_SHARE * trained
    _views_take(monkeypatch, 0.4 * allowed)
    ev = closing_evaluation(tr, budget, False, trained)
    assert ev["views"] == 2 and ev["skipped_views"] == stage1.EVAL_VIEWS - 2
    assert ev["seconds"] == pytest.approx(0.8 * allowed)
    err = capsys.readouterr().err
    assert f"skipped {ev['skipped_views']} of the evaluation's {stage1.EVAL_VIEWS} views" in err
    assert f"at most 10% of the training time ({allowed:.1f} s of {trained:.1f} s)" in err


@pytest.mark.parametrize("value", [-1, 4, 2.5, "x"])
def test_bad_max_size_is_a_user_error(tmp_path, value):
    from repaint_nerf.core.errors import UserError
    from repaint_nerf.core.scene.loaders.detect import load_scene

    write_blender(tmp_path, {"train": 1})
    with pytest.raises(UserError, match="--max-size"):
        load_scene(tmp_path, max_size=value)


def test_march_budget_ramps_coarse_to_fine():
    from repaint_nerf.core.train.stage1 import march_budget

    seq = [march_budget(s, 1024, 256, 256) for s in range(0, 300, 16)]
    assert seq[0] == 256 and seq[-1] == 1024 and march_budget(256, 1024, 256, 256) == 1024
    assert all(a <= b for a, b in zip(seq, seq[1:]))  # never coarser later
    assert march_budget(128, 1024, 256, 256) == 512  # geometric: halfway in steps, halfway in octaves
    assert march_budget(0, 1024, 0, 256) == 1024  # off
    assert march_budget(0, 128, 256, 256) == 128  # a budget below the early one is kept
    # keyed to the fog: the early budget until the step it cleared, then the same ramp from there
    assert [march_budget(s, 1024, 256, 256, 100) for s in (0, 100, 228, 356)] == [256, 256, 512, 1024]
    # still fog: held until the grid's warm-up ends (the ramp starts there at the latest)
    assert [march_budget(s, 1024, 256, 256, None) for s in (255, 256, 384, 512)] == [256, 256, 512, 1024]
    assert march_budget(384, 1024, 256, 256, 300) == 512  # cleared after the warm-up: ramps from its end


def test_early_steps_of_a_foggy_field_march_the_early_budget(scene_factory):
    """An untrained field keeps every sample of every ray; the first steps march at the early budget, so their
    samples per ray do not grow with the image's budget."""
    from repaint_nerf.core.scene.loaders.detect import load_scene
    from repaint_nerf.core.train.stage1 import Stage1Trainer, TrainConfig

    scene = load_scene(scene_factory("demo", size=32, views=4, test_views=2))
    spr = {}
    for early in (0, 64):
        cfg = TrainConfig(seed=0, rays_per_batch=256, grid_resolution=16, max_samples=512, early_max_samples=early)
        tr = Stage1Trainer(scene, None, cfg)
        info = tr.step()
        spr[early] = info["candidates_per_ray"]
        assert tr.fog_cleared_step is None  # the filter kept every candidate: fog
        assert tr.march_samples == (512 if early == 0 else 64)  # held while the field is fog
    assert spr[64] <= 64 and spr[0] > 4 * spr[64]


def test_the_early_budget_follows_the_space_the_field_marches(scene_factory, tmp_path):
    """Auto early budget: a field in its own cube marches EARLY_SAMPLES while it is fog, a warped (contracted or
    NDC) one or one trained on depth priors EARLY_SAMPLES_FINE; a value the user gives is kept, and the resolved
    value is what the run records."""
    from repaint_nerf.core.scene.loaders.detect import load_scene
    from repaint_nerf.core.synth.generate import make_scene
    from repaint_nerf.core.train.stage1 import EARLY_SAMPLES, EARLY_SAMPLES_FINE, Stage1Trainer, TrainConfig

    bounded = load_scene(scene_factory("demo", size=32, views=4, test_views=2))
    room = make_scene("room360", tmp_path / "room", size=32, views=4, test_views=2, seed=0)  # its own copy
    for split in ("train", "test"):  # a capture has no box around its content: it is contracted
        meta = json.loads((room / f"transforms_{split}.json").read_text())
        meta.pop("aabb")
        (room / f"transforms_{split}.json").write_text(json.dumps(meta))
    warped = load_scene(room)
    cfg = TrainConfig(seed=0, rays_per_batch=64, grid_resolution=16, max_samples=512)
    a, b = Stage1Trainer(bounded, None, cfg), Stage1Trainer(warped, None, cfg)
    assert a.grid.warp is None and b.grid.warp is not None
    assert (a.march_samples, b.march_samples) == (EARLY_SAMPLES, EARLY_SAMPLES_FINE)
    assert EARLY_SAMPLES < EARLY_SAMPLES_FINE
    assert TrainConfig.from_dict(dataclasses.asdict(a.cfg)).early_max_samples == EARLY_SAMPLES
    given = Stage1Trainer(warped, None, dataclasses.replace(cfg, early_max_samples=48))
    assert given.march_samples == 48
    priors = [np.where(im[..., 3] > 0, 4.0, np.nan).astype(np.float32) for im in bounded.train.images]
    assert Stage1Trainer(bounded, None, cfg, depth_priors=priors).march_samples == EARLY_SAMPLES_FINE
    unused = dataclasses.replace(cfg, lambda_depth=0.0)  # priors given but weighted 0: no depth to resolve
    assert Stage1Trainer(bounded, None, unused, depth_priors=priors).march_samples == EARLY_SAMPLES


def test_march_ramp_starts_when_the_fog_clears_and_resumes_there(scene_factory):
    """A field whose filter pass drops candidates (rays reach the transmittance threshold) has cleared: the ramp
    starts at that step, whatever the step count; a checkpoint keeps the step, so a resumed run and a render of
    the version march at the trained budget; files from before it was recorded ramped from step 0."""
    from repaint_nerf.core.scene.loaders.detect import load_scene
    from repaint_nerf.core.train.header import CheckpointHeader
    from repaint_nerf.core.train.stage1 import Stage1Trainer, TrainConfig, march_budget

    scene = load_scene(scene_factory("demo", size=32, views=4, test_views=2))
    cfg = TrainConfig(seed=0, rays_per_batch=256, grid_resolution=16, max_samples=512, early_max_samples=64,
                      grid_warmup_steps=32, grid_update_every=4)
    fog, opaque = Stage1Trainer(scene, None, cfg), Stage1Trainer(scene, None, cfg)
    with torch.no_grad():
        opaque.field.trunk_out.bias[0] += 12.0  # density e^12 everywhere: every ray ends in its first samples
    for _ in range(6):
        fog.step(), opaque.step()
    assert fog.fog_cleared_step is None and fog.march_samples == 64
    assert opaque.fog_cleared_step == 0 and opaque.filter_kept < cfg.one_pass_kept
    assert opaque.march_samples == march_budget(6, 512, 64, 32, 0) > 64
    for tr in (fog, opaque):
        header = CheckpointHeader.from_dict(tr.checkpoint().info.to_dict())
        assert header.fog_cleared_step == tr.fog_cleared_step and header.max_samples == tr.march_samples
        again = Stage1Trainer(scene, None, cfg)
        again.load(tr.checkpoint())
        assert again.fog_cleared_step == tr.fog_cleared_step and again.march_samples == tr.march_samples
    old = fog.checkpoint().info.to_dict()
    old.pop("march")
    assert CheckpointHeader.from_dict(old).max_samples == march_budget(6, 512, 64, 32, 0)  # ramped from step 0


def test_time_limited_evaluation_shrinks_its_grid_and_skips_views(trainer_160, monkeypatch):
    """An evaluation given `seconds` sizes its first view from the training step's seconds per ray (a smaller grid
    when the full one would not fit) and starts a view only when the slowest so far would still end in time."""
    from repaint_nerf.core.train import stage1
    from repaint_nerf.core.train.stage1 import EVAL_GRID, EVAL_GRID_MIN, eval_grid_side

    assert eval_grid_side(10.0, 1e-3) == EVAL_GRID  # 48^2 pixels x 1 ms = 2.3 s: fits
    assert eval_grid_side(0.5, 1e-3) == 22  # the largest square of at most 500 pixels
    assert eval_grid_side(0.01, 1e-3) == EVAL_GRID_MIN and eval_grid_side(0.5, 0.0) == EVAL_GRID
    assert eval_grid_side(float("inf"), 1.0) == EVAL_GRID
    tr = trainer_160
    tr.ray_seconds = 1e-3
    ev = tr.evaluate(seconds=60.0)
    assert ev["grid"] == EVAL_GRID and ev["views"] == stage1.EVAL_VIEWS and not ev["skipped_views"]
    _views_take(monkeypatch, 0.2)
    ev = tr.evaluate(seconds=0.5)
    assert ev["grid"] == 22 and ev["pixels"] == ev["views"] * 22 * 22
    # 0.2 s, then 0.2 + 0.2 <= 0.5: a second view; 0.4 + 0.2 > 0.5: the rest skipped
    assert ev["views"] == 2 and ev["skipped_views"] == stage1.EVAL_VIEWS - 2 and ev["seconds"] == pytest.approx(0.4)


def _views_take(monkeypatch, seconds: float) -> None:
    """Make each view of stage 1's bounded evaluation take exactly `seconds` on the clock it reads (a clock that
    only those views advance), so time limits are tested as behaviour, not as the machine's speed."""
    import types

    from repaint_nerf.core.train import stage1

    now = [time.perf_counter()]
    real = stage1.eval_pixels

    def view(*a):
        now[0] += seconds
        return real(*a)

    monkeypatch.setattr(stage1, "time", types.SimpleNamespace(perf_counter=lambda: now[0]))
    monkeypatch.setattr(stage1, "eval_pixels", view)


def test_untrained_field_at_256_px_renders_in_4x_the_work_of_128_px(scene_factory):
    """A foggy field marches to the far bound. Trained at 256 px its render does 4x the work of 128 px (the pixels),
    not 8x: the early march budget does not follow the image size. The work (samples evaluated) is what is
    asserted, as a count; the render times it leads to are bench scale's figures (`render_ms`), not a test's."""
    from repaint_nerf.core.render.renderer import RenderOptions, render_camera
    from repaint_nerf.core.scene.loaders.detect import load_scene
    from repaint_nerf.core.train.stage1 import Stage1Trainer, TrainConfig

    path = scene_factory("demo", size=256, views=2, test_views=1)
    small, big = (Stage1Trainer(load_scene(path, max_size=side), None, TrainConfig(seed=0, grid_resolution=32))
                  for side in (128, 256))
    ev = small.evaluate(full=True, max_views=1)
    work_small = ev["samples_per_ray"] * ev["pixels"]
    ev = big.evaluate(full=True, max_views=1)
    early = small.cfg.early_max_samples  # both sizes march the early budget while their field is fog
    assert ev["pixels"] == 256 * 256 and ev["samples_per_ray"] <= big.march_samples == small.march_samples == early
    assert ev["samples_per_ray"] * ev["pixels"] <= 4.0 * work_small * 1.01
    # the same field rendered at 256 px by the renderer directly marches the same samples per ray
    opts = RenderOptions(outputs=("rgb",), background=small.eval_background(), perturb=False,
                         max_samples=small.march_samples)
    ref = render_camera(small.field, small.grid, big.scene.field_cameras("test"), 0, opts)
    assert abs(ref["stats"]["samples_per_ray"] - ev["samples_per_ray"]) <= 0.05 * ev["samples_per_ray"]


def test_big_photos_are_held_at_training_resolution_and_decoded_one_at_a_time(tmp_path, monkeypatch):
    """Large photos: every decoded full-size image is gone before the next is decoded, and what the scene and the
    trainer hold is the training resolution's bytes (images stored at the size they are sampled at)."""
    import weakref

    from repaint_nerf.core.scene.loaders import images as images_mod
    from repaint_nerf.core.scene.loaders.detect import load_scene
    from repaint_nerf.core.train.stage1 import Stage1Trainer, TrainConfig

    write_blender(tmp_path, {"train": 6, "test": 2}, w=1200, h=900, fl=1000.0, rgba=False)
    decoded: list[weakref.ref] = []
    most_alive = [0]
    real = images_mod.to_uint8_rgb

    def tracking(img):
        out = real(img)
        most_alive[0] = max(most_alive[0], sum(r() is not None for r in decoded))
        decoded.append(weakref.ref(out))
        return out

    monkeypatch.setattr(images_mod, "to_uint8_rgb", tracking)
    scene = load_scene(tmp_path)  # default --max-size 512
    assert len(decoded) == 8 and most_alive[0] == 0  # at most one full-size image alive at a time
    assert all(r() is None for r in decoded)
    held = [im for s in scene.splits.values() for im in s.images]
    assert all(im.shape == (384, 512, 3) for im in held)
    assert sum(im.nbytes for im in held) == 8 * 384 * 512 * 3
    tr = Stage1Trainer(scene, None, TrainConfig(seed=0, rays_per_batch=64, grid_resolution=16))
    assert tr.pixels.dtype == torch.uint8 and tr.pixels.numel() == 6 * 384 * 512 * 3


def test_bounded_evaluation_pixels_cover_the_whole_view_at_every_size():
    """The bounded evaluation's pixels are the centres of a side x side split of the view: the same places in the
    scene at 128 and 256 px (a crop covered 4x less of the view at 256 px, often only background)."""
    from repaint_nerf.core.train.stage1 import eval_pixels

    for w, h in ((128, 128), (256, 256), (300, 200), (20, 30)):
        us, vs = eval_pixels(w, h, 48)
        assert len(us) == min(48, w) and len(vs) == min(48, h)
        assert np.all(np.diff(us) > 0) and np.all(np.diff(vs) > 0) and us[-1] < w and vs[-1] < h
        # each pixel is the centre of its 1/48 of the view: the span covers the view from edge to edge
        ref_u = [int((j + 0.5) * w / len(us)) for j in range(len(us))]
        assert us.tolist() == ref_u and us[0] <= w / 48 and us[-1] >= w - w / 48 - 1
    small, big = eval_pixels(128, 128, 48)[0], eval_pixels(256, 256, 48)[0]
    assert np.all(np.abs((small + 0.5) / 128 - (big + 0.5) / 256) <= 1.0 / 128)  # same relative places


def test_foggy_steps_skip_the_filter_pass_with_the_same_result(scene_factory):
    """An untrained field is fog: the density-only filter pass keeps every sample, so the next steps (until the grid's
    next update) evaluate them with grad in one pass: the same losses and weights as filtering, less work."""
    from repaint_nerf.core.scene.loaders.detect import load_scene
    from repaint_nerf.core.train.stage1 import Stage1Trainer, TrainConfig

    scene = load_scene(scene_factory("demo", size=32, views=4, test_views=2))
    runs = {}
    for kept in (0.99, 2.0):  # 2.0: never skip (the filter every step)
        cfg = TrainConfig(seed=0, rays_per_batch=256, grid_resolution=16, max_samples=64, early_max_samples=0,
                          grid_update_every=4, one_pass_kept=kept)
        tr = Stage1Trainer(scene, None, cfg)
        runs[kept] = (tr, [tr.step() for _ in range(6)])
    (skip, infos), (never, ref) = runs[0.99], runs[2.0]
    assert skip.filter_kept == 1.0  # fog: the filter kept every candidate
    # one pass after a filtered step, the filter again on the grid's update steps (0, 4)
    assert [i["one_pass"] for i in infos] == [False, True, True, True, False, True]
    assert not any(i["one_pass"] for i in ref)
    for a, b in zip(infos, ref):
        assert a["samples_per_ray"] == b["samples_per_ray"] and abs(a["loss"] - b["loss"]) <= 1e-5 * b["loss"]
    for p, q in zip(skip.field.parameters(), never.field.parameters()):
        assert torch.allclose(p, q, rtol=1e-4, atol=1e-6)
    skip.filter_kept = 0.5  # a field that has cleared: its filter drops samples, so it is kept
    assert not skip.step()["one_pass"]
