"""Stage-1 trainer: metrics, losses, schedule and progress bar against plain references; training on a tiny
generated scene raises test PSNR; feature/depth losses cost nothing when off and decrease when on;
checkpoints resume and render identically; `train`/`render` commands end to end with clear errors."""
from __future__ import annotations

import io
import math
from dataclasses import dataclass

import numpy as np
import pytest
import torch

from repaint_nerf.core.train import losses
from repaint_nerf.core.train.metrics import mse_to_psnr, psnr, ssim
from repaint_nerf.core.train.progress import ProgressBar
from repaint_nerf.core.train.schedule import LRSchedule


def _field_available() -> bool:
    try:
        import repaint_nerf.core.field.field as field  # noqa: F401
        return True
    except ImportError:
        return False


@dataclass
class TinyFieldConfig:
    """Config of the stand-in field used while `core.field.field` is not built."""

    resolution: int = 24
    feature_dim: int = 0
    bound: float = 1.0


class TinyField(torch.nn.Module):
    """A dense trilinear voxel field with the NGPField interface (density, forward, parameter_groups)."""

    def __init__(self, cfg: TinyFieldConfig):
        super().__init__()
        self.cfg = cfg
        r = cfg.resolution
        self.geo = torch.nn.Parameter(torch.randn(1, 4, r, r, r) * 0.01)
        self.feat = torch.nn.Parameter(torch.zeros(1, cfg.feature_dim, r, r, r)) if cfg.feature_dim else None

    def _sample(self, vol, x):
        g = (x / self.cfg.bound).reshape(1, -1, 1, 1, 3)
        # x30: Adam's step is ~lr per parameter, so this gives the voxels a hash grid's learning speed
        return 30 * torch.nn.functional.grid_sample(vol, g, align_corners=True).reshape(vol.shape[1], -1).T

    def density(self, x):
        inside = (x.abs() <= self.cfg.bound).all(-1)
        return torch.nn.functional.softplus(self._sample(self.geo[:, :1], x)[:, 0] - 1) * inside

    def forward(self, x, d, outputs=("rgb",)):
        v = self._sample(self.geo, x)
        inside = (x.abs() <= self.cfg.bound).all(-1)
        out = {"sigma": torch.nn.functional.softplus(v[:, 0] - 1) * inside}
        if "rgb" in outputs:
            out["rgb"] = torch.sigmoid(v[:, 1:4])
        if "feature" in outputs:
            out["feature"] = self._sample(self.feat, x)
        return out

    def parameter_groups(self):
        return {"grid": [self.geo], "feature": [self.feat] if self.feat is not None else []}


def _use_standin(monkeypatch) -> str:
    import repaint_nerf.core.train.stage1 as stage1

    def make(cfg=None, device=None, image_size=None):
        cfg = cfg or TinyFieldConfig()
        return TinyField(cfg).to(device), cfg

    monkeypatch.setattr(stage1, "make_field", make)
    monkeypatch.setattr(stage1, "field_config_from_dict", lambda d: TinyFieldConfig(**d))
    return "stand-in"


@pytest.fixture
def field_impl(monkeypatch):
    """The real field when built; else the stand-in (patched into the trainer's field factory)."""
    return "real" if _field_available() else _use_standin(monkeypatch)


@pytest.fixture
def standin_field(monkeypatch):
    """The cheap stand-in field, for tests of the trainer's own plumbing (losses, sampling)."""
    return _use_standin(monkeypatch)


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory):
    from repaint_nerf.core.scene.loaders.detect import load_scene
    from repaint_nerf.core.synth.generate import make_scene

    path = make_scene("demo", tmp_path_factory.mktemp("demo32") / "demo", size=32, views=12, seed=0, test_views=3)
    return path, load_scene(path, 1.0)


def _cfg(**kw):
    from repaint_nerf.core.train.stage1 import TrainConfig

    base = dict(rays_per_batch=1024, max_samples=128, grid_resolution=32, seed=0)
    base.update(kw)
    return TrainConfig(**base)


