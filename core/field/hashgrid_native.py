"""The hash encoding as a small native CPU kernel (core/field/csrc/hashgrid.c), called through ctypes.

Eager PyTorch builds (N, L, 8) index and weight tensors and gathers from them; the kernel walks each point
once, so on a CPU it is memory-bandwidth bound instead of allocation bound. It is compiled with the
system C compiler on first use into a per-user cache (keyed by the source's hash) and falls back to the
eager path with a warning when no compiler is available. CUDA tensors never come here.
"""
from __future__ import annotations

import ctypes
from pathlib import Path

import torch

from repaint_nerf.core.field.hashgrid import GridSpec
from repaint_nerf.core.field.hashgrid_fast import encode_vectorized
from repaint_nerf.core.native import NativeLibrary


def _bind(lib: ctypes.CDLL) -> ctypes.CDLL:
    p, i64, i32, u32, f32 = ctypes.c_void_p, ctypes.c_int64, ctypes.c_int32, ctypes.c_uint32, ctypes.c_float
    lib.hg_forward.argtypes = [p, i64, p, i32, i32, p, p, p, u32, f32, p, i32]
    lib.hg_backward.argtypes = [p, i64, p, i32, i32, p, p, p, u32, f32, p, i32]
    lib.hg_forward.restype = lib.hg_backward.restype = None
    lib.hg_max_features.restype = ctypes.c_int
    return lib


LIBRARY = NativeLibrary(Path(__file__).with_name("csrc") / "hashgrid.c", _bind, "hash-grid")


def native_lib() -> ctypes.CDLL | None:
    """The loaded kernel, building it on first use; None (after one warning) when it cannot be built."""
    return LIBRARY.get()


def native_available() -> bool:
    return native_lib() is not None


class _Consts:
    """Per-spec int tensors the kernel reads (kept alive with the spec)."""

    _cache: dict = {}

    def __init__(self, spec: GridSpec):
        self.res = torch.tensor(spec.resolutions, dtype=torch.int32)
        self.dense = torch.tensor([int(d) for d in spec.dense], dtype=torch.int32)
        self.offsets = torch.tensor(spec.offsets, dtype=torch.int64)

    @classmethod
    def get(cls, spec: GridSpec) -> "_Consts":
        if spec not in cls._cache:
            cls._cache[spec] = cls(spec)
        return cls._cache[spec]


def _args(spec: GridSpec) -> tuple:
    c = _Consts.get(spec)
    return (c.res.data_ptr(), c.dense.data_ptr(), c.offsets.data_ptr(), spec.table_size - 1, float(spec.bound))


class _NativeEncode(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, table, spec):
        lib = native_lib()
        n = x.shape[0]
        out = torch.empty(n, spec.out_dim, dtype=torch.float32)
        lib.hg_forward(x.data_ptr(), n, table.data_ptr(), spec.features, spec.levels, *_args(spec),
                       out.data_ptr(), torch.get_num_threads())
        ctx.save_for_backward(x, table)
        ctx.spec = spec
        return out

    @staticmethod
    def backward(ctx, grad_out):
        x, table = ctx.saved_tensors
        spec = ctx.spec
        grad_x = grad_table = None
        if ctx.needs_input_grad[1]:
            g = grad_out.contiguous().float()
            grad_table = torch.zeros_like(table)
            native_lib().hg_backward(x.data_ptr(), x.shape[0], g.data_ptr(), spec.features, spec.levels,
                                     *_args(spec), grad_table.data_ptr(), torch.get_num_threads())
        if ctx.needs_input_grad[0]:
            # input gradients are rare (no NeRF step needs them): recompute through plain autograd
            with torch.enable_grad():
                xd = x.detach().requires_grad_(True)
                (grad_x,) = torch.autograd.grad(encode_vectorized(xd, table.detach(), spec), xd, grad_out)
        return grad_x, grad_table, None


def usable(x: torch.Tensor, table: torch.Tensor, spec: GridSpec) -> bool:
    """Whether the kernel handles these inputs: CPU float32 and a built library."""
    if not (x.device.type == "cpu" and table.device.type == "cpu" and x.dtype == torch.float32
            and table.dtype == torch.float32):
        return False
    lib = native_lib()
    return lib is not None and spec.features <= lib.hg_max_features()


def encode_native(x: torch.Tensor, table: torch.Tensor, spec: GridSpec) -> torch.Tensor:
    """(N, 3) field coords -> (N, L*F) with the native kernel (falls back to the indexed path when unusable)."""
    if not usable(x, table, spec):
        from repaint_nerf.core.field.hashgrid_fast import encode_indexed

        return encode_indexed(x, table, spec)
    return _NativeEncode.apply(x.contiguous(), table.contiguous(), spec)
