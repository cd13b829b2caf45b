"""Fast paths of the hash encoding, all equal to `encode_reference` (tests check forward and backward).

- `encode_vectorized`: all levels and corners in one gather with int32 index math (plain autograd);
  the function torch.compile fuses (on CUDA, inductor turns it into Triton kernels).
- `encode_indexed`: the same forward under no_grad plus a hand-written backward that index_add_s into
  the flat table, so eager mode keeps no (N, L, 8, F) autograd intermediates.
- `compiled_encoder()`: torch.compile of `encode_vectorized`, switchable by $REPAINT_NERF_COMPILE=0 and
  falling back to eager with a warning when compilation fails (no C compiler on a user machine).
"""
from __future__ import annotations

import os
import warnings

import torch

from repaint_nerf.core.field.hashgrid import PRIMES, GridSpec

ENV_COMPILE = "REPAINT_NERF_COMPILE"


def _as_int32(v: int) -> int:
    """A uint32 constant as the int32 with the same bits: int32 products wrap mod 2^32, keeping the low bits exact."""
    return v - (1 << 32) if v >= (1 << 31) else v


_P1, _P2 = _as_int32(PRIMES[1]), _as_int32(PRIMES[2])
# corner c has offset bit a = (c >> a) & 1, the same order as the reference
_CORNERS = [[(c >> a) & 1 for a in range(3)] for c in range(8)]


class GridBuffers:
    """Per-level constants of a GridSpec as small tensors on one device (cached per spec and device)."""

    _cache: dict = {}

    def __init__(self, spec: GridSpec, device: torch.device):
        res = torch.tensor(spec.resolutions, dtype=torch.int32, device=device)
        self.res_f = res.float()  # (L,)
        self.res_max = res - 1
        self.stride_y = res + 1
        self.stride_z = (res + 1) * (res + 1)
        self.dense = torch.tensor(spec.dense, device=device)
        self.offsets = torch.tensor(spec.offsets, dtype=torch.int32, device=device)
        self.corners = torch.tensor(_CORNERS, dtype=torch.int32, device=device)  # (8, 3)
        self.hash_mask = spec.table_size - 1

    @classmethod
    def get(cls, spec: GridSpec, device: torch.device) -> "GridBuffers":
        key = (spec, str(device))
        if key not in cls._cache:
            cls._cache[key] = cls(spec, device)
        return cls._cache[key]


def corner_rows_weights(x: torch.Tensor, spec: GridSpec, buf: GridBuffers) -> tuple[torch.Tensor, torch.Tensor]:
    """Flat-table rows (N, L, 8) int32 and trilinear weights (N, L, 8) of every corner of every level."""
    u = ((x + spec.bound) / (2.0 * spec.bound)).clamp(0.0, 1.0).nan_to_num(0.0)  # as hashgrid.to_unit_cube
    pos = u[:, None, :] * buf.res_f[None, :, None]  # (N, L, 3)
    cell = torch.minimum(pos.floor().to(torch.int32), buf.res_max[None, :, None])
    frac = pos - cell.float()
    vert = cell[:, :, None, :] + buf.corners[None, None]  # (N, L, 8, 3)
    vx, vy, vz = vert.unbind(-1)
    dense_row = vx + vy * buf.stride_y[None, :, None] + vz * buf.stride_z[None, :, None]
    hash_row = (vx ^ (vy * _P1) ^ (vz * _P2)) & buf.hash_mask
    rows = torch.where(buf.dense[None, :, None], dense_row, hash_row) + buf.offsets[None, :, None]
    cf = buf.corners.bool()[None, None]  # (1, 1, 8, 3)
    f = frac[:, :, None, :]
    w = torch.where(cf, f, 1.0 - f).prod(-1)  # (N, L, 8)
    return rows, w


