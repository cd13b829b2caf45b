"""`HashGridEncoding`: the hash grid as a module, with its table as a parameter and a chosen implementation.

The implementations (reference, vectorized, indexed, compiled) compute the same function; "auto" picks
the compiled path where compilation is enabled and the indexed eager path otherwise.
"""
from __future__ import annotations

from typing import Callable

import torch

from core.field.hashgrid import GridSpec, encode_reference
from core.field.hashgrid_fast import compile_enabled, compiled_encoder, encode_indexed, encode_vectorized

EncodeFn = Callable[[torch.Tensor, torch.Tensor, GridSpec], torch.Tensor]


def encoder_fn(impl: str = "auto", compile: bool = True) -> EncodeFn:
    """The encode function for `impl` in {auto, reference, vectorized, indexed, compiled}."""
    from core.errors import UserError

    if impl == "auto":
        impl = "compiled" if compile_enabled(compile) else "indexed"
    table = {"reference": encode_reference, "vectorized": encode_vectorized, "indexed": encode_indexed}
    if impl == "compiled":
        return compiled_encoder() if compile_enabled(compile) else encode_indexed
    if impl not in table:
        raise UserError(f"unknown hash-encoding implementation '{impl}'",
                        hint="use one of auto, reference, vectorized, indexed, compiled")
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
