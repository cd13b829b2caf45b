"""Occupancy grid: instant-ngp's update rules, what it marks on an analytic sphere, checkpoints, and that
skipping with it changes a render's PSNR by less than 0.5 dB while evaluating fewer samples."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from repaint_nerf.core.errors import UserError
from repaint_nerf.core.render.analytic import SphereField
from repaint_nerf.core.render.occupancy import OccupancyGrid, default_step
from repaint_nerf.core.render.renderer import RenderOptions, render_camera
from repaint_nerf.core.scene.cameras import Cameras, look_at
from repaint_nerf.core.train.metrics import psnr


def _centres(grid: OccupancyGrid, c: int = 0) -> torch.Tensor:
    r, e = grid.resolution, grid.cascade_extent(c)
    i = torch.arange(r, dtype=torch.float32)
    g = torch.stack(torch.meshgrid(i, i, i, indexing="ij"), -1).reshape(-1, 3)
    return (g + 0.5) * (2 * e / r) - e


def _warm(grid: OccupancyGrid, fn, steps: int = 256) -> None:
    for step in range(steps):
        grid.update(step, fn)


def test_sphere_cells_marked_and_far_cells_not():
    radius = 0.5
    field = SphereField(radius=radius, sigma=20.0)
    grid = OccupancyGrid(resolution=32, device="cpu")
    assert grid.occupied_fraction() == 1.0  # everything is occupied before the first update
    _warm(grid, field.density)
    dist = _centres(grid).norm(dim=-1)
    half_diag = math.sqrt(3) / 32  # half a cell's diagonal
    occ = grid.occupied[0]
    assert occ[dist < radius - half_diag].all()
    assert not occ[dist > radius + half_diag].any()
    sphere_fraction = 4 / 3 * math.pi * radius ** 3 / 8
    assert abs(grid.occupied_fraction() - sphere_fraction) < 0.02
    # threshold rule: min(mean density, 0.01 / min_step)
    assert grid.threshold() == pytest.approx(min(float(grid.density[0].mean()), 0.01 / grid.min_step))


def test_update_cadence_and_sample_counts():
    """Acts every 16 steps; warm-up evaluates every cell, later a quarter uniform + a quarter occupied."""
    calls = []

    def fn(x):
        calls.append(x.shape[0])
        assert (x.abs() <= 1).all()
        return torch.zeros(x.shape[0])

    grid = OccupancyGrid(resolution=16, device="cpu", warmup_steps=32)
    n = 16 ** 3
    grid.update(5, fn)
    assert calls == []
    grid.update(0, fn)
    assert sum(calls) == n
    grid.mark_all()
    calls.clear()
    grid.update(48, fn)
    assert sum(calls) == n // 4 + n // 4


def test_spread_updates_do_the_same_work_in_even_steps():
    """spread=True: the first update is whole, later ones evaluate 1/16 of their cells per step and apply the
    rule on the period's last step; the grid then agrees with an unspread one."""
    calls = []

    def fn(x):
        calls.append(x.shape[0])
        return SphereField(radius=0.5, sigma=20.0).density(x)

    n = 16 ** 3
    grid = OccupancyGrid(resolution=16, device="cpu", warmup_steps=1000, spread=True)
    grid.update(0, fn)
    assert sum(calls) == n and grid.occupied_fraction() < 0.5  # seeded at once
    version = grid._version
    for step in range(1, 17):
        calls.clear()
        grid.update(step, fn)
        assert sum(calls) == n // 16
        assert grid._version == version + (step == 16)
    plain = OccupancyGrid(resolution=16, device="cpu", warmup_steps=1000)
    _warm(plain, fn, 17)
    agree = (grid.occupied == plain.occupied).float().mean()
    assert float(agree) > 0.97