# -- plain pieces ---------------------------------------------------------------------------------------
def test_psnr_and_ssim_against_references():
    rng = np.random.default_rng(0)
    a = rng.random((20, 24, 3)).astype(np.float32)
    b = np.clip(a + rng.normal(0, 0.05, a.shape), 0, 1).astype(np.float32)
    ref = 10 * math.log10(1.0 / np.mean((a - b) ** 2))
    assert psnr(torch.from_numpy(a), torch.from_numpy(b)) == pytest.approx(ref, rel=1e-5)
    assert mse_to_psnr(0.01) == pytest.approx(20.0)
    assert ssim(torch.from_numpy(a), torch.from_numpy(a)) == pytest.approx(1.0, abs=1e-6)
    noisy = ssim(torch.from_numpy(a), torch.from_numpy(b))
    assert 0.0 < noisy < 0.99
    # A constant image against a shifted constant: only the luminance term, computed by hand.
    x, y = torch.full((16, 16, 1), 0.2), torch.full((16, 16, 1), 0.6)
    c1 = 0.01 ** 2
    assert ssim(x, y) == pytest.approx((2 * 0.2 * 0.6 + c1) / (0.2 ** 2 + 0.6 ** 2 + c1), rel=1e-4)


def test_losses_match_definitions():
    p, t = torch.tensor([[0.0, 0.5, 1.0]]), torch.tensor([[1.0, 0.5, 0.0]])
    assert float(losses.color_loss(p, t)) == pytest.approx(2 / 3)
    assert float(losses.color_loss(p, t, "huber", delta=0.1)) == pytest.approx(2 * 0.1 * (1 - 0.05) / 3)
    z = torch.tensor([1.0, 2.0, 5.0])
    zt = torch.tensor([1.5, float("nan"), 1.0])
    valid = torch.isfinite(zt)
    assert float(losses.depth_loss(z, zt, valid)) == pytest.approx((0.25 + 16) / 2)
    assert float(losses.depth_loss(z, zt, torch.zeros(3, dtype=torch.bool))) == 0.0
    total = losses.stage1_loss(torch.tensor(1.0), torch.tensor(2.0), torch.tensor(3.0), 0.5, 0.1)
    assert float(total) == pytest.approx(1 + 1 + 0.3)  # paper Eq. s1
    assert float(losses.stage1_loss(torch.tensor(1.0), None, None, 0.5, 0.1)) == 1.0


def test_schedule():
    s = LRSchedule("exp", final_factor=0.1)
    assert s.factor(0) == 1.0 and s.factor(1) == pytest.approx(0.1) and s.factor(0.5) == pytest.approx(0.1 ** 0.5)
    assert s.factor(2.0) == pytest.approx(0.1)
    st = LRSchedule("step")
    assert st.factor(0.4) == 1.0 and st.factor(0.8) == pytest.approx(0.33 ** 2)
    w = LRSchedule("const", warmup=0.1)
    assert w.factor(0.0) == pytest.approx(0.1) and w.factor(0.2) == 1.0


def test_lr_progress_follows_steps_and_a_time_budget_anneals_its_end():
    """Keyed to steps, a slower run (a larger image) has the same rate at the same step; a time budget only brings
    the decay to its end over its last `anneal` share; anneal 1.0 is the old rule (by the seconds throughout)."""
    from repaint_nerf.core.train.schedule import training_progress as tp

    fast, slow = tp(500, 40.0, None, 300.0, 20000, 0.25), tp(500, 200.0, None, 300.0, 20000, 0.25)
    assert fast == slow == pytest.approx(500 / 20000)
    assert tp(500, 262.5, None, 300.0, 20000, 0.25) == pytest.approx(0.5)  # halfway through the last quarter
    assert tp(500, 300.0, None, 300.0, 20000, 0.25) == 1.0 and tp(500, 900.0, None, 300.0, 20000, 0.25) == 1.0
    assert tp(500, 200.0, None, 300.0, 20000, 1.0) == pytest.approx(200 / 300)  # by time throughout
    assert tp(500, 200.0, 1000, None, 20000, 0.25) == pytest.approx(0.5)  # a step budget
    assert tp(800, 10.0, 1000, 300.0, 20000, 0.25) == pytest.approx(0.8)  # both: whichever is further
    assert tp(40000, 0.0, None, None, 20000, 0.25) == 1.0  # open-ended: the horizon, clamped


