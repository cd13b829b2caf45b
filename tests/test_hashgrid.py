"""Hash-grid encoding: the fast paths equal the plain reference (values and gradients), indexing is right."""
from __future__ import annotations

import warnings

import pytest
import torch

from repaint_nerf.core.errors import UserError
from repaint_nerf.core.field import hashgrid_native
from repaint_nerf.core.field.encoding import AutoEncoder, HashGridEncoding, encoder_fn
from repaint_nerf.core.field.hashgrid import GridSpec, dense_index, encode_reference, spatial_hash
from repaint_nerf.core.field.hashgrid_fast import CompiledEncoder, encode_indexed, encode_vectorized
from repaint_nerf.core.field.hashgrid_native import encode_native

# float32 sums in another order: relative 1e-5, absolute 1e-5 of the largest value (input gradients
# scale with the finest resolution, table gradients are sums over thousands of points)
ATOL, RTOL = 1e-5, 1e-5


def _assert_same(got, ref):
    for g, r, name in zip(got, ref, ("output", "input grad", "table grad")):
        torch.testing.assert_close(g, r, atol=ATOL * max(1.0, float(r.abs().max())), rtol=RTOL, msg=name)


def _points(n: int, bound: float, seed: int = 0) -> torch.Tensor:
    """Random points in and beyond the cube, plus the corners, faces and far outside."""
    g = torch.Generator().manual_seed(seed)
    x = (torch.rand(n, 3, generator=g) * 2.6 - 1.3) * bound
    edges = torch.tensor([[1, 1, 1], [-1, -1, -1], [1, -1, 0.25], [0, 0, 1], [-1, 0.5, 0], [5, -7, 0.1], [0, 0, 0]])
    return torch.cat([x, edges * bound]).float()


def _table(spec: GridSpec) -> torch.Tensor:
    # larger than the 1e-4 init so the comparisons are not trivially within tolerance
    return torch.randn(spec.total_rows, spec.features, generator=torch.Generator().manual_seed(1))


def _value_and_grads(fn, x, table, spec):
    x = x.clone().requires_grad_(True)
    table = table.clone().requires_grad_(True)
    out = fn(x, table, spec)
    w = torch.linspace(-1, 1, out.numel()).view_as(out)  # a non-uniform upstream gradient
    gx, gt = torch.autograd.grad((out * w).sum(), (x, table))
    return out.detach(), gx, gt


SPECS = [GridSpec(levels=6, features=2, log2_table=12, base_res=4, finest_res=128, bound=1.0),
         GridSpec(levels=3, features=4, log2_table=9, base_res=2, finest_res=40, bound=2.5)]


@pytest.mark.parametrize("spec", SPECS, ids=["L6F2", "L3F4-bound2.5"])
@pytest.mark.parametrize("fn", [encode_vectorized, encode_indexed, encode_native],
                         ids=["vectorized", "indexed", "native"])
def test_eager_fast_paths_match_reference(spec, fn):
    assert any(spec.dense) and not all(spec.dense)  # both kinds of level are exercised
    x, table = _points(1500, spec.bound), _table(spec)
    ref = _value_and_grads(encode_reference, x, table, spec)
    got = _value_and_grads(fn, x, table, spec)
    _assert_same(got, ref)


def test_compiled_path_matches_reference():
    spec = GridSpec(levels=4, features=2, log2_table=10, base_res=4, finest_res=64)
    x, table = _points(2000, spec.bound, seed=3), _table(spec)
    enc = CompiledEncoder()
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a compile failure would silently fall back: make it visible
        got = _value_and_grads(enc, x, table, spec)
    assert enc.ok and not enc.failed
    ref = _value_and_grads(encode_reference, x, table, spec)
    _assert_same(got, ref)
    # a different point count reuses the dynamic-shape compile and stays correct
    x2 = x[:777]
    torch.testing.assert_close(enc(x2, table, spec), encode_reference(x2, table, spec), atol=ATOL, rtol=RTOL)


def test_compile_failure_falls_back_with_warning(monkeypatch):
    enc = CompiledEncoder()

    def broken(*args):
        raise RuntimeError("no C++ compiler")

    monkeypatch.setattr(enc, "_fn", broken)
    spec = SPECS[0]
    x, table = _points(100, 1.0), _table(spec)
    with pytest.warns(RuntimeWarning, match="compile"):
        out = enc(x, table, spec)
    assert enc.failed
    torch.testing.assert_close(out, encode_reference(x, table, spec), atol=ATOL, rtol=RTOL)


def test_compile_switch_by_env(monkeypatch):
    monkeypatch.setenv("REPAINT_NERF_COMPILE", "0")
    assert encoder_fn("auto").other is encode_indexed
    assert encoder_fn("compiled") is encode_indexed
    monkeypatch.setenv("REPAINT_NERF_COMPILE", "1")
    assert isinstance(encoder_fn("auto").other, CompiledEncoder)
    assert encoder_fn("auto", compile=False).other is encode_indexed


