"""The radiance field of stage 1 and 2: hash grid -> density MLP -> colour MLP, plus an optional feature head.

`NGPField.forward` computes only the outputs asked for; `density` is the cheap path for the occupancy
grid. The feature head realises the paper's feature field s: x -> f (Semantic Mask Extraction; rendered
like colour, paper Eq. F(r)) in one of two designs, chosen by `FieldConfig.feature_head`.
"""
from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import asdict, dataclass, fields

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from repaint_nerf.core.field.activations import density_activation
from repaint_nerf.core.field.appearance import AppearanceCodes
from repaint_nerf.core.field.contraction import make_warp
from repaint_nerf.core.field.direction import sh_dim, sh_encode
from repaint_nerf.core.field.encoding import HashGridEncoding
from repaint_nerf.core.field.hashgrid import GridSpec

OUTPUTS = ("sigma", "rgb", "feature")


_GRID = GridSpec()
# CPU inference evaluates the field this many points at a time instead of a marching round's up to 262k at once. Its
# temporaries (65536 x 64 floats: 16 MB) then come from memory malloc recycles, where a whole round's are freshly
# mapped (and page-faulted) each call, it seems. Fox capture, one 288x512 training view (medians of 3, alternating,
# 2 threads): colour 2.9-3.0 s against 3.9-4.5 s at once; features, depth and opacity 3.7-3.8 against 4.4-5.0 s;
# blocks of 4096 rows lost on per-call overhead (half-size views: colour 1.00 against 0.82 s).
INFER_ROWS = 65536


@dataclass
class FieldConfig:
    """Everything that shapes a field; JSON-serialisable (dataclasses.asdict) and saved with checkpoints.

    feature_head: "trunk" = a small MLP on the density trunk's hidden layer (the default); "separate" = DFF's
    design (own low-resolution hash grid + MLP, view-independent; its gradients never touch the geometry).
    Chosen by measurement (`repaint-nerf bench encoding --field-only`, 65k points, 32 feature dims, contended
    2-core CPU, two runs): over the field without a head, the trunk head adds 0.4-0.6 s per 100k points
    forward+backward, the separate head 0.9-3.1 s (0.7 s with 4 levels): its extra gather costs more than
    the small MLP. Pick "separate" when the feature loss must not move density and colour.
    """

    # the colour/density grid: GridSpec's defaults (instant-ngp's), stated once there
    levels: int = _GRID.levels
    features_per_level: int = _GRID.features
    log2_table: int = _GRID.log2_table
    base_res: int = _GRID.base_res
    finest_res: int = _GRID.finest_res
    hidden: int = 64
    geo_feat_dim: int = 15
    color_hidden_layers: int = 1
    sh_degree: int = 4
    density_activation: str = "trunc_exp"
    feature_dim: int = 0  # 0 = no feature head (costs nothing)
    feature_head: str = "trunk"
    feature_levels: int = 8
    feature_log2_table: int = 15
    feature_base_res: int = 8
    feature_finest_res: int = 128
    feature_hidden: int = 64
    encoding_impl: str = "auto"  # auto | reference | vectorized | indexed | compiled | native
    compile: bool = True  # $REPAINT_NERF_COMPILE=0 overrides to eager
    bound: float = _GRID.bound  # field cube half-size
    warp: dict | None = None  # unbounded / forward scenes: a core.field.contraction spec (None: bounded)
    appearance_dim: int = 0  # per-image appearance code size (core.field.appearance; 0 = none)
    appearance_count: int = 0  # training images with a code

    def grid_spec(self) -> GridSpec:
        return GridSpec(self.levels, self.features_per_level, self.log2_table, self.base_res, self.finest_res, self.bound)

    def feature_grid_spec(self) -> GridSpec:
        return GridSpec(self.feature_levels, 2, self.feature_log2_table, self.feature_base_res,
                        self.feature_finest_res, self.bound)

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "FieldConfig":
        """Build from a saved dict; unknown keys (from a newer version) are ignored."""
        known = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in d.items() if k in known})


def _mlp(n_in: int, hidden: int, n_out: int, hidden_layers: int = 1) -> nn.Sequential:
    layers: list[nn.Module] = []
    width = n_in
    for _ in range(hidden_layers):
        layers += [nn.Linear(width, hidden), nn.ReLU(inplace=True)]
        width = hidden
    layers.append(nn.Linear(width, n_out))
    return nn.Sequential(*layers)


