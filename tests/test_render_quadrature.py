"""The renderer against the volume-rendering integral (paper: C(r) = int T sigma c dt, T = exp(-int sigma)).

References are closed forms (uniform slab, ball of constant colour) or a brute-force float64 quadrature
with 60k steps per ray. Tolerances: where the density is smooth or its edges coincide with the
marching interval ends, 2e-3; at density discontinuities the marcher may misplace an edge by half a
step on each side, so |error| <= sigma * step (stated per test).
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from repaint_nerf.core.render.analytic import BoxField, GaussianField, SphereField
from repaint_nerf.core.render.occupancy import OccupancyGrid, default_step
from repaint_nerf.core.render.renderer import RenderOptions, render_rays

STEP = default_step(1.0, 1024)


def _rays(n: int, seed: int = 0, dist: float = 3.0, spread: float = 0.6):
    """Rays from a sphere of radius `dist` aimed at random points near the centre (unit directions)."""
    g = torch.Generator().manual_seed(seed)
    o = torch.randn(n, 3, generator=g, dtype=torch.float64)
    o = o / o.norm(dim=-1, keepdim=True) * dist
    target = (torch.rand(n, 3, generator=g, dtype=torch.float64) * 2 - 1) * spread
    d = target - o
    return o, d / d.norm(dim=-1, keepdim=True)


def _quadrature(density, color, o: np.ndarray, d: np.ndarray, n: int = 60_000, t_max: float = 6.0):
    """Brute-force float64 left Riemann sum of the volume-rendering integral along each ray."""
    rgb, opac, depth = [], [], []
    dt = t_max / n
    t = (np.arange(n) + 0.5) * dt
    for oi, di in zip(o, d):
        x = oi[None] + t[:, None] * di[None]
        sig = density(x)
        tau = sig * dt
        trans = np.exp(-(np.cumsum(tau) - tau))
        w = trans * -np.expm1(-tau)
        rgb.append((w[:, None] * color(x)).sum(0))
        opac.append(w.sum())
        depth.append((w * t).sum() / max(w.sum(), 1e-12))
    return np.array(rgb), np.array(opac), np.array(depth)


def _sigmoid(x):
    return 1.0 / (1.0 + np.exp(-x))


def test_uniform_cube_matches_closed_form():
    """Density sigma everywhere in the cube: opacity = 1 - exp(-sigma L) with L the chord through the cube."""
    sigma, rgb = 2.5, (0.2, 0.6, 0.9)
    field = BoxField((-1, -1, -1), (1, 1, 1), sigma=sigma, rgb=rgb)
    o, d = _rays(256, seed=1, spread=0.9)
    with torch.no_grad():
        out = render_rays(field, None, o.float(), d.float(), RenderOptions(t_threshold=0.0))
    inv = 1.0 / d
    t0, t1 = (-1 - o) * inv, (1 - o) * inv
    tn = torch.minimum(t0, t1).amax(-1).clamp_min(0)
    tf = torch.maximum(t0, t1).amin(-1)
    length = (tf - tn).clamp_min(0)
    expected = 1 - torch.exp(-sigma * length)
    assert torch.allclose(out["opacity"].double(), expected, atol=1e-5)
    assert torch.allclose(out["rgb"].double(), expected[:, None] * torch.tensor(rgb, dtype=torch.float64), atol=1e-4)
    # expected termination distance for constant density on [tn, tf]
    hit = length > 0.05
    mean_t = tn + 1 / sigma - length * torch.exp(-sigma * length) / (1 - torch.exp(-sigma * length))
    assert torch.allclose(out["depth"].double()[hit], mean_t[hit], atol=STEP)


def test_axis_slab_closed_form_and_quadrature():
    """A slab z in [-0.3, 0.2]: closed form along the axis, tolerance sigma * step for the two edges."""
    sigma = 4.0
    field = BoxField((-1, -1, -0.3), (1, 1, 0.2), sigma=sigma, rgb=(0.9, 0.5, 0.1))
    o = torch.tensor([[0.1, 0.2, -3.0], [-0.4, 0.3, 2.5]])
    d = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]])
    with torch.no_grad():
        out = render_rays(field, None, o, d, RenderOptions(outputs=("opacity",)))
    expected = 1 - math.exp(-sigma * 0.5)
    assert torch.allclose(out["opacity"], torch.full((2,), expected), atol=sigma * STEP)


@pytest.mark.parametrize("kind", ["sphere", "gaussian"])
def test_matches_brute_force_quadrature(kind):
    """Ball (sigma 6, edges: tolerance sigma*step) and Gaussian blob (smooth: 2e-3) with position-dependent colour."""
    slope = 1.5
    if kind == "sphere":
        sigma, c, r = 6.0, np.array([0.1, -0.1, 0.05]), 0.55
        field = SphereField(center=tuple(c), radius=r, sigma=sigma, rgb=(0.7, 0.4, 0.2), color_slope=slope)
        density = lambda x: sigma * (np.linalg.norm(x - c, axis=-1) <= r) * (np.abs(x).max(-1) <= 1)  # noqa: E731
        tol = sigma * STEP
    else:
        sigma, c, s = 20.0, np.array([0.0, 0.1, -0.1]), 0.25
        field = GaussianField(center=tuple(c), scale=s, sigma=sigma, rgb=(0.7, 0.4, 0.2), color_slope=slope)
        density = lambda x: sigma * np.exp(-((x - c) ** 2).sum(-1) / (2 * s * s))  # noqa: E731
        tol = 2e-3
    logit = field.rgb_logit.detach().double().numpy()
    color = lambda x: _sigmoid(logit[None] + slope * x)  # noqa: E731
    o, d = _rays(16, seed=2)
    ref_rgb, ref_op, ref_depth = _quadrature(density, color, o.numpy(), d.numpy())
    with torch.no_grad():
        out = render_rays(field, None, o.float(), d.float(), RenderOptions(t_threshold=0.0))
    assert np.abs(out["opacity"].double().numpy() - ref_op).max() < tol
    assert np.abs(out["rgb"].double().numpy() - ref_rgb).max() < tol
    hit = ref_op > 0.1
    assert np.abs(out["depth"].double().numpy() - ref_depth)[hit].max() < max(tol, STEP)


def test_miss_and_empty_rays_return_background():
    """A ray that misses the cube, and rays through empty space, give the background and zero opacity."""
    field = SphereField(radius=0.3, sigma=10.0)
    o = torch.tensor([[0.0, 0.0, 3.0], [0.0, 0.0, 3.0], [0.9, 0.9, 3.0]])
    d = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 0.0, -1.0]])  # miss, hit, empty
    bg = torch.tensor([0.25, 0.5, 0.75])
    for grid in (None, OccupancyGrid(resolution=32, device="cpu")):
        with torch.no_grad():
            out = render_rays(field, grid, o, d, RenderOptions(background=bg))
        assert out["opacity"][0] == 0 and out["opacity"][2] == 0
        assert torch.equal(out["rgb"][0], bg) and torch.equal(out["rgb"][2], bg)
        assert out["depth"][0] == 0 and torch.isfinite(out["depth"]).all()
        assert out["opacity"][1] > 0.99
    empty = BoxField((2, 2, 2), (3, 3, 3), sigma=5.0)
    with torch.no_grad():
        out = render_rays(empty, None, *_rays(64), RenderOptions(background=bg))
    assert torch.equal(out["opacity"], torch.zeros(64)) and torch.allclose(out["rgb"], bg.expand(64, 3))


def test_rays_starting_inside_geometry():
    """Origins inside a ball: opacity = 1 - exp(-sigma * (r - |o|)) along radial rays (edge tol sigma*step)."""
    sigma, r = 3.0, 0.6
    field = SphereField(radius=r, sigma=sigma)
    o = torch.tensor([[0.0, 0.0, 0.0], [0.2, 0.0, 0.0]])
    d = torch.tensor([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
    expected = 1 - torch.exp(-sigma * torch.tensor([r, r - 0.2]))
    for grid in (None, OccupancyGrid(resolution=32, device="cpu")):
        with torch.no_grad():
            out = render_rays(field, grid, o, d, RenderOptions(outputs=("opacity",)))
        assert torch.allclose(out["opacity"], expected, atol=sigma * STEP)


class _HazeBeforeWall(BoxField):
    """A thin haze (a fifth of the density) on z in [-0.6, -0.4] in front of a wall on z in [0, 0.5]."""

    def shape(self, x: torch.Tensor) -> torch.Tensor:
        z = x[:, 2]
        return torch.where((z >= 0.0) & (z <= 0.5), 1.0, torch.where((z >= -0.6) & (z <= -0.4), 0.1, 0.0)).to(x.dtype)


@pytest.mark.parametrize("strategy", ["rounds", "filter"])
def test_median_depth_is_where_transmittance_falls_through_half(strategy):
    """Uniform cube: T = exp(-sigma (t - tn)) falls through 0.5 at tn + ln 2 / sigma (closed form) on rays that get
    that opaque, and the median is the expected depth on the others. A haze in front of a wall: the median lies on
    the wall, which the expected depth blends with the haze."""
    sigma = 0.6
    field = BoxField((-1, -1, -1), (1, 1, 1), sigma=sigma)
    o, d = _rays(256, seed=2, spread=1.5)
    opts = RenderOptions(outputs=("depth", "median_depth", "opacity"), t_threshold=0.0, strategy=strategy)
    with torch.no_grad():
        out = render_rays(field, None, o.float(), d.float(), opts)
    inv = 1.0 / d
    t0, t1 = (-1 - o) * inv, (1 - o) * inv
    tn = torch.minimum(t0, t1).amax(-1).clamp_min(0)
    length = (torch.maximum(t0, t1).amin(-1) - tn).clamp_min(0)
    opaque = sigma * length > math.log(2.0) + 0.05
    thin = (length > 0.01) & (sigma * length < math.log(2.0) - 0.05)
    assert opaque.sum() > 50 and thin.sum() > 5
    med = out["median_depth"].double()
    assert torch.allclose(med[opaque], (tn + math.log(2.0) / sigma)[opaque], atol=STEP)
    assert torch.equal(out["median_depth"][thin], out["depth"][thin])

    haze = _HazeBeforeWall((-1, -1, -1), (1, 1, 1), sigma=20.0)
    o2, d2 = torch.tensor([[0.1, -0.2, -3.0]]), torch.tensor([[0.0, 0.0, 1.0]])
    with torch.no_grad():
        out2 = render_rays(haze, None, o2, d2, opts)
    t_haze = math.exp(-20.0 * 0.1 * 0.2)  # T behind the haze: 0.67
    wall = 3.0 + math.log(t_haze / 0.5) / 20.0
    assert abs(float(out2["median_depth"][0]) - wall) < 2 * STEP
    assert float(out2["depth"][0]) < wall - 0.1  # the expected depth is pulled towards the haze
