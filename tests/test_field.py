"""NGPField: asked-for outputs only, no feature gradients unless asked, zero density outside, stable activations."""
from __future__ import annotations

import json

import pytest
import torch

from repaint_nerf.core.errors import UserError
from repaint_nerf.core.field.activations import softplus_density, trunc_exp
from repaint_nerf.core.field.direction import sh_encode
from repaint_nerf.core.field.field import FieldConfig, NGPField, default_field_config

SMALL = dict(levels=4, log2_table=10, base_res=4, finest_res=64, feature_levels=2, feature_log2_table=8,
             feature_finest_res=16, encoding_impl="indexed")


def _field(**kw) -> NGPField:
    torch.manual_seed(0)
    return NGPField(FieldConfig(**{**SMALL, **kw}))


def _xd(n=500, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(n, 3, generator=g) * 2 - 1, torch.randn(n, 3, generator=g)


@pytest.mark.parametrize("fn", [trunc_exp, softplus_density])
def test_density_activation_finite_for_extreme_inputs(fn):
    pre = torch.tensor([-1e4, -100.0, 0.0, 15.0, 100.0, 1e4, 3e38], requires_grad=True)
    out = fn(pre)
    out.sum().backward()
    assert torch.isfinite(out).all() and (out >= 0).all()
    assert torch.isfinite(pre.grad).all()
    assert out[2] > 0 and out[-1] >= out[3]  # monotone, not clipped to zero


def test_trunc_exp_is_exp_in_range():
    x = torch.linspace(-10, 10, 41, dtype=torch.float64, requires_grad=True)
    y = trunc_exp(x)
    y.sum().backward()
    torch.testing.assert_close(y, torch.exp(x))
    torch.testing.assert_close(x.grad, torch.exp(x.detach()))


def test_field_density_finite_for_huge_preactivation():
    f = _field()
    with torch.no_grad():
        f.trunk_out.bias[0] = 1e4
    x, d = _xd(50)
    x.requires_grad_(True)
    sigma = f.density(x)
    sigma.sum().backward()
    assert torch.isfinite(sigma).all() and torch.isfinite(x.grad).all()
    assert all(torch.isfinite(p.grad).all() for p in f.parameters() if p.grad is not None)


def test_outside_points_have_zero_density_and_inside_positive():
    f = _field(bound=1.5)
    outside = torch.tensor([[1.6, 0, 0], [0, -1.51, 0], [0, 0, 9.0], [-3.0, 2.0, 1.0]])
    inside = torch.tensor([[1.5, 1.5, -1.5], [0, 0, 0], [-1.4, 0.3, 1.2]])
    assert (f.density(outside) == 0).all()
    assert (f(outside, torch.ones_like(outside))["sigma"] == 0).all()
    assert (f.density(inside) > 0).all()


def test_density_matches_forward_sigma():
    f = _field(feature_dim=4)
    x, d = _xd()
    torch.testing.assert_close(f.density(x), f(x, d)["sigma"])


def test_only_asked_outputs_and_ranges():
    f = _field(feature_dim=6)
    x, d = _xd()
    assert set(f(x, d, ("rgb",))) == {"sigma", "rgb"}
    assert set(f(x, None, ("sigma",))) == {"sigma"}
    out = f(x, d, ("rgb", "feature"))
    assert set(out) == {"sigma", "rgb", "feature"}
    assert out["sigma"].shape == (500,) and out["rgb"].shape == (500, 3) and out["feature"].shape == (500, 6)
    assert (out["rgb"] >= 0).all() and (out["rgb"] <= 1).all() and (out["sigma"] >= 0).all()
    with pytest.raises(UserError):
        _field()(x, d, ("feature",))  # no feature head
    with pytest.raises(UserError):
        f(x, d, ("normals",))


@pytest.mark.parametrize("head", ["separate", "trunk"])
def test_feature_params_untouched_unless_asked(head):
    f = _field(feature_dim=4, feature_head=head)
    x, d = _xd()
    out = f(x, d, ("rgb",))
    (out["rgb"].sum() + out["sigma"].sum()).backward()
    groups = f.parameter_groups()
    assert groups["feature"] and all(p.grad is None for p in groups["feature"])
    assert all(p.grad is not None for p in groups["grid"] + groups["mlp"])
    f.zero_grad(set_to_none=True)
    f(x, d, ("feature",))["feature"].sum().backward()
    assert all(p.grad is not None for p in groups["feature"])
    if head == "separate":  # DFF's design: the feature loss never moves the geometry
        assert all(p.grad is None for p in groups["grid"] + groups["mlp"])


def test_parameter_groups_partition_parameters():
    for kw in ({}, {"feature_dim": 3}, {"feature_dim": 3, "feature_head": "trunk"}):
        f = _field(**kw)
        grouped = [p for ps in f.parameter_groups().values() for p in ps]
        assert len(grouped) == len({id(p) for p in grouped}) == len(list(f.parameters()))
    assert _field().parameter_groups()["feature"] == []


def test_config_round_trips_through_json():
    cfg = FieldConfig(**SMALL, feature_dim=8)
    back = FieldConfig.from_dict(json.loads(json.dumps(cfg.to_dict())) | {"from_the_future": 1})
    assert back == cfg


def test_sh_encoding_orthonormal():
    # Monte-Carlo check that the 16 real SH functions are orthonormal on the sphere
    d = torch.randn(200_000, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    y = sh_encode(d, 4)
    gram = (y.T @ y) * (4 * torch.pi / d.shape[0])
    torch.testing.assert_close(gram, torch.eye(16, dtype=torch.float64), atol=0.03, rtol=0)
    assert sh_encode(d[:5], 2).shape == (5, 4)
    with pytest.raises(UserError):
        sh_encode(d[:5], 5)


def test_default_config_per_device():
    cpu, cuda = default_field_config("cpu", 128), default_field_config("cuda", 800)
    assert (cuda.levels, cuda.log2_table, cuda.finest_res) == (16, 19, 2048)
    assert cpu.log2_table < cuda.log2_table  # CPU tables stay in cache
    NGPField(FieldConfig(**{**cpu.to_dict(), "encoding_impl": "indexed"}))  # builds


def test_cpu_table_grows_with_the_image_from_256_px():
    """A CPU field keeps the in-cache 2^14 table up to 256-px images and grows it 4x per doubling of the image
    (the finest level's cells on a surface) to 2^16 at ~512 px, never past it; CUDA keeps instant-ngp's 2^19."""
    tables = {px: default_field_config("cpu", px).log2_table for px in (64, 128, 256, 300, 362, 500, 512, 1024, 4096)}
    assert tables == {64: 14, 128: 14, 256: 14, 300: 14, 362: 15, 500: 16, 512: 16, 1024: 16, 4096: 16}
    assert default_field_config("cuda", 512).log2_table == 19
    assert default_field_config("cpu", 512, log2_table=12).log2_table == 12  # an override still wins


@pytest.mark.parametrize("codes", [0, 4])
def test_directions_per_ray_give_the_per_point_colours_and_gradients(codes):
    """The renderer's call (directions and image codes per ray, each point's ray index) computes the colour head's
    view part once per ray: the same colours and gradients as directions repeated per point."""
    field = _field(appearance_dim=codes, appearance_count=3 if codes else 0)
    with torch.no_grad():  # a trained colour head and non-zero codes, so every column of the first layer matters
        for p in field.color_net.parameters():
            p.normal_(0.0, 0.3)
        if field.appearance is not None:
            field.appearance.embedding.weight.normal_()
    ray = torch.randint(0, 7, (200,)).sort().values
    dirs = torch.nn.functional.normalize(torch.randn(7, 3), dim=-1)
    image = torch.randint(0, 3, (7,)) if codes else None
    x = torch.rand(200, 3) * 2 - 1
    per_ray = field(x, dirs, outputs=("rgb",), appearance=image, ray=ray)
    grads_ray = torch.autograd.grad(per_ray["rgb"].square().sum(), list(field.color_net.parameters()))
    per_point = field(x, dirs[ray], outputs=("rgb",), appearance=None if image is None else image[ray])
    grads_point = torch.autograd.grad(per_point["rgb"].square().sum(), list(field.color_net.parameters()))
    torch.testing.assert_close(per_ray["rgb"], per_point["rgb"], atol=1e-6, rtol=1e-5)
    assert float(per_ray["rgb"].std()) > 0.05
    for a, b in zip(grads_ray, grads_point):
        torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-4)


def test_renders_through_directions_per_ray_match_per_point(monkeypatch):
    """The renderer passes each round's rays with samples (and their image codes) once: the same image and
    gradients as the per-point call."""
    from repaint_nerf.core.render.renderer import RenderOptions, render_rays

    field = _field(appearance_dim=4, appearance_count=3)
    with torch.no_grad():
        for p in field.color_net.parameters():
            p.normal_(0.0, 0.3)
        field.appearance.embedding.weight.normal_()
        field.grid.table.normal_(0.0, 1.0)
    g = torch.Generator().manual_seed(1)
    o = torch.tensor([0.0, 0.0, -2.5]).expand(300, 3)
    d = torch.nn.functional.normalize(torch.randn(300, 3, generator=g) * 0.2 + torch.tensor([0.0, 0.0, 1.0]), dim=-1)
    image = torch.randint(0, 3, (300,), generator=g)
    results = []
    for per_ray in (True, False):
        monkeypatch.setattr(NGPField, "view_per_ray", per_ray)
        for strategy in ("rounds", "filter"):
            opts = RenderOptions(outputs=("rgb",), max_samples=128, appearance=image, strategy=strategy, chunk=4096)
            out = render_rays(field, None, o, d, opts)
            grad = torch.autograd.grad(out["rgb"].sum(), field.appearance.embedding.weight)[0] \
                if strategy == "filter" else None
            results.append((out["rgb"].detach(), grad))
    for (a, ga), (b, gb) in zip(results[:2], results[2:]):
        torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-4)
        if ga is not None:
            torch.testing.assert_close(ga, gb, atol=1e-4, rtol=1e-3)
    assert float(results[0][0].std()) > 0.02