def test_progress_bar_text():
    buf = io.StringIO()
    bar = ProgressBar(total_steps=100, stream=buf)
    text = bar.format(0, 0.0)
    text = bar.format(50, 10.0, psnr=23.456)
    assert "50%" in text and "50/100" in text and "ETA 00:10" in text and "23.46 dB" in text and "5.0 it/s" in text
    bar.update(50, 23.4, force=True)
    bar.close(100, 25.0)
    assert buf.getvalue().strip().splitlines()[-1].startswith("train 100%|" + "#" * 24 + "|")
    timed = ProgressBar(total_seconds=60, stream=io.StringIO())
    timed.format(0, 0.0)
    assert " 25%|" in timed.format(30, 15.0) and "ETA 00:45" in timed.format(30, 15.0)


# -- the trainer ------------------------------------------------------------------------------------------
def test_training_raises_test_psnr(tiny_scene, field_impl):
    from repaint_nerf.core.train.stage1 import Stage1Trainer

    _, scene = tiny_scene
    tr = Stage1Trainer(scene, None, _cfg(rays_per_batch=1024))
    before = tr.evaluate()["psnr"]
    tr.plan(steps=40)  # a few seconds on an idle machine (steps, not seconds: the test must not depend on load)
    info = tr.train(steps=40)
    after = tr.evaluate()["psnr"]
    assert info["step"] == tr.step_count == 40
    assert set(info) >= {"color", "loss", "psnr", "seconds", "lr"}
    assert after > before + 4.0, (before, after, tr.step_count, field_impl)
    assert tr.done


def test_seeded_and_reproducible(tiny_scene, standin_field):
    from repaint_nerf.core.train.stage1 import Stage1Trainer

    _, scene = tiny_scene
    runs = []
    for _ in range(2):
        tr = Stage1Trainer(scene, None, _cfg(rays_per_batch=256))
        runs.append([tr.step()["loss"] for _ in range(3)])
    assert runs[0] == runs[1]


def test_an_interlude_within_the_forward_pass_changes_neither_the_update_nor_the_step_time(tiny_scene, field_impl):
    """The editor's worker renders a new view within a step (`interlude`): at each marching round's start, before
    the differentiable pass and after the forward pass. The render sees the parameters before the update, the
    update is the one a step without it makes, and the interlude's time is not the step's."""
    import time

    from repaint_nerf.core.render.renderer import RenderOptions, render_rays
    from repaint_nerf.core.train.stage1 import Stage1Trainer

    _, scene = tiny_scene
    plain = Stage1Trainer(scene, None, _cfg(rays_per_batch=256))
    a = plain.step()
    paused = Stage1Trainer(scene, None, _cfg(rays_per_batch=256))  # seeded as `plain` was
    seen, differentiable, at_call = [], [], []
    paused.field.grid.register_forward_hook(lambda m, i, o: differentiable.append(1) if torch.is_grad_enabled()
                                            else None)

    def interlude():
        assert all(p.grad is None for p in paused.field.parameters())  # before the backward pass
        at_call.append(len(differentiable))
        o = torch.zeros(64, 3, device=paused.device) + torch.tensor([0.0, 0.0, -2.0], device=paused.device)
        jitter = torch.randn(64, 3, generator=torch.Generator().manual_seed(len(seen))).to(paused.device)
        d = torch.nn.functional.normalize(jitter * 0.1 + torch.tensor([0.0, 0.0, 1.0], device=paused.device), dim=-1)
        paused.field.eval()
        with torch.no_grad():
            seen.append(render_rays(paused.field, paused.grid, o, d, RenderOptions(outputs=("rgb",)))["rgb"])
        paused.field.train()
        time.sleep(0.3)

    b = paused.step(interlude)
    assert len(seen) >= 3 and all(torch.isfinite(x).all() for x in seen)
    assert at_call[0] == 0 and at_call[-2] == 0 and at_call[-1] >= 1  # before the differentiable pass, and after
    assert a["loss"] == b["loss"] and b["seconds"] < 0.3 and paused.train_seconds < 0.3
    for p, q in zip(plain.field.parameters(), paused.field.parameters()):
        assert torch.equal(p, q)