def encode_vectorized(x: torch.Tensor, table: torch.Tensor, spec: GridSpec) -> torch.Tensor:
    """All levels in one gather: (N, 3) field coords -> (N, L*F). Differentiable by plain autograd."""
    buf = GridBuffers.get(spec, x.device)
    rows, w = corner_rows_weights(x, spec, buf)
    n = x.shape[0]
    vals = table[rows.reshape(-1)].view(n, spec.levels, 8, spec.features)
    return (vals * w[..., None].to(table.dtype)).sum(2).reshape(n, spec.out_dim)


class _IndexedEncode(torch.autograd.Function):
    """Forward without autograd intermediates; backward scatters into the flat table with index_add_."""

    @staticmethod
    def forward(ctx, x, table, spec):
        buf = GridBuffers.get(spec, x.device)
        with torch.no_grad():
            rows, w = corner_rows_weights(x, spec, buf)
            n = x.shape[0]
            rows = rows.reshape(n, -1)
            vals = table.index_select(0, rows.reshape(-1)).view(n, spec.levels, 8, spec.features)
            out = (vals * w[..., None]).sum(2).reshape(n, spec.out_dim)
        ctx.save_for_backward(x, table, rows, w)
        ctx.spec = spec
        return out

    @staticmethod
    def backward(ctx, grad_out):
        x, table, rows, w = ctx.saved_tensors
        spec = ctx.spec
        grad_x = grad_table = None
        g = grad_out.reshape(-1, spec.levels, 1, spec.features)
        if ctx.needs_input_grad[1]:
            contrib = (g * w[..., None]).reshape(-1, spec.features)
            grad_table = torch.zeros_like(table).index_add_(0, rows.reshape(-1), contrib.to(table.dtype))
        if ctx.needs_input_grad[0]:
            # input gradients are rare (no NeRF step needs them): recompute through plain autograd
            with torch.enable_grad():
                xd = x.detach().requires_grad_(True)
                out = encode_vectorized(xd, table.detach(), spec)
                (grad_x,) = torch.autograd.grad(out, xd, grad_out)
        return grad_x, grad_table, None


def encode_indexed(x: torch.Tensor, table: torch.Tensor, spec: GridSpec) -> torch.Tensor:
    """Vectorised forward with an index_add_ backward: (N, 3) -> (N, L*F)."""
    return _IndexedEncode.apply(x, table, spec)


def compile_enabled(flag: bool = True) -> bool:
    """Compilation is on when the config flag is set and $REPAINT_NERF_COMPILE is not 0/false/off."""
    env = os.environ.get(ENV_COMPILE, "1").strip().lower()
    return flag and env not in ("0", "false", "off", "no")


class CompiledEncoder:
    """torch.compile of `encode_vectorized` (dynamic point count); eager `fallback` with a warning if compiling fails."""

    def __init__(self, fallback=encode_indexed):
        self.fallback = fallback
        self.failed = False
        self.ok = False
        import torch._dynamo

        # each grid shape and grad mode is one compiled variant: a field plus its feature grid, training and
        # rendering, need more than dynamo's default of 8
        cfg = torch._dynamo.config
        cfg.recompile_limit = max(getattr(cfg, "recompile_limit", 8), 64)
        self._fn = torch.compile(encode_vectorized, dynamic=True)

    def __call__(self, x: torch.Tensor, table: torch.Tensor, spec: GridSpec) -> torch.Tensor:
        if self.failed:
            return self.fallback(x, table, spec)
        if self.ok:
            return self._fn(x, table, spec)
        try:
            out = self._fn(x, table, spec)
        except Exception as exc:  # noqa: BLE001 - any compiler failure means: run eager
            self.failed = True
            warnings.warn(f"torch.compile of the hash encoding failed ({type(exc).__name__}: {exc}); "
                          f"running eager (set {ENV_COMPILE}=0 to skip compiling)", RuntimeWarning, stacklevel=2)
            return self.fallback(x, table, spec)
        self.ok = True
        return out


_COMPILED: CompiledEncoder | None = None


def compiled_encoder() -> CompiledEncoder:
    """The process-wide compiled encoder (one compile cache for every grid)."""
    global _COMPILED
    if _COMPILED is None:
        _COMPILED = CompiledEncoder()
    return _COMPILED
