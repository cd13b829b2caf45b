"""The hash encoding's reference and fast paths timed side by side, and the field's cost per feature head.

`time_case` gives forward (no grad, the render path) and forward+backward (the training path) of one grid
shape and point count; `time_field` one training-style field step; `field_cases` the feature-head
comparison. Returns dicts; the `bench encoding` driver (app/bench/encoding.py) sweeps, prints and writes JSON.
Timings on a shared machine are noisy: compare paths within one run, not across runs.
"""
from __future__ import annotations

import time

IMPLS = ("reference", "vectorized", "indexed", "compiled")


def _time(fn, repeats: int) -> float:
    from repaint_nerf.core.device import synchronize

    fn()  # warm-up (and compile)
    synchronize()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        synchronize()
        times.append(time.perf_counter() - t0)
    return sorted(times)[len(times) // 2]


def time_case(impl: str, spec, n: int, repeats: int, device) -> dict:
    """Median seconds and points/s of forward and forward+backward for one implementation and shape."""
    import torch

    from repaint_nerf.core.field.encoding import encoder_fn

    fn = encoder_fn(impl)
    gen = torch.Generator(device="cpu").manual_seed(0)
    table = spec.init_table(device).requires_grad_(True)
    x = (torch.rand(n, 3, generator=gen) * 2 - 1).to(device)

    def fwd():
        with torch.no_grad():
            fn(x, table, spec)

    def fwd_bwd():
        table.grad = None
        fn(x, table, spec).sum().backward()

    t_f, t_fb = _time(fwd, repeats), _time(fwd_bwd, repeats)
    return {"impl": impl, "points": n, "log2_table": spec.log2_table, "levels": spec.levels,
            "finest_res": spec.finest_res, "table_mb": spec.total_rows * spec.features * 4 / 2**20,
            "fwd_s": t_f, "fwd_bwd_s": t_fb, "fwd_points_per_s": n / t_f, "fwd_bwd_points_per_s": n / t_fb}


def time_field(cfg, n: int, repeats: int, device, outputs: tuple) -> dict:
    """Median seconds of one training-style step (forward of `outputs`, sum, backward) on n points."""
    import torch

    from repaint_nerf.core.field.field import NGPField

    field = NGPField(cfg).to(device)
    gen = torch.Generator(device="cpu").manual_seed(0)
    x = (torch.rand(n, 3, generator=gen) * 2 - 1).to(device)
    d = torch.randn(n, 3, generator=gen).to(device)

    def step():
        field.zero_grad(set_to_none=True)
        out = field(x, d, outputs)
        sum(v.float().mean() for v in out.values()).backward()

    t = _time(step, repeats)
    return {"points": n, "outputs": list(outputs), "feature_dim": cfg.feature_dim, "feature_head": cfg.feature_head,
            "levels": cfg.levels, "log2_table": cfg.log2_table, "finest_res": cfg.finest_res,
            "fwd_bwd_s": t, "s_per_100k_points": t * 1e5 / n}


def field_cases(device, feature_dim: int) -> list[tuple[str, object, tuple]]:
    """(name, FieldConfig, outputs) of the feature-head cost comparison (and the CPU default shape against
    instant-ngp's)."""
    from repaint_nerf.core.field.field import default_field_config

    base = default_field_config(device, 128)
    return [("default, no feature head", base, ("rgb",)),
            ("default + separate feature head", default_field_config(device, 128, feature_dim=feature_dim,
                                                                     feature_head="separate"), ("rgb", "feature")),
            ("default + separate feature head, 4 levels to 64",
             default_field_config(device, 128, feature_dim=feature_dim, feature_head="separate",
                                  feature_levels=4, feature_finest_res=64), ("rgb", "feature")),
            ("default + trunk feature head", default_field_config(device, 128, feature_dim=feature_dim,
                                                                  feature_head="trunk"), ("rgb", "feature")),
            ("instant-ngp shape (16 levels, 2^19), no feature head",
             default_field_config("cuda", 128), ("rgb",))]