def test_random_background_targets(tiny_scene, standin_field):
    from repaint_nerf.core.train.stage1 import Stage1Trainer

    _, scene = tiny_scene
    tr = Stage1Trainer(scene, None, _cfg(rays_per_batch=4096))
    assert tr.has_alpha and tr.pixels.dtype == torch.uint8 and tr.pixels.shape[0] == 12 * 32 * 32
    b = tr.make_batch()
    idx_img, u, v = tr.pixel_coords(torch.tensor([0, 31, 32, 32 * 32 + 5], device=tr.device))
    assert idx_img.tolist() == [0, 0, 0, 1] and u.tolist() == [0, 31, 0, 5] and v.tolist() == [0, 0, 1, 0]
    bg = b["background"]
    assert bg.shape == (4096, 3) and bg.std() > 0.2  # a random colour per ray
    # Where the image is transparent the target is exactly the background colour of that ray.
    torch.manual_seed(0)
    tr2 = Stage1Trainer(scene, None, _cfg(rays_per_batch=4096))
    idx = tr2.sample_pixels(4096)
    alpha = tr2.pixels[idx, 3]
    tr2.gen.manual_seed(0)
    b2 = tr2.make_batch()
    clear = alpha == 0
    assert clear.any()
    assert torch.allclose(b2["rgb"][clear], b2["background"][clear])


class _Spy:
    def __init__(self, fn):
        self.fn, self.outputs = fn, []

    def __call__(self, field, grid, origins, dirs, opts):
        self.outputs.append(tuple(opts.outputs))
        return self.fn(field, grid, origins, dirs, opts)


def test_feature_and_depth_are_free_when_off(tiny_scene, field_impl, monkeypatch):
    import repaint_nerf.core.train.stage1 as stage1

    _, scene = tiny_scene
    spy = _Spy(stage1.render_rays)
    monkeypatch.setattr(stage1, "render_rays", spy)
    tr = stage1.Stage1Trainer(scene, None, _cfg(rays_per_batch=256, reopen_error=0.0))
    info = tr.step()
    assert spy.outputs == [("rgb",)]
    assert "feature" not in info and "depth" not in info
    assert tr.features is None and tr.depth is None


def test_feature_and_depth_losses_act_when_on(tiny_scene, standin_field, monkeypatch):
    import repaint_nerf.core.train.stage1 as stage1

    _, scene = tiny_scene
    spy = _Spy(stage1.render_rays)
    monkeypatch.setattr(stage1, "render_rays", spy)
    n = len(scene.train)
    target = np.zeros((16, 16, 8), np.float32)  # half resolution, like the compressed cache
    target[..., 0] = 1.0
    # a constant z-depth of 4 world units where the image shows something (nothing to hit elsewhere)
    depth = [np.where(im[..., 3] > 0, 4.0, np.nan).astype(np.float32) for im in scene.train.images]
    ends = {}
    for weight in (1.0, 1e-6):  # same seed and batches; only the weight of Eq. s1's extra terms differs
        tr = stage1.Stage1Trainer(scene, None, _cfg(rays_per_batch=512, lambda_feature=weight, lambda_depth=weight),
                                  feature_targets=[target] * n, depth_priors=depth)
        assert tr.field_cfg.feature_dim == 8
        first = tr.step()
        tr.train(steps=30)
        last = [tr.step() for _ in range(3)]
        ends[weight] = (first, {k: np.mean([i[k] for i in last]) for k in ("feature", "depth")})
    assert set(spy.outputs[0]) == {"rgb", "feature", "depth", "opacity"}  # depth, opacity: for reopening
    (first, on), (_, off) = ends[1.0], ends[1e-6]
    assert on["feature"] < 0.5 * first["feature"] and on["feature"] < 0.5 * off["feature"], (first, on, off)
    assert on["depth"] < 0.5 * off["depth"], (first, on, off)
    # Depth priors are converted to field units with the scene's scale.
    assert float(torch.nanmean(tr.depth)) == pytest.approx(4.0 * scene.norm.scale, rel=1e-5)