@pytest.mark.parametrize("head", ["separate", "trunk"])
def test_first_surface_features_evaluated_on_their_rows_only_are_the_full_heads(monkeypatch, head):
    """With features composited at the first surface, the renderer runs the feature head only on the samples the
    composite reads (`first_surface_samples`): the same images, bit for bit, from fewer feature rows."""
    from repaint_nerf.core.render.renderer import RenderOptions, render_rays

    field = _field(feature_dim=6, feature_head=head, appearance_dim=4, appearance_count=2)
    with torch.no_grad():
        field.grid.table.normal_(0.0, 1.0)
        if field.feature_grid is not None:
            field.feature_grid.table.normal_(0.0, 1.0)
        field.trunk_out.bias[0] = 1.0  # dense enough that rays stop inside the cube
    g = torch.Generator().manual_seed(2)
    o = torch.tensor([0.0, 0.0, -2.5]).expand(200, 3)
    d = torch.nn.functional.normalize(torch.randn(200, 3, generator=g) * 0.3 + torch.tensor([0.0, 0.0, 1.0]), dim=-1)
    rows = []
    field.feature_net[0].register_forward_hook(lambda m, i, out: rows.append(i[0].shape[0]))
    results = []
    for sparse in (True, False):
        monkeypatch.setattr(NGPField, "sparse_features", sparse)
        rows.clear()
        with torch.no_grad():
            out = render_rays(field, None, o, d, RenderOptions(outputs=("rgb", "feature", "depth", "opacity"),
                                                               max_samples=128,
                                                               feature_first_surface=True, chunk=4096,
                                                               appearance=torch.zeros(200, dtype=torch.long)))
        results.append((out, sum(rows)))
    (sparse_out, sparse_rows), (full_out, full_rows) = results
    for k in ("rgb", "feature", "depth", "opacity"):
        assert torch.equal(sparse_out[k], full_out[k]), k
    assert float(full_out["opacity"].mean()) > 0.5 and float(full_out["feature"].abs().mean()) > 0.01
    assert 0 < sparse_rows < 0.8 * full_rows  # samples behind the first surface and of no weight were skipped


