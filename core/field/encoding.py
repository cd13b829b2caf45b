"""`HashGridEncoding`: the hash grid as a module, with its table as a parameter and a chosen implementation.

The implementations (reference, vectorized, indexed, compiled, native) compute the same function; "auto"
picks the native C kernel for CPU tensors (22x the indexed eager path, 3.3x the compiled one, measured at
262k points, 12 levels) and, on other devices or without a C compiler, the compiled path where compilation
is enabled and the indexed eager path otherwise.
"""
from __future__ import annotations

from typing import Callable

import torch

from repaint_nerf.core.field.hashgrid import GridSpec, encode_reference
from repaint_nerf.core.field.hashgrid_fast import compile_enabled, compiled_encoder, encode_indexed, encode_vectorized
from repaint_nerf.core.field.hashgrid_native import encode_native
from repaint_nerf.core.field.hashgrid_native import usable as native_usable

EncodeFn = Callable[[torch.Tensor, torch.Tensor, GridSpec], torch.Tensor]


class AutoEncoder:
    """The native kernel for CPU float32 inputs when it could be built, else `other` (compiled or indexed)."""

    def __init__(self, other: EncodeFn):
        self.other = other

    def __call__(self, x: torch.Tensor, table: torch.Tensor, spec: GridSpec) -> torch.Tensor:
        return encode_native(x, table, spec) if native_usable(x, table, spec) else self.other(x, table, spec)


def encoder_fn(impl: str = "auto", compile: bool = True) -> EncodeFn:
    """The encode function for `impl` in {auto, reference, vectorized, indexed, compiled, native}."""
    from repaint_nerf.core.errors import UserError

    if impl == "auto":
        return AutoEncoder(encoder_fn("compiled" if compile_enabled(compile) else "indexed", compile))
    table = {"reference": encode_reference, "vectorized": encode_vectorized, "indexed": encode_indexed,
             "native": encode_native}
    if impl == "compiled":
        return compiled_encoder() if compile_enabled(compile) else encode_indexed
    if impl not in table:
        raise UserError(f"unknown hash-encoding implementation '{impl}'",
                        hint="use one of auto, reference, vectorized, indexed, compiled, native")
    return table[impl]


class HashGridEncoding(torch.nn.Module):
    """(N, 3) field coordinates -> (N, L*F) features, with the flat table as the parameter `table`."""

    def __init__(self, spec: GridSpec, impl: str = "auto", compile: bool = True):
        super().__init__()
        self.spec = spec
        self.table = torch.nn.Parameter(spec.init_table())
        self._fn = encoder_fn(impl, compile)

    @property
    def out_dim(self) -> int:
        return self.spec.out_dim

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.shape[0] == 0:
            return x.new_zeros(0, self.out_dim)
        return self._fn(x.contiguous(), self.table, self.spec)