def test_feature_targets_of_transparent_pixels_are_zero(tiny_scene, standin_field):
    """Empty space renders a zero feature, so an RGBA pixel's feature target is the teacher's times alpha
    (the teacher saw the image over white; chasing that feature grew floaters in the background)."""
    from repaint_nerf.core.train.stage1 import Stage1Trainer

    _, scene = tiny_scene
    n = len(scene.train)
    target = np.ones((32, 32, 4), np.float32)
    tr = Stage1Trainer(scene, None, _cfg(rays_per_batch=4096), feature_targets=[target] * n)
    idx = tr.sample_pixels(4096)
    alpha = tr.pixels[idx, 3].float() / 255.0
    tr.gen.manual_seed(tr.cfg.seed)
    torch.manual_seed(0)
    tr2 = Stage1Trainer(scene, None, _cfg(rays_per_batch=4096), feature_targets=[target] * n)
    b = tr2.make_batch()
    assert (alpha == 0).any() and (alpha == 1).any()
    assert torch.allclose(b["feature"].float(), alpha[:, None].expand(-1, 4), atol=1e-3)


def test_worst_rays_reopen_the_grid_in_front_of_their_surface(tiny_scene, standin_field, monkeypatch):
    """Each step hands the rays with the largest colour error (above reopen_error, at most reopen_fraction of
    the batch) to OccupancyGrid.reopen, up to their depth where they hit something, whole where they don't."""
    from repaint_nerf.core.train.stage1 import Stage1Trainer

    _, scene = tiny_scene
    calls = []
    tr = Stage1Trainer(scene, None, _cfg(rays_per_batch=1000, reopen_fraction=0.01, reopen_error=0.005))
    monkeypatch.setattr(tr.grid, "reopen", lambda o, d, t: calls.append((o, d, t)))
    batch = tr.make_batch()
    rgb = batch["rgb"].clone()
    rgb[:5] = 1.0 - rgb[:5]  # five rays far off
    rgb[5:20] = (rgb[5:20] + 0.1).clamp(max=1.0)  # fifteen a little off, three with no room to move
    rgb[5:20, 0] = torch.where(rgb[5:20, 0] > 0.95, rgb[5:20, 0] - 0.15, rgb[5:20, 0])
    out = {"rgb": rgb, "opacity": torch.cat([torch.ones(3), torch.zeros(997)]).to(rgb.device),
           "depth": torch.full((1000,), 2.0, device=rgb.device)}
    err = ((rgb - batch["rgb"]) ** 2).mean(-1)
    tr._reopen_worst(batch, out)
    (o, d, t), = calls
    assert o.shape == (10, 3)  # the batch's worst 1%
    assert torch.equal(d, batch["dirs"][err.topk(10).indices])
    hit = out["opacity"][err.topk(10).indices] > 0.5
    assert (t[hit] == 2.0).all() and torch.isinf(t[~hit]).all()
    calls.clear()
    tr.cfg.reopen_error = 10.0  # nothing that bad: nothing reopened
    tr._reopen_worst(batch, out)
    assert calls == []


