"""`repaint-nerf bench recon`: the driver of core/bench/recon.py (stage-1 reconstruction speed): generates the
scene when none is given, prints the curve and figures, writes the JSON and an optional plot."""
from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

from repaint_nerf.core.bench.recon import NERFACTO, REPORT_AT, TARGET_PSNR, measure

HELP = "reconstruction speed: test PSNR against seconds, render time, samples per ray, step-time breakdown"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scene", default=None, help="scene folder in any supported layout (default: generate --preset)")
    p.add_argument("--preset", default="demo", help="synthetic preset to generate when no --scene is given")
    p.add_argument("--size", type=int, default=128, help="generated image size (pixels)")
    p.add_argument("--views", type=int, default=100, help="generated training views")
    p.add_argument("--test-views", type=int, default=20, help="generated test views")
    p.add_argument("--downscale", type=float, default=1.0)
    p.add_argument("--kind", choices=("bounded", "forward", "unbounded"), default=None,
                   help="scene kind (default: the dataset's, else detected from the camera layout), as train --kind")
    p.add_argument("--seconds", type=float, default=60.0, help="training time budget (evaluation not counted)")
    p.add_argument("--evals", type=int, default=12, help="evenly spaced test evaluations along the run")
    p.add_argument("--report-at", default=",".join(f"{t:g}" for t in REPORT_AT),
                   help="training seconds at which to report test PSNR and SSIM (comma-separated)")
    p.add_argument("--no-minute-curve", action="store_true",
                   help="skip the first-minute curve (evaluations at 10, 20, ..., 60 s)")
    p.add_argument("--holdout-every", type=int, default=None,
                   help="a capture without its own test split holds out views 0, N, 2N, ... (default 8, as "
                        "nerfstudio and instant-ngp); synthetic scenes keep their test split")
    p.add_argument("--eval-views", type=int, default=None, help="test views per evaluation (default: all)")
    p.add_argument("--rays", type=int, default=None, help="rays per batch (default: the trainer's)")
    p.add_argument("--lr", type=float, default=None)
    p.add_argument("--distortion", type=float, default=None, metavar="W",
                   help="distortion loss weight, as train --distortion (default: the trainer's)")
    p.add_argument("--as-train", action="store_true",
                   help="train what the train command trains: colour plus the default teacher's features and depth "
                        "priors (default: colour alone, as nerfacto and instant-ngp)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--profile-steps", type=int, default=8, help="extra profiled steps for the breakdown")
    p.add_argument("--json", required=True, help="output JSON path")
    p.add_argument("--plot", default=None, help="output PNG plot of PSNR against seconds")
    p.add_argument("--device", default=None)


