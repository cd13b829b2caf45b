"""`repaint-nerf bench encoding`: the driver of core/bench/encoding.py: sweeps grid shapes, point counts and
implementations (and optionally the field's feature heads), prints points per second and writes JSON."""
from __future__ import annotations

import argparse
import json
from pathlib import Path

from repaint_nerf.core.bench.encoding import IMPLS, field_cases, time_case, time_field

HELP = "time the hash-grid encoding (reference vs fast paths) for several table sizes and point counts"


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


def run_field(args: argparse.Namespace, device) -> list[dict]:
    """The feature-head cost comparison, side by side."""
    rows = []
    n = max(args.points)
    for name, cfg, outputs in field_cases(device, args.feature_dim):
        r = time_field(cfg, n, args.repeats, device, outputs)
        r["case"] = name
        rows.append(r)
        print(f"field {name:55s} n={n}: {r['s_per_100k_points'] * 1e3:7.1f} ms per 100k points fwd+bwd", flush=True)
    return rows


def run(args: argparse.Namespace) -> int:
    from repaint_nerf.core.device import describe, get_device
    from repaint_nerf.core.field.hashgrid import GridSpec

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