def test_sparse_depth_priors_get_extra_rays(tiny_scene, standin_field):
    import repaint_nerf.core.train.stage1 as stage1

    _, scene = tiny_scene
    n = len(scene.train)
    pts = [{"u": np.array([3.5, 10.2]), "v": np.array([4.5, 20.9]), "z": np.array([2.0, 3.0])} for _ in range(n)]
    tr = stage1.Stage1Trainer(scene, None, _cfg(rays_per_batch=512, lambda_depth=1.0), depth_priors=pts)
    assert tr.depth_pixels is not None and tr.depth_pixels.numel() == 2 * n
    assert float(tr.depth[4 * 32 + 3]) == pytest.approx(2.0 * scene.norm.scale)
    b = tr.make_batch()
    assert b["rgb"].shape[0] == 512 + 64 and torch.isfinite(b["depth"][512:]).all()
    assert math.isfinite(tr.step()["depth"])


# -- checkpoints --------------------------------------------------------------------------------------------
def test_checkpoint_resume_and_identical_render(tiny_scene, field_impl, tmp_path):
    from repaint_nerf.core.render.renderer import RenderOptions, render_camera
    from repaint_nerf.core.train.checkpoint import Checkpoint
    from repaint_nerf.core.train.stage1 import Stage1Trainer, restore_field
    from repaint_nerf.core.workspace.workspace import Workspace

    _, scene = tiny_scene
    ws = Workspace.create(tmp_path / "ws")
    tr = Stage1Trainer(scene, ws, _cfg(rays_per_batch=256))
    tr.train(steps=20)
    path = tr.save_checkpoint()
    # Resuming continues exactly where an uninterrupted run would be (the RNG states are part of the checkpoint).
    more = [tr.step()["loss"] for _ in range(3)]
    tr2 = Stage1Trainer(scene, ws, _cfg(rays_per_batch=256))
    assert tr2.resume() and tr2.step_count == 20
    again = [tr2.step()["loss"] for _ in range(3)]
    assert again == pytest.approx(more, rel=1e-6, abs=1e-9)
    # A field restored from the file renders what the saved one rendered.
    cams = scene.field_cameras("test")
    opts = RenderOptions(outputs=("rgb", "depth"), perturb=False)
    tr_ref = Stage1Trainer(scene, None, _cfg(rays_per_batch=256))
    tr_ref.load(Checkpoint.load(path))
    ref = render_camera(tr_ref.field, tr_ref.grid, cams, 0, opts)
    fld, grid, header = restore_field(Checkpoint.load(path))
    got = render_camera(fld, grid, cams, 0, opts)
    assert header.step == 20
    assert torch.allclose(got["rgb"], ref["rgb"], atol=1e-6) and torch.allclose(got["depth"], ref["depth"], atol=1e-6)
    assert not torch.allclose(got["rgb"], render_camera(tr.field, tr.grid, cams, 0, opts)["rgb"], atol=1e-6)
    # The reconstruction becomes a version that later versions do not overwrite.
    v = tr2.save_version()
    assert ws.original_version.id == v.id and ws.current_version.kind == "stage1"


def test_the_grid_rate_grows_with_the_image_on_a_cpu_only():
    """The paper's rate up to 256 px, 3x from 512 px (a large image's run waits on its step count), 1x on CUDA."""
    from repaint_nerf.core.train.stage1 import grid_lr_factor_for

    cpu, cuda = torch.device("cpu"), torch.device("cuda")
    assert [grid_lr_factor_for(cpu, s) for s in (32, 128, 256, 512, 1000, 4000)] == [1.0, 1.0, 1.0, 3.0, 3.0, 3.0]
    assert grid_lr_factor_for(cpu, 362) == pytest.approx(1.0 + 2.0 * math.log2(362 / 256))
    assert grid_lr_factor_for(cuda, 512) == grid_lr_factor_for(cuda, 32) == 1.0


