"""`repaint-nerf bench encoding`: the hash encoding's reference and fast paths timed side by side.

For each grid shape (table size, levels, finest resolution) and point count it times forward (no grad,
the render path) and forward+backward (the training path) and writes points per second as JSON.
Timings on a shared machine are noisy: compare paths within one run, not across runs.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

HELP = "time the hash-grid encoding (reference vs fast paths) for several table sizes and point counts"
IMPLS = ("reference", "vectorized", "indexed", "compiled")


def _ints(text: str) -> list[int]:
    return [int(v) for v in text.split(",") if v]


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--log2-tables", type=_ints, default=[14, 16, 17, 19], help="comma list of log2 table sizes")
    p.add_argument("--levels", type=_ints, default=[16], help="comma list of level counts")
    p.add_argument("--finest", type=_ints, default=[2048], help="comma list of finest resolutions")
    p.add_argument("--points", type=_ints, default=[131072], help="comma list of point counts")
    p.add_argument("--impls", default=",".join(IMPLS), help=f"comma list of {IMPLS}")
    p.add_argument("--repeats", type=int, default=3, help="timed repeats per case (the median is kept)")
    p.add_argument("--field", action="store_true",
                   help="also time the whole field forward+backward (rgb + sigma) with no feature head, "
                        "the separate (DFF) head and the trunk head, per 100k points")
    p.add_argument("--field-only", action="store_true", help="skip the encoding sweep, time only the field")
    p.add_argument("--feature-dim", type=int, default=32, help="feature width for --field")
    p.add_argument("--json", default="bench_encoding.json", help="output JSON path")


def _time(fn, repeats: int) -> float:
    from core.device import synchronize

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

    from core.field.encoding import encoder_fn

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

    from core.field.field import NGPField

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


def run_field(args: argparse.Namespace, device) -> list[dict]:
    """The feature-head cost comparison (and the CPU default shape against instant-ngp's), side by side."""
    from core.field.field import default_field_config

    rows = []
    n = max(args.points)
    base = default_field_config(device, 128)
    cases = [("default, no feature head", base, ("rgb",)),
             ("default + separate feature head", default_field_config(device, 128, feature_dim=args.feature_dim,
                                                                      feature_head="separate"), ("rgb", "feature")),
             ("default + separate feature head, 4 levels to 64",
              default_field_config(device, 128, feature_dim=args.feature_dim, feature_head="separate",
                                   feature_levels=4, feature_finest_res=64), ("rgb", "feature")),
             ("default + trunk feature head", default_field_config(device, 128, feature_dim=args.feature_dim,
                                                                   feature_head="trunk"), ("rgb", "feature")),
             ("instant-ngp shape (16 levels, 2^19), no feature head",
              default_field_config("cuda", 128), ("rgb",))]
    for name, cfg, outputs in cases:
        r = time_field(cfg, n, args.repeats, device, outputs)
        r["case"] = name
        rows.append(r)
        print(f"field {name:55s} n={n}: {r['s_per_100k_points'] * 1e3:7.1f} ms per 100k points fwd+bwd", flush=True)
    return rows


def run(args: argparse.Namespace) -> int:
    from core.device import describe, get_device
    from core.field.hashgrid import GridSpec

    device = get_device()
    impls = [i for i in args.impls.split(",") if i]
    rows = []
    for lvl in ([] if args.field_only else args.levels):
        for fin in args.finest:
            for t in args.log2_tables:
                spec = GridSpec(levels=lvl, features=2, log2_table=t, base_res=16, finest_res=fin)
                for n in args.points:
                    for impl in impls:
                        r = time_case(impl, spec, n, args.repeats, device)
                        rows.append(r)
                        print(f"L={lvl:2d} N_max={fin:4d} T=2^{t} ({r['table_mb']:6.1f} MB) n={n:7d} {impl:10s} "
                              f"fwd {r['fwd_points_per_s'] / 1e6:6.2f} Mpt/s  fwd+bwd {r['fwd_bwd_points_per_s'] / 1e6:6.2f} Mpt/s",
                              flush=True)
    out = Path(args.json)
    out.parent.mkdir(parents=True, exist_ok=True)
    field_rows = run_field(args, device) if (args.field or args.field_only) else []
    out.write_text(json.dumps({"device": describe(device), "results": rows, "field": field_rows}, indent=1))
    print(f"wrote {out}")
    return 0