class NGPField(nn.Module):
    """Instant-NGP style field over the cube [-bound, bound]^3: sigma, view-dependent rgb, optional features."""

    view_per_ray = True  # forward takes directions per ray with each point's `ray` (the renderer's fast call)
    sparse_features = True  # forward takes `feature_rows`: the feature head reads neither view nor image code

    def __init__(self, cfg: FieldConfig):
        super().__init__()
        from repaint_nerf.core.errors import UserError

        if cfg.feature_head not in ("separate", "trunk"):
            raise UserError(f"unknown feature head '{cfg.feature_head}'", hint="use 'separate' or 'trunk'")
        self.cfg = cfg
        self.warp = make_warp(cfg.warp)
        self.grid = HashGridEncoding(cfg.grid_spec(), cfg.encoding_impl, cfg.compile)
        # density trunk: encoding -> hidden -> [density pre-activation, geo features]
        self.trunk = nn.Linear(self.grid.out_dim, cfg.hidden)
        self.trunk_out = nn.Linear(cfg.hidden, 1 + cfg.geo_feat_dim)
        self.appearance = AppearanceCodes(cfg.appearance_count, cfg.appearance_dim) \
            if cfg.appearance_dim > 0 and cfg.appearance_count > 0 else None
        color_in = cfg.geo_feat_dim + sh_dim(cfg.sh_degree) + (cfg.appearance_dim if self.appearance else 0)
        self.color_net = _mlp(color_in, cfg.hidden, 3, cfg.color_hidden_layers)
        self.act = density_activation(cfg.density_activation)
        self.feature_grid: HashGridEncoding | None = None
        self.feature_net: nn.Sequential | None = None
        if cfg.feature_dim > 0:
            if cfg.feature_head == "separate":
                self.feature_grid = HashGridEncoding(cfg.feature_grid_spec(), cfg.encoding_impl, cfg.compile)
                self.feature_net = _mlp(self.feature_grid.out_dim, cfg.feature_hidden, cfg.feature_dim)
            else:
                self.feature_net = _mlp(cfg.hidden, cfg.feature_hidden, cfg.feature_dim)

    def inside(self, x: Tensor) -> Tensor:
        """(N,) bool: the point lies in the closed cube [-bound, bound]^3."""
        return (x.abs() <= self.cfg.bound).all(dim=-1)

    def march(self) -> tuple[float, float]:
        """(extent, cone) for the renderer: rays run inside [-extent, extent]^3 with steps >= cone * distance."""
        if self.warp is None:
            return self.cfg.bound, 0.0
        return float(self.cfg.warp["extent"]), float(self.cfg.warp.get("cone", 0.0))

    def _hidden(self, x: Tensor) -> Tensor:
        return F.relu(self.trunk(self.grid(x)), inplace=True)  # no second (N, hidden) tensor

    def _by_rows(self, n: int) -> bool:
        """Whether `n` points are evaluated `INFER_ROWS` at a time: inference (no gradients) on a CPU."""
        return n > INFER_ROWS and not torch.is_grad_enabled() and self.trunk.weight.device.type == "cpu"

    def density(self, x: Tensor) -> Tensor:
        """(N, 3) field coordinates -> (N,) sigma >= 0, 0 outside the cube. Only the density row of the trunk runs."""
        if self.warp is not None:
            x = self.warp(x)
        if self._by_rows(x.shape[0]):
            sigma = x.new_empty(x.shape[0])
            for a in range(0, x.shape[0], INFER_ROWS):
                sigma[a:a + INFER_ROWS] = self._density_rows(x[a:a + INFER_ROWS])
            return sigma
        return self._density_rows(x)

    def _density_rows(self, x: Tensor) -> Tensor:
        pre = F.linear(self._hidden(x), self.trunk_out.weight[:1], self.trunk_out.bias[:1])[:, 0]
        return self.act(pre) * self.inside(x).to(pre.dtype)

    def forward(self, x: Tensor, d: Tensor | None = None, outputs=("rgb",),
                appearance: Tensor | None = None, ray: Tensor | None = None,
                feature_rows: Callable[[Tensor], Tensor] | None = None) -> dict[str, Tensor]:
        """Evaluate at points x (N, 3) seen along directions d (N, 3): 'sigma' always, 'rgb'/'feature' when asked.
        `appearance` (N,) picks each point's image code (fields with codes; None: the mean code).
        With `ray` (N,) long, d (R, 3) and appearance (R,) are per ray and point i lies on ray[i]: what depends
        on the view alone is then computed once per ray, not once per point (a renderer's R is ~30x smaller).
        `feature_rows(sigma)` (long indices) picks the points whose 'feature' is evaluated; the others' are 0."""
        from repaint_nerf.core.errors import UserError

        unknown = set(outputs) - set(OUTPUTS)
        if unknown:
            raise UserError(f"unknown field outputs {sorted(unknown)}", hint=f"ask for any of {OUTPUTS}")
        if "rgb" in outputs and d is None:
            raise UserError("the field needs view directions to compute 'rgb'", hint="pass d (N, 3)")
        if "feature" in outputs and self.feature_net is None:
            raise UserError("this field has no feature head", hint="set feature_dim > 0 in the field config")
        if self.warp is not None:
            x = self.warp(x)
        if self._by_rows(x.shape[0]):
            return self._heads_by_rows(x, d, outputs, appearance, ray, feature_rows)
        return self._heads(x, d, outputs, appearance, ray, feature_rows)

    def _heads(self, x: Tensor, d: Tensor | None, outputs, appearance: Tensor | None, ray: Tensor | None,
               feature_rows: Callable[[Tensor], Tensor] | None) -> dict[str, Tensor]:
        """`forward` on warped points, in one call."""
        h = self._hidden(x)
        out_t = self.trunk_out(h)
        result = {"sigma": self.act(out_t[:, 0]) * self.inside(x).to(out_t.dtype)}
        if "rgb" in outputs:
            result["rgb"] = torch.sigmoid(self.color_net[1:](self._color_input(out_t, d, appearance, ray)))
        if "feature" in outputs:
            if feature_rows is None:
                result["feature"] = self.feature_net(self.feature_grid(x) if self.feature_grid is not None else h)
            else:
                rows = feature_rows(result["sigma"])
                src = self.feature_grid(x[rows]) if self.feature_grid is not None else h.index_select(0, rows)
                picked = self.feature_net(src)
                result["feature"] = picked.new_zeros((x.shape[0], picked.shape[-1])).index_copy_(0, rows, picked)
        return result

    def _heads_by_rows(self, x: Tensor, d: Tensor | None, outputs, appearance: Tensor | None, ray: Tensor | None,
                       feature_rows: Callable[[Tensor], Tensor] | None) -> dict[str, Tensor]:
        """`_heads` without gradients, `INFER_ROWS` points at a time: the same values from smaller temporaries (see
        `INFER_ROWS`). A block of per-ray calls takes the rays its points lie on. Features on the rows
        `feature_rows` picks (a function of every point's sigma) follow the blocks; a trunk head evaluates those
        rows' trunk again, cheaper than keeping (N, hidden) for a third of them."""
        n, rows = x.shape[0], INFER_ROWS
        chosen = "feature" in outputs and feature_rows is not None
        heads = tuple(o for o in outputs if not (chosen and o == "feature"))
        result: dict[str, Tensor] = {}
        for a in range(0, n, rows):
            if ray is None:
                part = self._heads(x[a:a + rows], None if d is None else d[a:a + rows], heads,
                                   None if appearance is None else appearance[a:a + rows], None, None)
            else:
                rb = ray[a:a + rows]
                r0, r1 = int(rb.min()), int(rb.max()) + 1
                part = self._heads(x[a:a + rows], None if d is None else d[r0:r1], heads,
                                   None if appearance is None else appearance[r0:r1], rb - r0, None)
            for k, v in part.items():
                if k not in result:
                    result[k] = v.new_empty((n,) + tuple(v.shape[1:]))
                result[k][a:a + rows] = v
        if chosen:
            picked = feature_rows(result["sigma"])
            feat = x.new_zeros((n, self.cfg.feature_dim))
            for a in range(0, picked.shape[0], rows):
                pb = picked[a:a + rows]
                xp = x.index_select(0, pb)
                src = self.feature_grid(xp) if self.feature_grid is not None else self._hidden(xp)
                feat.index_copy_(0, pb, self.feature_net(src))
            result["feature"] = feat
        return result

    def _color_input(self, out_t: Tensor, d: Tensor, appearance: Tensor | None, ray: Tensor | None) -> Tensor:
        """The colour head's first layer on [geo features, SH(d), appearance code], split by its columns: the view
        part (SH, code, bias) per row of d, gathered by `ray` when d is per ray, plus the geo part per point."""
        first: nn.Linear = self.color_net[0]
        g, k = self.cfg.geo_feat_dim, sh_dim(self.cfg.sh_degree)
        w = first.weight
        view = torch.addmm(first.bias, sh_encode(d, self.cfg.sh_degree).to(w.dtype), w[:, g:g + k].t())
        if self.appearance is not None:
            view = view + self.appearance(appearance, d.shape[0]).to(w.dtype) @ w[:, g + k:].t()
        if ray is not None:
            view = view.index_select(0, ray)
        # in place: no (N, hidden) copy of the view term; in-place ops skip autocast, so the dtypes are made to match
        return view.addmm_(out_t[:, 1:].to(view.dtype), w[:, :g].t().to(view.dtype))

    def parameter_groups(self) -> dict[str, list[nn.Parameter]]:
        """Parameters by learning-rate group: 'grid' (hash table), 'mlp' (density + colour), 'feature' (feature head)."""
        feature = []
        if self.feature_grid is not None:
            feature += list(self.feature_grid.parameters())
        if self.feature_net is not None:
            feature += list(self.feature_net.parameters())
        mlp = [*self.trunk.parameters(), *self.trunk_out.parameters(), *self.color_net.parameters()]
        if self.appearance is not None:
            mlp += list(self.appearance.parameters())
        return {"grid": list(self.grid.parameters()), "mlp": mlp, "feature": feature}