def test_the_grid_rate_factor_holds_through_the_schedule_and_a_resume(tiny_scene, standin_field, tmp_path):
    from repaint_nerf.core.train.stage1 import Stage1Trainer
    from repaint_nerf.core.workspace.workspace import Workspace

    _, scene = tiny_scene
    auto = Stage1Trainer(scene, None, _cfg(rays_per_batch=256))
    assert auto.cfg.grid_lr_factor == 1.0  # 32 px: the paper's rate for every group

    def rates(tr):
        return {g["name"]: g["lr"] for g in tr.optimizer.param_groups}

    ws = Workspace.create(tmp_path / "ws")
    tr = Stage1Trainer(scene, ws, _cfg(rays_per_batch=256, grid_lr_factor=3.0, horizon_steps=40))
    assert rates(tr)["grid"] == pytest.approx(3.0 * tr.cfg.lr)
    tr.train(steps=20)
    scheduled = tr._set_lr()  # the paper's rate at this point of the schedule
    assert scheduled < tr.cfg.lr and rates(tr)["grid"] == pytest.approx(3.0 * scheduled)
    tr.save_checkpoint()
    tr2 = Stage1Trainer(scene, ws, _cfg(rays_per_batch=256, grid_lr_factor=3.0, horizon_steps=40))
    assert tr2.resume()
    tr2.step()
    tr.step()
    assert rates(tr2) == pytest.approx(rates(tr))


# -- command line ----------------------------------------------------------------------------------------------
def test_cli_train_and_render(tiny_scene, field_impl, tmp_path, capsys):
    from repaint_nerf.app.cli import main

    path, _ = tiny_scene
    ws = tmp_path / "ws"
    assert main(["train", str(path), "--workspace", str(ws), "--steps", "15", "--rays", "512",
                 "--max-samples", "128"]) == 0
    out = capsys.readouterr()
    assert "test PSNR" in out.out and "saved version v0001" in out.out
    assert (ws / "checkpoints" / "stage1.safetensors").exists()
    assert main(["train", str(path), "--workspace", str(ws), "--steps", "20", "--rays", "512",
                 "--max-samples", "128", "--resume"]) == 0
    assert "resumed at step 15" in capsys.readouterr().out
    outdir = tmp_path / "renders"
    assert main(["render", str(ws), "--split", "test", "--out", str(outdir), "--depth"]) == 0
    assert sorted(p.name for p in outdir.iterdir()) == ["test_000.png", "test_000_depth.png", "test_001.png",
                                                        "test_001_depth.png", "test_002.png", "test_002_depth.png"]
    import cv2

    assert cv2.imread(str(outdir / "test_000.png")).shape == (32, 32, 3)
    tt = tmp_path / "tt"
    assert main(["render", str(ws), "--split", "turntable", "--out", str(tt), "--frames", "4", "--scale", "0.5"]) == 0
    text = capsys.readouterr().out
    assert len(list(tt.glob("turntable_*.png"))) == 4
    assert cv2.imread(str(tt / "turntable_000.png")).shape == (16, 16, 3)
    assert (tt / "turntable.mp4").exists() or "PNGs only" in text


def test_cli_bad_input(tmp_path, capsys):
    from repaint_nerf.app.cli import main

    assert main(["train", str(tmp_path / "nope"), "--workspace", str(tmp_path / "ws"), "--steps", "1"]) == 2
    err = capsys.readouterr().err
    assert "nope" in err and "no such" in err and "Traceback" not in err
    assert main(["render", str(tmp_path / "missing_ws"), "--out", str(tmp_path / "o")]) == 2
    assert "missing_ws" in capsys.readouterr().err
    (tmp_path / "notws").mkdir()
    (tmp_path / "notws" / "x.txt").write_text("hi")
    assert main(["render", str(tmp_path / "notws"), "--out", str(tmp_path / "o")]) == 2
    assert "not a repaint-nerf workspace" in capsys.readouterr().err