@pytest.mark.parametrize("head", ["separate", "trunk"])
@pytest.mark.parametrize("per_ray", [True, False])
def test_inference_by_row_blocks_gives_the_whole_tensor_values(monkeypatch, head, per_ray):
    """Without gradients on a CPU the field runs `INFER_ROWS` points at a time (smaller temporaries):
    sigma, colour and features, all rows or chosen ones, equal the one-call path's, and `density` the same."""
    from repaint_nerf.core.field import field as field_module

    field = _field(feature_dim=6, feature_head=head, appearance_dim=4, appearance_count=3)
    with torch.no_grad():
        for p in field.parameters():
            p.normal_(0.0, 0.3)
    n, rays = 1000, 37
    x = torch.rand(n, 3) * 2.4 - 1.2  # some points outside the cube: zero density there too
    ray = torch.randint(0, rays, (n,)).sort().values
    dirs = torch.nn.functional.normalize(torch.randn(rays, 3), dim=-1)
    image = torch.randint(0, 3, (rays,))
    args = (dirs, image, ray) if per_ray else (dirs[ray], image[ray], None)
    picked = lambda sigma: (sigma > sigma.median()).nonzero(as_tuple=True)[0]  # noqa: E731
    calls = [dict(outputs=("rgb",)), dict(outputs=("rgb", "feature")), dict(outputs=("feature",)),
             dict(outputs=("rgb", "feature"), feature_rows=picked)]
    results = {}
    for rows in (10 ** 6, 128):  # one block, then 8 blocks and a short last one
        monkeypatch.setattr(field_module, "INFER_ROWS", rows)
        with torch.no_grad():
            results[rows] = [field(x, args[0], appearance=args[1], ray=args[2], **kw) for kw in calls] + \
                [{"sigma": field.density(x)}]
    for whole, blocks in zip(results[10 ** 6], results[128]):
        assert whole.keys() == blocks.keys()
        for k in whole:
            torch.testing.assert_close(blocks[k], whole[k], atol=1e-6, rtol=1e-5)
    assert float(results[128][0]["rgb"].std()) > 0.05 and float((results[128][0]["sigma"] == 0).float().mean()) > 0.1
    with_rows = results[128][3]["feature"]
    assert 0 < int((with_rows.abs().sum(1) > 0).sum()) < n  # only the picked rows have features
