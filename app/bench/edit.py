"""`repaint-nerf bench edit`: the CLI driver of core.bench.edit (options, printing, the JSON file).

Reports first, as "drift", the repaint under a drifting guidance with the default settings (the case that
matches Stable Diffusion), then the exact analytic guidance, the lambda_unmask ablations and the offline edits.
"""
from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

HELP = ("edit quality: under a drifting guidance with the default settings first, then masked PSNR vs the edited "
        "ground truth, unmasked PSNR vs the original, lambda_unmask ablations, recolour and remove")


def add_arguments(p: argparse.ArgumentParser) -> None:
    from repaint_nerf.core.bench.edit import ABLATION
    from repaint_nerf.core.repaint.objective import UNMASK_REDUCTIONS

    p.add_argument("--scene", default=None, help="scene folder with gt/ and edited/ (default: generate --preset)")
    p.add_argument("--preset", default="demo", help="synthetic preset to generate when no --scene is given")
    p.add_argument("--size", type=int, default=64, help="generated image size")
    p.add_argument("--views", type=int, default=40, help="generated training views")
    p.add_argument("--test-views", type=int, default=8)
    p.add_argument("--stage1-steps", type=int, default=1500)
    p.add_argument("--rays", type=int, default=None, help="stage-1 rays per batch (default: the trainer's)")
    p.add_argument("--steps", type=int, default=None,
                   help="edit steps of the main run (default: the repaint default, what a user's edit runs)")
    p.add_argument("--ablation-steps", type=int, default=None,
                   help="edit steps of the drift run and each ablation run (default --steps)")
    p.add_argument("--evals", type=int, default=6, help="evaluations along the drift run and the main run")
    p.add_argument("--optimizer", default=None, choices=("paper", "official"),
                   help="optimiser preset (default: RepaintConfig's)")
    p.add_argument("--unmask-reduction", choices=UNMASK_REDUCTIONS, default=None,
                   help="Eq. unmask summed over rays (the paper) or averaged over the image (the official code); "
                        "default: RepaintConfig's")
    p.add_argument("--lambda-unmask", type=float, default=None, help="default: RepaintConfig's")
    p.add_argument("--ablation-lambdas", default=",".join(f"{x:g}" for x in ABLATION),
                   help="comma-separated lambda_unmask values of the ablations")
    p.add_argument("--no-ablation", action="store_true")
    p.add_argument("--no-offline", action="store_true", help="skip recolour and remove")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", required=True, help="output JSON path")
    p.add_argument("--device", default=None)


def run(args: argparse.Namespace) -> int:
    from repaint_nerf.core.bench.edit import EditBenchOptions, measure

    opts = EditBenchOptions(
        scene=args.scene, preset=args.preset, size=args.size, views=args.views, test_views=args.test_views,
        stage1_steps=args.stage1_steps, rays=args.rays, steps=args.steps, ablation_steps=args.ablation_steps,
        evals=args.evals, optimizer=args.optimizer, unmask_reduction=args.unmask_reduction,
        lambda_unmask=args.lambda_unmask, ablation=not args.no_ablation,
        ablation_lambdas=tuple(float(x) for x in args.ablation_lambdas.split(",") if x.strip()),
        offline=not args.no_offline, seed=args.seed, device=args.device, log=lambda s: print(s, flush=True))
    with tempfile.TemporaryDirectory() as tmp:
        result = measure(opts, Path(tmp))
    out = Path(args.json)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2, default=float))
    d = result["drift"]
    print(f"drift {d['drift']:g}, defaults ({d['unmask_reduction']}, lambda_unmask {d['lambda_unmask']:g}, "
          f"{d['optimizer']}): masked {d['psnr_masked']:.2f} dB, unmasked {d['psnr_unmasked']:.2f} dB "
          f"(drop {d['unmasked_drop_db']:.2f} dB) -> {'ok' if d['ok'] else 'NOT ok'}")
    print(f"  drop within {d['border_px']} px of the object {d['border']['drop_db']:.2f} dB, beyond "
          f"{d['beyond_border']['drop_db']:.2f} dB; masked dB along the edit: "
          + ", ".join(f"{r['step']}: {r['psnr_masked']:.2f}" for r in d["curve"]))
    f, b = result["final"], result["before"]
    print(f"exact guidance: masked {f['psnr_masked']:.2f} dB (from {b['psnr_masked']:.2f}), unmasked "
          f"{f['psnr_unmasked']:.2f} dB (from {b['psnr_unmasked']:.2f})")
    tables = [("lambda_unmask | masked dB | unmasked dB", result["ablation"])]
    if "ablation_drift" in result:
        tables.append((f"with the guidance's background drifted {result['ablation_drift']['drift']:g} toward a tint:",
                       result["ablation_drift"]["rows"]))
    for title, rows in tables:
        if rows:
            print(title)
            for row in rows:
                print(f"{row['lambda_unmask']:>13g} | {row['psnr_masked']:9.2f} | {row['psnr_unmasked']:11.2f}")
    for kind, r in result["offline"].items():
        print(f"{kind}: unmasked drop {r['unmasked_drop_db']:.2f} dB outside its mask "
              f"({r['unmasked_drop_db_gt']:.2f} dB outside the true object), {r['seconds_per_step']:.3f} s/step")
    print(f"wrote {out}")
    return 0