def test_cli_rejects_a_bad_distortion_before_touching_the_workspace(tiny_scene, tmp_path, capsys):
    from repaint_nerf.app.cli import main

    path, _ = tiny_scene
    ws = tmp_path / "ws"
    for bad in ("-1", "inf", "nan"):
        assert main(["train", str(path), "--workspace", str(ws), "--steps", "1", "--distortion", bad]) == 2
        err = capsys.readouterr().err
        assert "--distortion" in err and "Traceback" not in err
        assert not ws.exists()
    assert main(["bench", "recon", "--scene", str(path), "--seconds", "1", "--distortion", "inf",
                 "--json", str(tmp_path / "r.json")]) == 2
    assert "--distortion" in capsys.readouterr().err and not (tmp_path / "r.json").exists()


class _ManualStream:
    """A feature stream (core.teachers.feature_stream) whose codes the test hands over itself."""

    def __init__(self, maps):
        self.maps, self.dims, self.sizes = maps, maps[0].shape[-1], [m.shape[:2] for m in maps]
        self.pending, self.received, self.stopped, self.threads = [], 0, False, 1

    def __len__(self):
        return len(self.maps)

    def send(self, *views):
        self.pending += [(i, torch.from_numpy(self.maps[i]).half()) for i in views]

    def poll(self):
        out, self.pending = self.pending, []
        self.received += len(out)
        return out

    @property
    def complete(self):
        return self.received == len(self.maps)

    def stop(self):
        self.stopped = True


def test_features_streamed_in_join_the_loss_view_by_view(tiny_scene, standin_field, monkeypatch):
    """With codes still being computed, colour trains alone; each view's feature loss joins when its codes
    arrive (only its rays count), and once all have arrived the trainer drops the stream."""
    import repaint_nerf.core.train.stage1 as stage1

    _, scene = tiny_scene
    spy = _Spy(stage1.render_rays)
    monkeypatch.setattr(stage1, "render_rays", spy)
    n = len(scene.train)
    maps = [np.full((32, 32, 4), float(i + 1), np.float32) for i in range(n)]
    stream = _ManualStream(maps)
    tr = stage1.Stage1Trainer(scene, None, _cfg(rays_per_batch=512), feature_targets=stream)
    assert tr.field_cfg.feature_dim == 4 and tr.feature_stream is stream
    info = tr.step()
    assert "feature" not in info and "feature" not in spy.outputs[-1]  # nothing to distil yet: not rendered
    targets, real = [], stage1.losses.feature_loss
    monkeypatch.setattr(stage1.losses, "feature_loss", lambda pred, target: (targets.append(target), real(pred, target))[1])
    batches, make = [], tr.make_batch
    monkeypatch.setattr(tr, "make_batch", lambda: (batches.append(make()), batches[-1])[1])
    stream.send(2)
    tr.step()
    from_2 = batches[0]["image"] == 2
    assert len(targets) == 1 and 0 < len(targets[0]) == int(from_2.sum())  # view 2's rays only
    assert torch.equal(targets[0], batches[0]["feature"][from_2]) and float(targets[0].max()) == 3.0
    assert "feature" in spy.outputs[-1] and bool(tr.feature_ready[2]) and int(tr.feature_ready.sum()) == 1
    a, b = int(tr.feat_offsets[2]), int(tr.feat_offsets[3])
    assert torch.all(tr.features[a:b] == 3.0) and torch.all(tr.features[:a] == 0)
    batch = tr.make_batch()
    assert torch.equal(batch["feature_ready"], batch["image"] == 2)
    stream.send(*[i for i in range(n) if i != 2])
    tr.close()
    assert stream.stopped
    tr.step()
    assert tr.feature_stream is None and tr.feature_ready is None and "feature_ready" not in tr.make_batch()
    assert torch.equal(tr.features, torch.cat([torch.from_numpy(m).reshape(-1, 4) for m in maps]).half())
