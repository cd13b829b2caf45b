"""`repaint-nerf bench sdcost`: what one Stable Diffusion score-distillation step costs, stage by stage, for
each speed option (bf16 UNet, tiny autoencoder, 256-px SDS, token merging and their combination), measured in one process
by core.bench.sdcost; writes the JSON and prints a table."""
from __future__ import annotations

import argparse
import json
from pathlib import Path

HELP = "cost of one Stable Diffusion score-distillation step per stage and per speed option (random weights)"
STAGES = ("resize", "encode_forward", "unet_forward", "loss", "rest", "backward")


def add_arguments(p: argparse.ArgumentParser) -> None:
    from repaint_nerf.core.bench.sdcost import FAMILIES, OPTIONS

    p.add_argument("--steps", type=int, default=2, help="timed steps per option and round (after one warm-up step "
                                                         "each)")
    p.add_argument("--rounds", type=int, default=1,
                   help="rounds in which the options take turns (a shared machine's load weighs on all alike)")
    p.add_argument("--size", type=int, default=128, help="render side in pixels (resized to the SDS resolution)")
    p.add_argument("--family", choices=FAMILIES, default="sd15", help="architecture: SD 1.5 or SD 2-base")
    p.add_argument("--options", default=None,
                   help=f"comma-separated subset of: {', '.join(OPTIONS)} (default: all, in that order)")
    p.add_argument("--json", required=True, help="output JSON path")
    p.add_argument("--device", default=None)


def table(result: dict, cpu: bool = False) -> str:
    """The per-option figures (wall seconds, or CPU seconds when `cpu`) as a fixed-width text table."""
    sfx = "_cpu" if cpu else ""
    head = (f"{'option':<22}{'CPU s' if cpu else 's/step':>8}{'x base':>8}" + "".join(f"{s[:10]:>11}" for s in STAGES)
            + f"{'peak MB':>9}")
    lines = [head]
    speed = result.get("cpu_speedup_vs_baseline" if cpu else "speedup_vs_baseline", {})
    for name, r in result["options"].items():
        st = r[f"stages{sfx}_seconds"]
        lines.append(f"{name:<22}{r[f'step{sfx}_seconds']:>8.2f}{speed.get(name, float('nan')):>8.2f}"
                     + "".join(f"{st.get(s, float('nan')):>11.2f}" for s in STAGES) + f"{r['peak_rss_mb']:>9.0f}")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    from repaint_nerf.core.bench.sdcost import measure

    names = [n.strip() for n in args.options.split(",") if n.strip()] if args.options else None
    out = Path(args.json)
    out.parent.mkdir(parents=True, exist_ok=True)

    def write(result: dict) -> None:
        out.write_text(json.dumps(result, indent=2))

    result = measure(args.device, steps=args.steps, size=args.size, family=args.family, options=names,
                     rounds=args.rounds,
                     progress=lambda m: print(m, flush=True), on_option=write)
    write(result)
    print("wall seconds (contended on a shared machine):")
    print(table(result))
    print("CPU seconds of this process (steadier under contention; / threads ~ an idle machine's wall time):")
    print(table(result, cpu=True))
    cosines = {n: r["grad_cosine"] for n, r in result["options"].items() if "grad_cosine" in r}
    if cosines:
        print("guidance-gradient cosine with the fp32 UNet's, by t:")
        for n, c in cosines.items():
            print(f"  {n:<30}" + "  ".join(f"t={t}: {v:.4f}" for t, v in c.items()))
    print(f"wrote {out}")
    return 0