def test_decay_and_threshold():
    """new = max(0.95 * old, sampled): a field that vanishes decays geometrically and cells empty out."""
    grid = OccupancyGrid(resolution=8, device="cpu")
    grid.update(0, lambda x: torch.full((x.shape[0],), 100.0))
    assert torch.allclose(grid.density, torch.full_like(grid.density, 100.0))
    assert grid.occupied.all()  # mean = 100 but the 0.01-optical-thickness cap is lower
    assert grid.threshold() == pytest.approx(0.01 / default_step(1.0, 1024))
    for k in range(1, 4):
        grid.update(16 * k, lambda x: torch.zeros(x.shape[0]))
    assert torch.allclose(grid.density, torch.full_like(grid.density, 100.0 * 0.95 ** 3))
    grid.update(64, lambda x: torch.full((x.shape[0],), float("nan")))  # non-finite density counts as empty
    assert torch.isfinite(grid.density).all()


def test_cascades_cover_doubling_cubes():
    field = SphereField(center=(1.5, 0.0, 0.0), radius=0.3, sigma=20.0, bound=4.0)
    grid = OccupancyGrid(resolution=16, cascades=2, bound=1.0, device="cpu")
    assert grid.extent == 2.0
    _warm(grid, field.density, 64)
    assert not grid.occupied[0].any()  # the inner cube [-1, 1] holds nothing
    assert grid.occupied[1].any()
    assert bool(grid.is_occupied(torch.tensor([[1.5, 0.0, 0.0]]))[0])
    assert not bool(grid.is_occupied(torch.tensor([[-1.5, 0.0, 0.0], [0.0, 0.0, 0.0]])).any())


def test_reopen_opens_the_cells_a_ray_crosses_for_one_update():
    """Cells a pruned thin structure sat in come back for one update period: exactly the cells along the
    queued ray (up to t_end), unchanged density, pruned again by the following update if still empty."""
    grid = OccupancyGrid(resolution=16, device="cpu", warmup_steps=0)
    empty = lambda x: torch.zeros(x.shape[0])  # noqa: E731
    grid.update(0, empty)
    assert not grid.occupied.any()
    # along +x through cell centres (y, z in cell 8), from outside the cube; stops at x = 0.3
    origin, direction = torch.tensor([[-3.0, 0.0625, 0.0625]]), torch.tensor([[1.0, 0.0, 0.0]])
    assert grid.reopen(origin, direction, torch.tensor([3.3])) == 11  # x cells 0..10 (x < 0.375)
    assert not grid.occupied.any()  # queued, not yet applied: the marcher's view changes only at updates
    grid.update(16, empty)
    occ = grid.occupied[0].view(16, 16, 16)
    assert occ[:11, 8, 8].all() and int(occ.sum()) == 11
    assert float(grid.density.abs().max()) == 0.0
    grid.update(32, empty)
    assert not grid.occupied.any()
    # a ray missing the cube queues nothing; a whole ray (t_end = inf) crosses all 16 cells
    assert grid.reopen(torch.tensor([[-3.0, 5.0, 0.0]]), direction) == 0
    assert grid.reopen(origin, direction, torch.tensor([math.inf])) == 16


def test_state_dict_round_trip_and_mismatch():
    field = SphereField(radius=0.4, sigma=20.0)
    grid = OccupancyGrid(resolution=16, device="cpu")
    _warm(grid, field.density, 32)
    other = OccupancyGrid(resolution=16, device="cpu")
    other.load_state_dict(grid.state_dict())
    assert torch.equal(other.occupied, grid.occupied) and torch.equal(other.density, grid.density)
    assert other.threshold() == grid.threshold()
    with pytest.raises(UserError, match="resolution"):
        OccupancyGrid(resolution=8, device="cpu").load_state_dict(grid.state_dict())


def test_skipping_changes_psnr_by_less_than_half_a_db():
    """A 'converged' field (a sphere slightly off the true one) rendered against ground-truth images with
    and without the grid: PSNR changes < 0.5 dB while far fewer samples are evaluated."""
    truth = SphereField(center=(0.02, 0.0, 0.0), radius=0.52, sigma=10.0, color_slope=2.2)
    model = SphereField(radius=0.5, sigma=8.0, color_slope=2.0)
    grid = OccupancyGrid(resolution=32, device="cpu")
    _warm(grid, model.density)
    cams = Cameras.create([look_at((0.3, -2.5, 0.8), (0, 0, 0)), look_at((2.2, 1.0, -1.0), (0, 0, 0))],
                          50, 50, 24, 24, 48, 48)
    opts = RenderOptions(background=torch.ones(3))
    for i in range(2):
        gt = render_camera(truth, None, cams, i, RenderOptions(background=torch.ones(3), max_samples=2048))["rgb"]
        skip = render_camera(model, grid, cams, i, opts)
        full = render_camera(model, None, cams, i, opts)
        assert abs(psnr(skip["rgb"], gt) - psnr(full["rgb"], gt)) < 0.5
        assert skip["stats"]["samples"] < 0.2 * full["stats"]["samples"]


