"""The native marcher (core/render/csrc/march.c) against the PyTorch segment path it replaces on the CPU."""
from __future__ import annotations

import pytest
import torch

from repaint_nerf.core.field.contraction import CONE, ContractWarp, NDCWarp, contract
from repaint_nerf.core.render import march_native
from repaint_nerf.core.render.analytic import SphereField
from repaint_nerf.core.render.occupancy import OccupancyGrid, default_step
from repaint_nerf.core.render.box import cube
from repaint_nerf.core.render.raymarch import Samples, expand_segments, next_segments, plan_rays
from repaint_nerf.core.render.renderer import RenderOptions, render_camera, render_rays
from repaint_nerf.core.scene.cameras import Cameras, look_at


def _rays(n: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    origins = torch.randn(n, 3, generator=g)
    origins = 2.5 * origins / origins.norm(dim=-1, keepdim=True)
    target = 0.6 * (torch.rand(n, 3, generator=g) * 2 - 1)
    dirs = target - origins
    return origins, dirs / dirs.norm(dim=-1, keepdim=True)


def _grid(resolution: int, cascades: int, seed: int) -> OccupancyGrid:
    """Occupied blobs (so whole coarse blocks are empty) plus scattered single cells."""
    grid = OccupancyGrid(resolution, cascades, bound=0.5 if cascades > 1 else 1.0, device="cpu")
    g = torch.Generator().manual_seed(seed)
    r = resolution
    ijk = torch.stack(torch.meshgrid(*(torch.arange(r),) * 3, indexing="ij"), -1).float()
    occ = torch.zeros(cascades, r, r, r, dtype=torch.bool)
    for c in range(cascades):
        for _ in range(3):
            centre = torch.rand(3, generator=g) * r
            occ[c] |= (ijk - centre).norm(dim=-1) < r * 0.12
        occ[c] |= torch.rand(r, r, r, generator=g) < 0.01
    grid.occupied = occ.reshape(cascades, -1)
    grid._version += 1
    return grid


def _reference(o, d, plan, grid, k: int = 16) -> Samples:
    """Every occupied step of every ray, through the PyTorch segment path."""
    ids = torch.arange(o.shape[0])
    window = int((plan.n_steps.max() + k - 1) // k) + 1
    segs = next_segments(o, d, plan, grid, ids, torch.zeros_like(ids), k, window, window)
    return expand_segments(o, d, plan, grid, *segs, False)


def _native_all(o, d, plan, grid, take: int, perturb: bool = False) -> Samples:
    """All samples through the native marcher, `take` per ray per round, rounds concatenated then sorted by ray."""
    cursor = torch.zeros(o.shape[0], dtype=torch.long)
    parts = []
    while True:
        ids = (cursor < plan.n_steps).nonzero(as_tuple=True)[0]
        if ids.numel() == 0:
            break
        parts.append(march_native.march(o, d, plan, grid, ids, cursor, take, perturb))
    s = Samples(*(torch.cat([getattr(p, f) for p in parts]) for f in ("ray", "t_start", "t_end", "t", "x")))
    return s.select(torch.sort(s.ray, stable=True).indices)


@pytest.mark.parametrize("resolution,cascades", [(32, 1), (64, 1), (16, 2), (30, 1)])
def test_native_march_emits_exactly_the_reference_samples(resolution, cascades):
    o, d = _rays(3000, seed=resolution + cascades)
    grid = _grid(resolution, cascades, seed=7)
    plan = plan_rays(o, d, *cube(grid.extent), default_step(grid.bound, 256), 256 * 2 ** (cascades - 1))
    assert march_native.usable(o, plan, grid), march_native.LIBRARY.failed
    ref = _reference(o, d, plan, grid)
    assert len(ref) > 1000  # the rays cross occupied space
    for take in (1, 3, 1 << 20):  # rounds of any size add up to the same samples
        got = _native_all(o, d, plan, grid, take)
        assert len(got) == len(ref)
        assert torch.equal(got.ray, ref.ray)
        for f in ("t_start", "t_end", "t", "x"):
            torch.testing.assert_close(getattr(got, f), getattr(ref, f), atol=0, rtol=0)


def test_native_march_jitter_stays_in_its_step_and_follows_the_seed():
    o, d = _rays(500, seed=3)
    grid = _grid(32, 1, seed=2)
    plan = plan_rays(o, d, *cube(1.0), default_step(1.0, 128), 128)
    torch.manual_seed(0)
    a = _native_all(o, d, plan, grid, 8, perturb=True)
    torch.manual_seed(0)
    b = _native_all(o, d, plan, grid, 8, perturb=True)
    torch.manual_seed(1)
    c = _native_all(o, d, plan, grid, 8, perturb=True)
    assert len(a) > 100 and torch.equal(a.t, b.t)
    assert ((a.t >= a.t_start) & (a.t <= a.t_end)).all()
    frac = ((a.t - a.t_start) / (a.t_end - a.t_start).clamp_min(1e-12))
    assert 0.4 < float(frac.mean()) < 0.6 and float(frac.std()) > 0.2  # spread over the step, not centred
    ordered = a.ray[1:] != a.ray[:-1]
    assert ((a.t[1:] > a.t[:-1]) | ordered).all()  # sorted by distance within each ray
    assert not torch.equal(a.t[:min(len(a), len(c))], c.t[:min(len(a), len(c))])


def _sphere_scene():
    field = SphereField(radius=0.45, sigma=40.0, rgb=(0.9, 0.3, 0.2))
    grid = OccupancyGrid(32, 1, bound=1.0, device="cpu")
    for step in range(0, 64, 16):
        grid.update(step, field.density)
    cams = Cameras.create(look_at((0.0, -2.2, 0.9), (0.0, 0.0, 0.0)), 40.0, 40.0, 24.0, 24.0, 48, 48)
    return field, grid, cams


def test_renders_match_the_pytorch_path(monkeypatch):
    field, grid, cams = _sphere_scene()
    opts = RenderOptions(outputs=("rgb", "depth", "opacity"), background=torch.ones(3), max_samples=256)
    native = render_camera(field, grid, cams, 0, opts)
    monkeypatch.setattr(march_native, "usable", lambda *a: False)
    plain = render_camera(field, grid, cams, 0, opts)
    assert float(native["opacity"].max()) > 0.99
    for k in ("rgb", "depth", "opacity"):
        torch.testing.assert_close(native[k], plain[k], atol=2e-4, rtol=0)
    assert native["stats"]["samples"] <= plain["stats"]["samples"]


def test_training_pass_matches_the_pytorch_path(monkeypatch):
    field, grid, cams = _sphere_scene()
    o, d, _ = cams[0].image_rays(0)
    o, d = o.reshape(-1, 3), d.reshape(-1, 3)
    opts = RenderOptions(outputs=("rgb",), strategy="filter", max_samples=256)
    native = render_rays(field, grid, o, d, opts)
    monkeypatch.setattr(march_native, "usable", lambda *a: False)
    plain = render_rays(field, grid, o, d, opts)
    torch.testing.assert_close(native["rgb"], plain["rgb"], atol=2e-4, rtol=0)


def test_unknown_warps_and_other_tensors_take_the_pytorch_path():
    field, grid, cams = _sphere_scene()
    o, d = _rays(10, seed=1)
    plan = plan_rays(o, d, *cube(1.0), 0.01, 256)
    assert march_native.usable(o, plan, grid)
    assert not march_native.usable(o, plan, None)
    assert not march_native.usable(o.double(), plan, grid)
    assert march_native.usable(o, plan_rays(o, d, *cube(1.0), 0.01, 256, cone=0.01), grid)
    assert march_native.usable(o, plan, OccupancyGrid(16, 1, warp=ContractWarp(), march_extent=4.0, device="cpu"))
    assert not march_native.usable(o, plan, OccupancyGrid(16, 1, warp=lambda x: x, march_extent=4.0, device="cpu"))


def _warped_grid(warp, resolution: int, seed: int) -> OccupancyGrid:
    grid = OccupancyGrid(resolution, 1, warp=warp, march_extent=16.0, device="cpu")
    grid.occupied = _grid(resolution, 1, seed).occupied
    grid._version += 1
    return grid


@pytest.mark.parametrize("kind", ["contract", "ndc"])
def test_warped_native_march_emits_the_reference_samples(kind):
    """Contracted and NDC grids with cone steps: the kernel's jumps (exact for NDC and the contraction's core, a
    Lipschitz bound past it) skip no occupied step the PyTorch path keeps. Step distances agree to float rounding
    (the kernel takes the cone's powers in double)."""
    o, d = _rays(3000, seed=5)
    if kind == "contract":
        warp = ContractWarp()
        o = 0.35 * o  # cameras inside the unit cube, rays out to the far shells
    else:  # a reference camera at the origin looking down -z; rays start in front of it, looking forward
        warp = NDCWarp(torch.eye(4).numpy(), 1.0, 1.0, 2.0, 2.0, 0.3)
        o = 0.2 * o - torch.tensor([0.0, 0.0, 0.5])
        d = torch.nn.functional.normalize(d * torch.tensor([0.4, 0.4, 1.0]) - torch.tensor([0.0, 0.0, 1.0]), dim=-1)
    grid = _warped_grid(warp, 32, seed=4)
    step = default_step(1.0, 256)
    plan = plan_rays(o, d, *cube(16.0), step, 1024, 0.0, max(CONE, step))
    assert march_native.usable(o, plan, grid), march_native.LIBRARY.failed
    ref = _reference(o, d, plan, grid)
    assert len(ref) > 2000 and int(plan.n_steps.sum()) > 20 * len(ref)  # mostly empty steps to skip
    for take in (1, 5, 1 << 20):
        got = _native_all(o, d, plan, grid, take)
        assert len(got) == len(ref) and torch.equal(got.ray, ref.ray)
        for f in ("t_start", "t_end", "t", "x"):
            torch.testing.assert_close(getattr(got, f), getattr(ref, f), atol=1e-5, rtol=1e-5)


def test_contraction_moves_points_no_faster_than_the_marchers_bound():
    """march.c skips past the contraction's core by |J|_inf <= 2/n - 1.5/n^2 at |x|_inf = n >= 1 (at most 2/3):
    the Jacobian's largest row sum, checked by autograd at random points and near the faces' corners."""
    g = torch.Generator().manual_seed(0)
    dirs = torch.nn.functional.normalize(torch.randn(4000, 3, generator=g), dim=-1)
    n = 1.0 + 30.0 * torch.rand(4000, 1, generator=g) ** 2
    x = dirs / dirs.abs().amax(-1, keepdim=True) * n  # |x|_inf = n
    x[:100, 0], x[:100, 1] = n[:100, 0], -0.999 * n[:100, 0]  # edges: two axes nearly dominant
    jac = torch.func.vmap(torch.func.jacrev(lambda p: contract(p[None], "inf")[0]))(x)
    rows = jac.abs().sum(-1).amax(-1)
    m = x.abs().amax(-1)
    bound = 2.0 / m - 1.5 / m ** 2
    assert bool((rows <= bound + 1e-5).all()) and float(rows.max()) <= 2.0 / 3.0 + 1e-5
    assert float((rows / bound).max()) > 0.95  # the bound is reached: it is not loose


def test_build_failure_falls_back_to_the_pytorch_path(monkeypatch, tmp_path):
    monkeypatch.setattr(march_native.LIBRARY, "lib", None)
    monkeypatch.setattr(march_native.LIBRARY, "failed", None)
    monkeypatch.setenv("REPAINT_NERF_CACHE", str(tmp_path))
    monkeypatch.setenv("CC", "/bin/false")
    field, grid, cams = _sphere_scene()
    opts = RenderOptions(outputs=("rgb",), background=torch.ones(3), max_samples=256)
    with pytest.warns(RuntimeWarning, match="native ray-marching kernel unavailable"):
        out = render_camera(field, grid, cams, 0, opts)
    assert march_native.LIBRARY.failed and float(out["rgb"].min()) < 0.9
    assert not list(tmp_path.rglob("*.so"))