def default_field_config(device: torch.device | str | None = None, image_size: int = 800, **overrides) -> FieldConfig:
    """Field shape for the device and image size (longest side in pixels).

    CUDA: instant-ngp's 16 levels x 2 features, 2^19 table, finest 2048. CPU: cost grows with the level
    count and with the table once it leaves cache. Measured (compiled path, 131k points, 16 levels, finest
    2048, contended 2-core CPU, rough): forward+backward 0.23 Mpt/s at 2^14, 0.10 at 2^16; at 2^16 and
    finest 512, 8 levels 0.14 Mpt/s vs 12 levels 0.09. So the CPU default takes the in-cache 2^14 table
    (128 KB per hashed level) and 12 levels, and the finest resolution follows the image (4 cells per
    pixel, 256..2048): finer levels add no detail a 128-px view can show. The table grows with the image
    (`cpu_log2_table`). Reconstruction quality of these shapes is for the recon benchmark to confirm. Figures:
    `repaint-nerf bench encoding`.
    """
    from repaint_nerf.core.device import get_device

    dev = torch.device(device) if device is not None else get_device()
    if dev.type == "cuda":
        cfg = FieldConfig(levels=16, features_per_level=2, log2_table=19, base_res=16, finest_res=2048)
    else:
        finest = int(min(2048, max(256, 4 * image_size)))
        cfg = FieldConfig(levels=CPU_LEVELS, features_per_level=2, log2_table=cpu_log2_table(image_size),
                          base_res=16, finest_res=finest)
    return FieldConfig(**{**cfg.to_dict(), **overrides})


def cpu_log2_table(image_size: int) -> int:
    """log2 of a hashed level's table on a CPU for images `image_size` pixels on their long side: 2^14 up to 256 px,
    then 4x per doubling of the image (the cells a surface covers at the finest level, which follows the image), up
    to 2^16 from about 512 px. 2^14 stays in cache, where each step is fastest; 2^16 (512 KB a level) makes each step
    15-27% slower, and on photos of ~500 px gains more than that: one core, 300 s, 2^16 against 2^14, held-out PSNR at
    60 / 120 / 300 s: fox +0.59 / +0.73 / +1.10 dB, fern +0.36 / +0.36 / +0.52, ethiopian_head +0.22 / +0.18 / +0.16
    (docs/ARCHITECTURE.md, "Speed")."""
    grow = CPU_LOG2_TABLE + 2 * math.log2(max(image_size, 1) / CPU_TABLE_FROM_PX)
    return int(min(CPU_LOG2_TABLE_MAX, max(CPU_LOG2_TABLE, round(grow))))


CPU_LEVELS = 12
CPU_LOG2_TABLE = 14  # up to CPU_TABLE_FROM_PX
CPU_TABLE_FROM_PX = 256
CPU_LOG2_TABLE_MAX = 16
