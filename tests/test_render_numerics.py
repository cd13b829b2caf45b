"""Compositing numerics (extreme densities and steps against float64), gradients, output selection,
chunking, strategies agreeing, background handling, render_camera shapes and z-depth, cancellation."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from repaint_nerf.core.errors import UserError
from repaint_nerf.core.render.analytic import BoxField, SphereField
from repaint_nerf.core.render.composite import composite
from repaint_nerf.core.render.occupancy import OccupancyGrid, default_step
from repaint_nerf.core.render.renderer import RenderOptions, render_camera, render_rays
from repaint_nerf.core.scene.cameras import Cameras, look_at


def _reference(sigma, delta, ray, n_rays, rgb):
    """Plain float64 per-ray loop: T_i = exp(-sum_{j<i} sigma_j delta_j), alpha = 1 - exp(-sigma delta)."""
    sigma, delta, rgb = (np.asarray(a, dtype=np.float64) for a in (sigma, delta, rgb))
    out_rgb, out_op = np.zeros((n_rays, 3)), np.zeros(n_rays)
    for r in range(n_rays):
        m = np.asarray(ray) == r
        tau = sigma[m] * delta[m]
        trans = np.exp(-(np.cumsum(tau) - tau))
        w = trans * -np.expm1(-tau)
        out_op[r] = w.sum()
        out_rgb[r] = (w[:, None] * rgb[m]).sum(0)
    return out_rgb, out_op


@pytest.mark.parametrize("seed", range(4))
def test_composite_extreme_values_match_float64(seed):
    """Densities up to 1e8 and steps down to 1e-9: finite outputs and gradients that agree with float64."""
    g = torch.Generator().manual_seed(seed)
    n_rays, per = 16, 40
    ray = torch.arange(n_rays).repeat_interleave(per)
    n = ray.numel()
    sigma = 10 ** (torch.rand(n, generator=g) * 16 - 8)  # 1e-8 .. 1e8
    sigma[torch.rand(n, generator=g) < 0.2] = 0.0
    delta = 10 ** (torch.rand(n, generator=g) * 9 - 9)  # 1e-9 .. 1
    t_start = torch.cumsum(delta.double(), 0).float() - delta
    rgb = torch.rand(n, 3, generator=g)
    sigma_p = sigma.clone().requires_grad_(True)
    rgb_p = rgb.clone().requires_grad_(True)
    out = composite(sigma_p, t_start, t_start + delta, t_start + delta / 2, ray, n_rays, {"rgb": rgb_p})
    ref_rgb, ref_op = _reference(sigma, (t_start + delta) - t_start, ray, n_rays, rgb)
    assert np.abs(out["opacity"].detach().double().numpy() - ref_op).max() < 1e-5
    assert np.abs(out["rgb"].detach().double().numpy() - ref_rgb).max() < 1e-5
    (out["rgb"].sum() + out["opacity"].sum()).backward()
    assert torch.isfinite(sigma_p.grad).all() and torch.isfinite(rgb_p.grad).all()
    # d opacity / d rgb_i is the weight, which float64 also gives
    assert (rgb_p.grad >= 0).all() and rgb_p.grad.max() <= 1.0 + 1e-6


def test_composite_gradient_matches_float64_autograd():
    g = torch.Generator().manual_seed(7)
    ray = torch.arange(4).repeat_interleave(25)
    sigma = 10 ** (torch.rand(100, generator=g) * 6 - 3)
    delta = torch.full((100,), 0.01)
    t0 = torch.arange(100) * 0.01
    values = torch.rand(100, 3, generator=g)
    grads = []
    for dt in (torch.float32, torch.float64):
        s = sigma.to(dt).detach().clone().requires_grad_(True)
        out = composite(s, t0.to(dt), (t0 + delta).to(dt), t0.to(dt), ray, 4, {"rgb": values.to(dt)})
        (out["rgb"] * torch.tensor([0.3, -0.5, 0.9], dtype=dt)).sum().backward()
        grads.append(s.grad.double())
    assert torch.allclose(grads[0], grads[1], rtol=1e-3, atol=1e-6)


def test_huge_density_and_tiny_step_through_render_rays():
    """sigma = 1e8 with step 1e-9 from inside geometry: finite outputs and gradients, float64 closed form."""
    rgb = (0.3, 0.6, 0.2)
    o = torch.tensor([[0.0, 0.0, 0.0], [0.5, 0.2, -0.1]])
    d = torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    for sigma in (1e8, 1e6, 1e3):
        field = BoxField((-0.9, -0.9, -0.9), (0.9, 0.9, 0.9), sigma=sigma, rgb=rgb)
        opts = RenderOptions(step_size=1e-9, max_samples=1000, t_threshold=0.0)
        out = render_rays(field, None, o, d, opts)
        length = 1000 * 1e-9
        expected = -math.expm1(-sigma * length)
        assert torch.allclose(out["opacity"].double(), torch.full((2,), expected, dtype=torch.float64), rtol=1e-4)
        assert torch.allclose(out["rgb"].double(), torch.tensor(rgb, dtype=torch.float64) * expected, rtol=1e-4)
        (out["rgb"].sum() + out["depth"].sum()).backward()
        assert torch.isfinite(field.sigma.grad) and torch.isfinite(field.rgb_logit.grad).all()
        # d opacity / d sigma = L exp(-sigma L), through the field's parameter
        field.zero_grad()
        render_rays(field, None, o[:1], d[:1], RenderOptions(outputs=("opacity",), step_size=1e-9, max_samples=1000,
                                                             t_threshold=0.0))["opacity"].sum().backward()
        # float32 sums of terms of size ~L leave round-off of ~1e-8 * L where the true value underflows
        assert float(field.sigma.grad) == pytest.approx(length * math.exp(-sigma * length), rel=1e-3, abs=1e-8 * length)


def test_opaque_slab_is_finite_with_termination():
    field = BoxField((-1, -1, -0.2), (1, 1, 0.2), sigma=1e8, rgb=(0.9, 0.1, 0.1))
    o, d = torch.tensor([[0.0, 0.0, 3.0]]), torch.tensor([[0.0, 0.0, -1.0]])
    out = render_rays(field, None, o, d, RenderOptions(background=torch.ones(3)))
    assert torch.allclose(out["opacity"], torch.ones(1))
    assert torch.allclose(out["rgb"], torch.tensor([[0.9, 0.1, 0.1]]), atol=1e-4)
    assert abs(float(out["depth"].detach()) - 2.8) < 0.01
    # samples from the cube's face (t = 2) to the slab (t = 2.8), then nothing behind the opaque one
    assert out["stats"]["samples"] <= math.ceil(0.8 / default_step(1.0, 1024)) + 2
    out["rgb"].sum().backward()
    assert torch.isfinite(field.sigma.grad) and torch.isfinite(field.rgb_logit.grad).all()


def _rays(n, seed=0):
    g = torch.Generator().manual_seed(seed)
    o = torch.randn(n, 3, generator=g)
    o = o / o.norm(dim=-1, keepdim=True) * 2.5
    d = (torch.rand(n, 3, generator=g) - 0.5) * 0.8 - o
    return o, d / d.norm(dim=-1, keepdim=True)


class _Recorder(SphereField):
    """A sphere that records which heads it was asked for."""

    def __init__(self, **kw):
        super().__init__(**kw)
        self.asked: list[tuple] = []

    def forward(self, x, d, outputs=("rgb",)):
        self.asked.append(tuple(outputs))
        return super().forward(x, d, outputs)


def test_only_asked_outputs_and_feature_head_not_evaluated():
    field = _Recorder(radius=0.5, sigma=10.0, feature_dim=4)
    o, d = _rays(64)
    with torch.no_grad():
        out = render_rays(field, None, o, d, RenderOptions(outputs=("depth",)))
        assert set(out) == {"depth", "stats"} and field.asked == []  # density only
        out = render_rays(field, None, o, d, RenderOptions(outputs=("rgb",)))
        assert set(out) == {"rgb", "stats"} and all("feature" not in a for a in field.asked)
        out = render_rays(field, None, o, d, RenderOptions(outputs=("feature", "opacity")))
        assert set(out) == {"feature", "opacity", "stats"} and out["feature"].shape == (64, 4)
    with pytest.raises(UserError, match="unknown render output"):
        render_rays(field, None, o, d, RenderOptions(outputs=("normals",)))


def test_gradients_flow_and_training_path_matches_inference():
    field = SphereField(radius=0.5, sigma=10.0, color_slope=1.0, feature_dim=3)
    grid = OccupancyGrid(resolution=32, device="cpu")
    for step in range(0, 64, 16):
        grid.update(step, field.density)
    o, d = _rays(256, seed=1)
    opts = RenderOptions(outputs=("rgb", "depth", "opacity", "feature"), background=torch.rand(256, 3))
    out = render_rays(field, grid, o, d, opts)
    assert out["stats"]["strategy"] == "filter"
    loss = out["rgb"].square().sum() + out["depth"].sum() + out["feature"].sum()
    loss.backward()
    for p in (field.sigma, field.rgb_logit, field.feature):
        assert p.grad is not None and torch.isfinite(p.grad).all() and p.grad.abs().sum() > 0
    with torch.no_grad():
        ref = render_rays(field, grid, o, d, opts)
    assert ref["stats"]["strategy"] == "rounds"
    for k in ("rgb", "depth", "opacity", "feature"):
        assert torch.allclose(out[k].detach(), ref[k], atol=2e-4), k


def test_chunk_budget_does_not_change_the_render():
    """Same render under a small memory budget: exact without termination, within t_threshold with it."""
    field = SphereField(radius=0.5, sigma=10.0, color_slope=1.0)
    o, d = _rays(300, seed=2)
    for thr, tol in ((0.0, 1e-5), (1e-4, 2e-4)):
        with torch.no_grad():
            a = render_rays(field, None, o, d, RenderOptions(t_threshold=thr))
            b = render_rays(field, None, o, d, RenderOptions(t_threshold=thr, chunk=1024))
        assert torch.allclose(a["rgb"], b["rgb"], atol=tol) and torch.allclose(a["opacity"], b["opacity"], atol=tol)
        assert 0 < b["stats"]["peak_samples"] <= 1024 < a["stats"]["peak_samples"]


def test_empty_batch_keeps_the_graph():
    """No sample at all (rays miss): outputs still connect to the field so backward() works."""
    field = SphereField(radius=0.3)
    out = render_rays(field, None, torch.tensor([[0.0, 0.0, 3.0]]), torch.tensor([[1.0, 0.0, 0.0]]))
    assert out["stats"]["samples"] == 0 and out["rgb"].shape == (1, 3) and out["opacity"].shape == (1,)
    assert torch.equal(out["rgb"].detach(), torch.zeros(1, 3)) and float(out["opacity"]) == 0.0  # black, empty
    assert out["rgb"].requires_grad
    out["rgb"].sum().backward()
    params = list(field.parameters())
    assert params and all(p.grad is not None and torch.count_nonzero(p.grad) == 0 for p in params)


def _camera():
    return Cameras.create(look_at((0.0, 0.0, 3.0), (0, 0, 0), up=(0, 1, 0)), 40, 40, 16, 12, 32, 24)


def test_render_camera_shapes_z_depth_and_scale():
    """A plane z = 0.25 facing the camera at z = 3: z-depth 2.75 everywhere, half resolution at scale 0.5."""
    field = BoxField((-1, -1, 0.2), (1, 1, 0.25), sigma=1e5, rgb=(0.5, 0.5, 0.5))
    cams = _camera()
    out = render_camera(field, None, cams, 0, RenderOptions(outputs=("rgb", "depth", "opacity")))
    assert out["rgb"].shape == (24, 32, 3) and out["depth"].shape == (24, 32) and out["opacity"].shape == (24, 32)
    hit = out["opacity"] > 0.5  # the corners look past the plane's edges
    assert hit.float().mean() > 0.9 and (out["opacity"][~hit] == 0).all()
    assert torch.allclose(out["depth"][hit], torch.full((int(hit.sum()),), 2.75), atol=5e-3)
    small = render_camera(field, None, cams, 0, RenderOptions(), scale=0.5)
    assert small["rgb"].shape == (12, 16, 3)
    assert not small["rgb"].requires_grad


def test_render_camera_cancel_returns_none():
    field = SphereField(radius=0.5)
    calls = []
    assert render_camera(field, None, _camera(), 0, RenderOptions(), cancel=lambda: calls.append(1) or True) is None
    assert calls