@pytest.mark.parametrize("resolution,cascade", [(16, 0), (128, 1), (256, 0)])
def test_cell_index_matches_a_plain_floor_and_flatten(resolution, cascade):
    """The float-matmul cell index equals floor-then-flatten in integers for points inside, on the edges of and
    outside the cascade, and gives a NaN point a cell inside the grid."""
    grid = OccupancyGrid(resolution=resolution, cascades=2, bound=0.5, device="cpu")
    e, r = grid.cascade_extent(cascade), resolution
    g = torch.Generator().manual_seed(resolution)
    inside = (torch.rand(20000, 3, generator=g) * 2 - 1) * e
    faces = torch.tensor([[-e, -e, -e], [e, e, e], [e - 1e-7, 0.0, -e], [0.0, e * (1 - 1e-6), e]])
    outside = torch.tensor([[3 * e, -5 * e, 0.0], [float("inf"), float("-inf"), 0.1]])
    x = torch.cat([inside, faces, outside])
    ijk = torch.floor((x.double() + e) * (r / (2 * e))).clamp(0, r - 1).long()
    want = (ijk[:, 0] * r + ijk[:, 1]) * r + ijk[:, 2]
    got = grid._cell_index(x, cascade)
    assert got.dtype == torch.long
    # a point within float32 rounding of a cell face may land on either side of it; nowhere else may they differ
    differ = got != want
    assert int(differ[:20000].sum()) <= 2 and not bool(differ[20000:].any())
    nan = int(grid._cell_index(torch.tensor([[float("nan"), 0.0, 0.0]]), cascade)[0])
    assert 0 <= nan < r ** 3  # a valid cell, never an index past the grid


def _arc_cameras() -> Cameras:
    """Three narrow cameras on one side of the cube, looking at its centre: much of the cube is out of view."""
    eyes = [(0.0, 0.0, 3.0), (1.0, 0.0, 2.8), (-1.0, 0.3, 2.8)]
    c2w = np.stack([look_at(e, (0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0)) for e in eyes])
    return Cameras.create(c2w, 120.0, 120.0, 16.0, 12.0, 32, 24)


def _seen_by_dense_points(grid: OccupancyGrid, cams: Cameras, per_axis: int = 4) -> torch.Tensor:
    """Reference visibility: a cell is seen when any of per_axis^3 points spread through it (faces included)
    projects inside an image in front of its camera."""
    r, e = grid.resolution, grid.cascade_extent(0)
    i = torch.arange(r, dtype=torch.float32)
    cell = torch.stack(torch.meshgrid(i, i, i, indexing="ij"), -1).reshape(-1, 1, 3)
    f = torch.linspace(0.0, 1.0, per_axis)
    off = torch.stack(torch.meshgrid(f, f, f, indexing="ij"), -1).reshape(1, -1, 3)
    y = ((cell + off) * (2 * e / r) - e).reshape(-1, 3)
    x = grid.warp.inverse(y) if grid.warp is not None else y
    uv, z = cams.project_views(x, torch.arange(len(cams)))
    inside = (z > 0) & (uv[..., 0] >= 0) & (uv[..., 0] <= cams.width[:, None]) & (uv[..., 1] >= 0) \
        & (uv[..., 1] <= cams.height[:, None])
    return inside.any(0).view(r ** 3, -1).any(1)


