"""Multi-resolution hash encoding (instant-ngp, Mueller et al. 2022): the layout and a plain reference.

`GridSpec` fixes the level resolutions, which levels are dense, and where each level lives in one flat
table of shape (sum of level sizes, F). `encode_reference` is the readable loop over levels and corners
that every fast path is tested against.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import torch

# instant-ngp's spatial-hash primes for x, y, z (the first is 1 so nearby x stay coherent in memory).
PRIMES = (1, 2654435761, 805459861)
INIT_SCALE = 1e-4  # table entries start uniform in [-1e-4, 1e-4]


@dataclass(frozen=True)
class GridSpec:
    """Shape of a hash grid: L levels of F features, 2^T entries per hashed level, resolutions N_min..N_max."""

    levels: int = 16
    features: int = 2
    log2_table: int = 19
    base_res: int = 16
    finest_res: int = 2048
    bound: float = 1.0

    def __post_init__(self) -> None:
        from repaint_nerf.core.errors import UserError

        if self.levels < 1 or self.features < 1 or not 1 <= self.log2_table <= 30:
            raise UserError(f"invalid hash-grid shape {self}", hint="levels, features >= 1; log2_table in 1..30")
        if not 1 <= self.base_res <= self.finest_res or self.bound <= 0:
            raise UserError(f"invalid hash-grid resolutions {self}", hint="need 1 <= base_res <= finest_res, bound > 0")

    @property
    def table_size(self) -> int:
        return 1 << self.log2_table

    @property
    def growth(self) -> float:
        """Per-level growth factor b = exp((ln N_max - ln N_min) / (L - 1))."""
        if self.levels == 1:
            return 1.0
        return math.exp((math.log(self.finest_res) - math.log(self.base_res)) / (self.levels - 1))

    @cached_property
    def resolutions(self) -> tuple[int, ...]:
        """Cells per axis of each level, floor(N_min * b^l) (the +1e-6 keeps N_max exact)."""
        return tuple(int(math.floor(self.base_res * self.growth ** l + 1e-6)) for l in range(self.levels))

    @cached_property
    def dense(self) -> tuple[bool, ...]:
        """A level is indexed densely (no collisions) when its (res+1)^3 vertices fit in the table."""
        return tuple((r + 1) ** 3 <= self.table_size for r in self.resolutions)

    @cached_property
    def level_sizes(self) -> tuple[int, ...]:
        return tuple((r + 1) ** 3 if d else self.table_size for r, d in zip(self.resolutions, self.dense))

    @cached_property
    def offsets(self) -> tuple[int, ...]:
        """Start row of each level in the flat table."""
        out, acc = [], 0
        for size in self.level_sizes:
            out.append(acc)
            acc += size
        return tuple(out)

    @property
    def total_rows(self) -> int:
        return sum(self.level_sizes)

    @property
    def out_dim(self) -> int:
        return self.levels * self.features

    def init_table(self, device: torch.device | str | None = None, generator: torch.Generator | None = None) -> torch.Tensor:
        """A fresh flat table (total_rows, F), uniform in [-1e-4, 1e-4]."""
        t = torch.empty(self.total_rows, self.features, device=device)
        return t.uniform_(-INIT_SCALE, INIT_SCALE, generator=generator)


def spatial_hash(coords: torch.Tensor, table_size: int) -> torch.Tensor:
    """instant-ngp's hash of integer vertex coordinates (..., 3): xor of coord * prime, modulo table_size (a power of 2)."""
    c = coords.long()
    h = (c[..., 0] * PRIMES[0]) ^ (c[..., 1] * PRIMES[1]) ^ (c[..., 2] * PRIMES[2])
    return h & (table_size - 1)


def dense_index(coords: torch.Tensor, res: int) -> torch.Tensor:
    """Row of vertex (x, y, z) in a dense level with res+1 vertices per axis: x + y (res+1) + z (res+1)^2."""
    c = coords.long()
    n = res + 1
    return c[..., 0] + c[..., 1] * n + c[..., 2] * (n * n)


def to_unit_cube(x: torch.Tensor, bound: float) -> torch.Tensor:
    """Field coordinates in [-bound, bound]^3 -> [0, 1]^3; points beyond the cube are clamped onto its faces
    and NaN coordinates (e.g. a warp's 0/0) go to 0, so they index the table instead of crashing the gather."""
    return ((x + bound) / (2.0 * bound)).clamp(0.0, 1.0).nan_to_num(0.0)


def encode_reference(x: torch.Tensor, table: torch.Tensor, spec: GridSpec) -> torch.Tensor:
    """Encode points x (N, 3) in field space with the flat table: (N, L*F), level-major. Plain loops, for tests."""
    u = to_unit_cube(x, spec.bound)
    feats = []
    for level, res in enumerate(spec.resolutions):
        pos = u * res
        cell = pos.floor().clamp(0, res - 1)  # u == 1 lands in the last cell with fraction 1
        frac = pos - cell
        cell = cell.long()
        acc = torch.zeros(x.shape[0], spec.features, dtype=table.dtype, device=x.device)
        for corner in range(8):
            bits = [(corner >> a) & 1 for a in range(3)]
            vertex = cell + torch.tensor(bits, device=x.device)
            if spec.dense[level]:
                row = dense_index(vertex, res)
            else:
                row = spatial_hash(vertex, spec.table_size)
            weight = torch.ones_like(frac[:, 0])
            for a in range(3):
                weight = weight * (frac[:, a] if bits[a] else 1.0 - frac[:, a])
            acc = acc + weight[:, None] * table[spec.offsets[level] + row]
        feats.append(acc)
    return torch.cat(feats, dim=-1)