def test_native_kernel_is_built_and_auto_uses_it_on_cpu():
    spec = SPECS[0]
    assert hashgrid_native.native_available(), hashgrid_native.LIBRARY.failed  # CI has a C compiler: the fast path runs
    x, table = _points(3000, spec.bound, seed=5), _table(spec)
    assert hashgrid_native.usable(x, table, spec)
    auto = encoder_fn("auto", compile=False)
    assert isinstance(auto, AutoEncoder)
    _assert_same(_value_and_grads(auto, x, table, spec), _value_and_grads(encode_reference, x, table, spec))
    assert not hashgrid_native.usable(x.double(), table.double(), spec)  # float64 goes to the PyTorch path
    torch.testing.assert_close(auto(x.double(), table.double(), spec), encode_reference(x.double(), table.double(), spec))


def test_native_build_failure_falls_back_with_warning(monkeypatch, tmp_path):
    monkeypatch.setattr(hashgrid_native.LIBRARY, "lib", None)
    monkeypatch.setattr(hashgrid_native.LIBRARY, "failed", None)
    monkeypatch.setenv("REPAINT_NERF_CACHE", str(tmp_path))  # nothing built there yet
    monkeypatch.setenv("CC", "/bin/false")  # a compiler that always fails
    spec = SPECS[0]
    x, table = _points(200, spec.bound), _table(spec)
    with pytest.warns(RuntimeWarning, match="native hash-grid kernel unavailable"):
        out = encode_native(x, table, spec)
    assert hashgrid_native.LIBRARY.failed and not hashgrid_native.native_available()
    torch.testing.assert_close(out, encode_reference(x, table, spec), atol=ATOL, rtol=RTOL)
    assert not list(tmp_path.rglob("*.so"))  # no half-built library left behind


def test_dense_levels_have_no_collisions():
    spec = GridSpec(levels=8, features=2, log2_table=14, base_res=4, finest_res=256)
    dense_levels = [l for l, d in enumerate(spec.dense) if d]
    assert dense_levels and len(dense_levels) < spec.levels
    for l in dense_levels:
        r = spec.resolutions[l]
        assert (r + 1) ** 3 <= spec.table_size
        ax = torch.arange(r + 1)
        verts = torch.stack(torch.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
        rows = dense_index(verts, r)
        assert rows.unique().numel() == verts.shape[0]  # a bijection onto 0..(r+1)^3-1
        assert int(rows.min()) == 0 and int(rows.max()) == (r + 1) ** 3 - 1
    # the finer levels really are hashed and fill the whole table
    assert spec.level_sizes[-1] == spec.table_size and spec.total_rows == sum(spec.level_sizes)


def test_hash_of_known_coordinate():
    # (3, 5, 7): 3*1 ^ 5*2654435761 ^ 7*805459861 = 3 ^ 13272178805 ^ 5638219027 = 9781445989; mod 2^14 = 1381
    assert 3 ^ 13272178805 ^ 5638219027 == 9781445989 and 9781445989 % (1 << 14) == 1381
    assert int(spatial_hash(torch.tensor([3, 5, 7]), 1 << 14)) == 1381
    assert int(spatial_hash(torch.tensor([0, 0, 0]), 1 << 19)) == 0
    # the int32 (wrapping) index math of the fast path gives the same rows as int64 on a hashed level
    spec = GridSpec(levels=1, features=1, log2_table=14, base_res=2048, finest_res=2048)
    assert not spec.dense[0]
    table = torch.arange(spec.total_rows, dtype=torch.float32)[:, None]
    x = torch.tensor([[3.0, 5.0, 7.0]]) / 2048 * 2 - 1  # exactly on vertex (3, 5, 7): weight 1 on that corner
    assert float(encode_reference(x, table, spec)) == pytest.approx(1381, abs=1e-2)
    assert float(encode_vectorized(x, table, spec)) == pytest.approx(1381, abs=1e-2)


def test_resolutions_grow_geometrically_to_finest():
    spec = GridSpec(levels=16, base_res=16, finest_res=2048)
    assert spec.resolutions[0] == 16 and spec.resolutions[-1] == 2048
    assert all(a < b for a, b in zip(spec.resolutions, spec.resolutions[1:]))
    assert spec.growth == pytest.approx(2 ** (7 / 15))


def test_module_init_range_and_empty_input():
    enc = HashGridEncoding(GridSpec(levels=2, log2_table=8, finest_res=32), impl="indexed")
    assert enc.table.abs().max() <= 1e-4 and enc.table.abs().max() > 0
    assert enc(torch.zeros(0, 3)).shape == (0, enc.out_dim)


def test_bad_shapes_are_user_errors():
    with pytest.raises(UserError):
        GridSpec(base_res=64, finest_res=16)
    with pytest.raises(UserError):
        encoder_fn("magic")