@pytest.mark.parametrize("warp", [None, "contract"])
def test_cells_no_camera_sees_are_never_occupied_nor_evaluated(warp):
    """restrict_to_views keeps every cell a camera sees (against dense points through each cell), drops cells
    more than two cells from any seen one, and updates then evaluate and occupy only the kept cells."""
    from repaint_nerf.core.field.contraction import ContractWarp

    grid = OccupancyGrid(resolution=16, device="cpu", warmup_steps=32,
                         warp=ContractWarp() if warp else None, march_extent=16.0 if warp else None)
    cams = _arc_cameras()
    fraction = grid.restrict_to_views(cams)
    seen = grid.visible[0]
    assert 0.05 < fraction < 0.9 and fraction == pytest.approx(float(seen.float().mean()))
    ref = _seen_by_dense_points(grid, cams)
    assert bool(seen[ref].all())  # conservative: nothing seen is dropped
    near = torch.nn.functional.max_pool3d(ref.view(1, 1, 16, 16, 16).float(), 5, stride=1, padding=2)
    assert not bool((seen & (near.reshape(-1) == 0)).any())  # and tight to within two cells
    assert torch.equal(grid.occupied[0], seen)

    points = []

    def fog(x):
        points.append(x)
        return torch.full((x.shape[0],), 50.0)

    grid.update(0, fog)
    x = torch.cat(points)
    assert x.shape[0] == int(seen.sum())
    assert bool(grid.visible[0, grid._cell_index(grid.to_grid(x), 0)].all())
    assert torch.equal(grid.occupied[0], seen)  # fog everywhere, yet only where a camera looks
    assert grid.threshold() == pytest.approx(min(float(grid.density[0][seen].mean()), 0.01 / grid.min_step))
    points.clear()
    grid.update(48, fog)  # past warm-up: a quarter of the seen cells, and a quarter of all cells' count of occupied
    m = int(seen.sum())
    assert sum(p.shape[0] for p in points) == m // 4 + 16 ** 3 // 4
    grid.mark_occupied(torch.tensor([[0.0, 0.0, -0.95]]))  # behind the object, out of every view
    assert torch.equal(grid.occupied[0], seen)


def test_visibility_survives_a_checkpoint_and_older_states_keep_the_grids_own():
    field = SphereField(radius=0.4, sigma=20.0)
    grid = OccupancyGrid(resolution=16, device="cpu")
    grid.restrict_to_views(_arc_cameras())
    _warm(grid, field.density, 32)
    other = OccupancyGrid(resolution=16, device="cpu")
    other.load_state_dict(grid.state_dict())
    assert torch.equal(other.visible, grid.visible) and torch.equal(other.occupied, grid.occupied)
    older = {k: v for k, v in grid.state_dict().items() if k != "visible"}
    older["occupied"] = torch.ones_like(grid.occupied)
    mine = OccupancyGrid(resolution=16, device="cpu")
    mine.restrict_to_views(_arc_cameras())
    mine.load_state_dict(older)
    assert torch.equal(mine.occupied, grid.visible)  # the state's cells, less those this grid never sees
    damaged = {**grid.state_dict(), "visible": torch.ones(1, 8 ** 3, dtype=torch.bool)}
    with pytest.raises(UserError, match="'visible' has shape"):
        OccupancyGrid(resolution=16, device="cpu").load_state_dict(damaged)


def test_a_longer_step_marches_proportionally_fewer_samples_for_a_close_picture():
    """step_stride (a moving view's preview) multiplies the step: twice the stride, about half the samples in the
    occupied cells, and the sphere's picture within 30 dB of the normal step's; a stride under 1 is refused."""
    field = SphereField(radius=0.5, sigma=8.0, color_slope=2.0)
    grid = OccupancyGrid(resolution=32, device="cpu")
    _warm(grid, field.density)
    cams = Cameras.create(look_at((0.3, -2.5, 0.8), (0, 0, 0)), 50, 50, 24, 24, 48, 48)
    base = render_camera(field, grid, cams, 0, RenderOptions(background=torch.ones(3), max_samples=512))
    long = render_camera(field, grid, cams, 0, RenderOptions(background=torch.ones(3), max_samples=512,
                                                             step_stride=2.0))
    assert 0.4 < long["stats"]["samples"] / base["stats"]["samples"] < 0.6
    assert psnr(long["rgb"], base["rgb"]) > 30.0
    with pytest.raises(UserError, match="step_stride"):
        render_camera(field, grid, cams, 0, RenderOptions(step_stride=0.5))
