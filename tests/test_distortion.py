"""Distortion loss (mip-NeRF 360, Eq. 15): the O(N) packed form against the plain double sum, values and
gradients; the renderer's per-ray output on a surface against a fog; the trainer's term lowers it when on."""
from __future__ import annotations

import pytest
import torch

from repaint_nerf.core.render.analytic import GaussianField, SphereField
from repaint_nerf.core.render.composite import distortion
from repaint_nerf.core.render.occupancy import OccupancyGrid
from repaint_nerf.core.render.renderer import RenderOptions, render_rays


def _plain(w, s0, s1, ray, n):
    """The definition, ray by ray: sum_ij w_i w_j |m_i - m_j| + 1/3 sum_i w_i^2 (s1_i - s0_i)."""
    out = []
    for r in range(n):
        k = ray == r
        wr, m = w[k], 0.5 * (s0[k] + s1[k])
        out.append((wr[:, None] * wr[None, :] * (m[:, None] - m[None, :]).abs()).sum()
                   + (wr ** 2 * (s1[k] - s0[k])).sum() / 3)
    return torch.stack(out)


def test_packed_distortion_equals_the_double_sum_with_its_gradient():
    g = torch.Generator().manual_seed(0)
    counts = [0, 1, 7, 30, 3]  # a ray with no sample and one with a single sample among them
    ray = torch.repeat_interleave(torch.arange(len(counts)), torch.tensor(counts))
    edges = [torch.cumsum(torch.rand(c + 1, generator=g, dtype=torch.float64), 0) for c in counts]
    s0 = torch.cat([e[:-1] for e in edges])
    s1 = torch.cat([e[1:] for e in edges])
    w1 = torch.rand(len(ray), generator=g, dtype=torch.float64).requires_grad_()
    w2 = w1.detach().clone().requires_grad_()
    fast, ref = distortion(w1, s0, s1, ray, len(counts)), _plain(w2, s0, s1, ray, len(counts))
    torch.testing.assert_close(fast, ref)
    assert float(fast[0].detach()) == 0.0
    (fast * torch.arange(1.0, 6.0, dtype=torch.float64)).sum().backward()
    (ref * torch.arange(1.0, 6.0, dtype=torch.float64)).sum().backward()
    torch.testing.assert_close(w1.grad, w2.grad)


def _rays(n: int = 64):
    g = torch.Generator().manual_seed(1)
    o = torch.tensor([0.0, 0.0, -2.0]).expand(n, 3).clone()
    d = torch.nn.functional.normalize(torch.tensor([0.0, 0.0, 1.0]) + 0.05 * torch.randn(n, 3, generator=g), dim=-1)
    return o, d


def test_a_surface_has_less_distortion_than_a_fog_and_rounds_give_the_filter_value():
    o, d = _rays()
    grid = OccupancyGrid(resolution=32, bound=1.0, device="cpu")
    opts = RenderOptions(outputs=("rgb", "distortion"), max_samples=256)
    hard = render_rays(SphereField(radius=0.5, sigma=200.0), grid, o, d, opts)["distortion"]
    fog = render_rays(GaussianField(scale=0.6, sigma=1.5), grid, o, d, opts)["distortion"]
    assert hard.shape == (64,) and bool((hard >= 0).all())
    assert float(hard.mean()) < 0.2 * float(fog.mean()), (float(hard.mean()), float(fog.mean()))
    rounds = render_rays(GaussianField(scale=0.6, sigma=1.5), grid, o, d,
                         RenderOptions(outputs=("rgb", "distortion"), max_samples=256, strategy="rounds"))
    torch.testing.assert_close(rounds["distortion"], fog)


def test_the_trainer_term_lowers_the_distortion(monkeypatch, tmp_path_factory):
    from test_train_stage1 import _cfg, _use_standin

    from repaint_nerf.core.scene.loaders.detect import load_scene
    from repaint_nerf.core.synth.generate import make_scene
    import repaint_nerf.core.train.stage1 as stage1

    _use_standin(monkeypatch)
    path = make_scene("demo", tmp_path_factory.mktemp("demo32") / "demo", size=32, views=12, seed=0, test_views=3)
    scene = load_scene(path, 1.0)
    ends = {}
    for weight in (0.0, 1.0):  # same seed and batches; only the distortion weight differs
        tr = stage1.Stage1Trainer(scene, None, _cfg(rays_per_batch=512, lambda_distortion=weight))
        tr.train(steps=40)
        o, d = tr.scene.field_cameras("train")[0].image_rays(0)[:2]
        with torch.no_grad():
            out = render_rays(tr.field, tr.grid, o, d, RenderOptions(outputs=("rgb", "distortion"), max_samples=128))
        ends[weight] = float(out["distortion"].mean())
        info = tr.step()
        assert ("distortion" in info) == (weight > 0)
    assert ends[1.0] < 0.5 * ends[0.0], ends


def test_auto_weight_is_on_for_forward_facing_scenes_only(tmp_path):
    from test_train_stage1 import _cfg

    from repaint_nerf.core.scene.loaders.detect import load_scene
    from repaint_nerf.core.synth.generate import make_scene
    from repaint_nerf.core.train.stage1 import FORWARD_DISTORTION, Stage1Trainer

    weights = {}
    for preset in ("forward", "demo"):
        scene = load_scene(make_scene(preset, tmp_path / preset, size=24, views=6, seed=0, test_views=1), 1.0)
        tr = Stage1Trainer(scene, None, _cfg(rays_per_batch=128))
        weights[preset] = (tr.cfg.lambda_distortion, "distortion" in tr.outputs)
        assert Stage1Trainer(scene, None, _cfg(rays_per_batch=128, lambda_distortion=0.0)).outputs == ("rgb", "depth",
                                                                                                     "opacity")
    assert weights == {"forward": (FORWARD_DISTORTION, True), "demo": (0.0, False)}
