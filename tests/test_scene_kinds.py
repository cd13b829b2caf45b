"""Scene-kind detection on the presets' camera layouts, and the bounded parametrisations (contraction, NDC)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from core.field.contraction import NDCWarp, WarpedField, contract, mean_pose, uncontract
from core.scene.kinds import choose_kind, kind_from_layout
from core.synth.presets import build_spec
from core.synth.raster import world_bbox


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


@pytest.mark.parametrize("preset,far,expected", [("demo", 5.5, "bounded"), ("room360", 7.5, "unbounded")])
def test_without_points_the_far_depth_decides(preset, far, expected):
    _, c2w, _ = _layout(preset)
    assert kind_from_layout(c2w, None, far)[0] == expected


def test_override_and_bad_override():
    from core.errors import UserError

    class S:  # the attributes choose_kind reads
        kind, extra, points = "bounded", {}, None

    _, c2w, _ = _layout("forward")
    from core.scene.cameras import Cameras
    from core.scene.scene import SceneSplit

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


def test_warped_field_evaluates_the_inner_field_at_warped_points():
    class Toy(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.w = torch.nn.Parameter(torch.ones(3))

        def density(self, x):
            return (x * self.w).sum(-1)

        def forward(self, x, d, outputs=("rgb",)):
            return {"sigma": self.density(x), "rgb": x.abs()}

        def parameter_groups(self):
            return {"grid": [self.w]}

    toy = Toy()
    f = WarpedField(toy, contract, bound=16.0)
    x = torch.tensor([[0.5, 0.0, 0.0], [4.0, 0.0, 0.0]])
    assert torch.allclose(f.density(x), torch.tensor([0.25, 0.5 * (2 - 0.25)]))
    out = f(x, torch.zeros_like(x), outputs=("rgb",))
    assert torch.allclose(out["rgb"], contract(x).abs()) and f.bound == 16.0
    assert f.parameter_groups()["grid"][0] is toy.w
    f.density(x).sum().backward()
    assert toy.w.grad is not None


@pytest.mark.slow  # importing the real field can compile its grid (minutes on a busy CPU)
def test_warped_ngp_field_sees_far_points_inside_its_cube():
    field_mod = pytest.importorskip("core.field.field")
    torch.manual_seed(0)
    inner = field_mod.NGPField(field_mod.FieldConfig(levels=2, log2_table=10, base_res=4, finest_res=8, hidden=16))
    far = torch.tensor([[10.0, 3.0, -2.0], [100.0, 0.0, 0.0]])
    assert torch.all(inner.density(far) == 0)  # outside the plain field's cube
    warped = WarpedField(inner, contract, bound=16.0)
    assert warped.cfg.bound == 16.0 and inner.cfg.bound == 1.0
    assert torch.allclose(warped.density(far), inner.density(contract(far)))
    assert torch.all(warped.density(far) > 0)
    out = warped(far, torch.nn.functional.normalize(far, dim=-1), outputs=("rgb",))
    assert out["rgb"].shape == (2, 3) and torch.isfinite(out["rgb"]).all()