def plot(result: dict, path: Path) -> None:
    """PSNR against training seconds, with the target and nerfacto's points."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.2), dpi=110)
    c = result["curve"]
    ax.plot([p["seconds"] for p in c], [p["psnr"] for p in c], "o-", label="repaint-nerf stage 1")
    ref = result["reference"]["nerfacto"]["curve"]
    ax.plot([p["seconds"] for p in ref], [p["psnr"] for p in ref], "s--", color="gray", label="nerfacto (issue 3, measured elsewhere)")
    ax.axhline(TARGET_PSNR, color="red", lw=0.8, ls=":", label=f"{TARGET_PSNR} dB")
    ax.set_xlabel("training seconds (evaluation excluded)")
    ax.set_ylabel("test PSNR (dB)")
    ax.set_title(f"{result['scene']['name']}: {result['final']['psnr']:.2f} dB after {result['final']['seconds']:.0f} s")
    ax.grid(alpha=0.3)
    ax.legend(loc="lower right")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)


def report_times(text: str) -> tuple[float, ...]:
    """--report-at "60,120,300" as positive seconds; a clear error otherwise."""
    from repaint_nerf.core.errors import UserError

    try:
        times = tuple(float(t) for t in text.split(",") if t.strip())
    except ValueError:
        times = ()
    if not times or any(not t > 0 for t in times):
        raise UserError(f"--report-at takes positive training seconds separated by commas, got {text!r}",
                        hint="e.g. --report-at 60,120,300")
    return times


def run(args: argparse.Namespace) -> int:
    from repaint_nerf.core.errors import UserError
    from repaint_nerf.core.workspace import atomic

    if not args.seconds > 0:
        raise UserError(f"--seconds must be positive, got {args.seconds}")
    report_at = report_times(args.report_at)
    tmp = None
    if args.scene:
        scene_path = Path(args.scene)
    else:
        from repaint_nerf.core.synth.generate import make_scene

        tmp = tempfile.TemporaryDirectory(prefix="repaint-nerf-bench-")
        print(f"generating preset '{args.preset}' ({args.views} views, {args.size}px) ...")
        scene_path = make_scene(args.preset, Path(tmp.name) / args.preset, size=args.size, views=args.views,
                                seed=args.seed, test_views=args.test_views)

    def progress(p: dict) -> None:
        if p["step"] == 0:
            print(f"step 0: test PSNR {p['psnr']:.2f} dB")
        else:
            print(f"{p['seconds']:7.1f} s  step {p['step']:6d}  test PSNR {p['psnr']:.2f} dB")

    try:
        result = measure(scene_path, args.seconds, args.evals, args.eval_views, args.rays, args.lr, args.seed,
                         args.profile_steps, args.downscale, args.device, progress, args.holdout_every, report_at,
                         not args.no_minute_curve, kind=args.kind, distortion=args.distortion,
                         as_train=args.as_train)
        result["scene"].update(generated=tmp is not None, preset=None if args.scene else args.preset)
        out = Path(args.json)
        atomic.write_json(out, result)
        if args.plot:
            plot(result, Path(args.plot))
    finally:
        if tmp is not None:
            tmp.cleanup()
    fin, t25, bd = result["final"], result["seconds_to_25_4"], result["breakdown"]
    ev = result["evaluation"]
    print(f"held out: {result['scene']['test_views']} {ev['split']} views ({(ev['holdout'] or {}).get('rule')}); "
          f"{result['scene']['train_views']} trained on; appearance: {ev['appearance']}")
    trains = result["trains"]
    print("trains: " + (trains if isinstance(trains, str) else
                        f"{trains['as']}; features of {trains['features']}, depth priors: "
                        f"{trains['depth_priors'] or 'none'} ({trains['depth_priors_s']:.1f} s before training)"))
    for t, pt in result["at"].items():
        print(f"at {t} s: " + ("beyond the budget" if pt is None else
                               f"test PSNR {pt['psnr']:.2f} dB, SSIM {pt['ssim']:.4f} (step {pt['step']})"))
    print(f"final: test PSNR {fin['psnr']:.2f} dB, SSIM {fin['ssim']:.4f}, "
          f"{fin['steps']} steps in {fin['seconds']:.1f} s ({result['steps_per_s']:.2f} steps/s)")
    print(f"time to {TARGET_PSNR} dB: " + ("not reached" if t25 is None else f"{t25:.1f} s "
          f"(nerfacto ~{NERFACTO['seconds_to_25_4']:.0f} s, a figure measured elsewhere: issue 3)"))
    sp = result["samples_per_ray"]
    print(f"render 128x128: {result['render_ms_128']:.1f} ms; samples/ray {sp['with_grid']:.1f} with grid, "
          f"{sp['without_grid']:.1f} without; peak RSS {result['peak_rss_mb']:.0f} MB")
    fog = result["fog"]
    if fog["ratio"] is not None:
        print(f"first {fog['first_steps']} steps: {fog['first_mean_ms']:.0f} ms each, {fog['ratio']:.2f}x a later step "
              f"({fog['later_median_ms']:.0f} ms)")
    print(f"step breakdown ({bd['step_ms']:.1f} ms/step):")
    for k, v in sorted(bd["fraction"].items(), key=lambda kv: -kv[1]):
        print(f"  {k:13s} {100 * v:5.1f}%  {bd['ms'][k]:8.2f} ms")
    print(f"wrote {out}" + (f" and {args.plot}" if args.plot else ""))
    return 0
