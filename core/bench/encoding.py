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


def run(args: argparse.Namespace) -> int:
    from core.device import describe, get_device
    from core.field.hashgrid import GridSpec

    device = get_device()
    impls = [i for i in args.impls.split(",") if i]
    rows = []
    for lvl in args.levels:
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
    out.write_text(json.dumps({"device": describe(device), "results": rows}, indent=1))
    print(f"wrote {out}")
    return 0
