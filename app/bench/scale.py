"""`repaint-nerf bench scale`: the driver of core/bench/scale.py (stage-1 cost against the image size): generates
the scene when none is given, prints a table, writes the JSON and a plot beside it."""
from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

from repaint_nerf.core.bench.scale import DENSE_UNTIL, TARGETS, measure

HELP = "cost against image size: time to target PSNRs, steps/s, samples per ray, render ms, evaluation, peak RSS"


def _sizes(text: str) -> list[int]:
    from repaint_nerf.core.errors import UserError

    try:
        sizes = [int(s) for s in str(text).split(",") if s.strip()]
    except ValueError:
        sizes = []
    if not sizes or any(s < 8 for s in sizes):
        raise UserError(f"--sizes must be a comma-separated list of pixel sizes >= 8, got {text!r}",
                        hint="e.g. --sizes 128,256,512")
    return sizes


def _targets(text: str) -> tuple[float, ...]:
    from repaint_nerf.core.errors import UserError

    try:
        targets = tuple(sorted(float(t) for t in str(text).split(",") if t.strip()))
    except ValueError:
        targets = ()
    if not targets or any(not 0 < t < 100 for t in targets):
        raise UserError(f"--targets must be a comma-separated list of PSNRs in dB, got {text!r}",
                        hint="e.g. --targets 25,30; a real capture that never reaches 30 dB: --targets 22,24")
    return targets


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scene", default=None, help="scene folder in any supported layout (default: generate --preset)")
    p.add_argument("--preset", default="demo", help="synthetic preset to generate when no --scene is given")
    p.add_argument("--size", type=int, default=None, help="generated image size (default: the largest of --sizes)")
    p.add_argument("--views", type=int, default=100, help="generated training views")
    p.add_argument("--test-views", type=int, default=20, help="generated test views")
    p.add_argument("--sizes", default="128,256,512", help="long sides to load the scene at (comma-separated)")
    p.add_argument("--targets", default=",".join(f"{t:g}" for t in TARGETS),
                   help="test PSNRs (dB) to time, comma-separated; the size ratios are read at the highest")
    p.add_argument("--seconds", type=float, default=60.0, help="training budget per size (evaluation not counted)")
    p.add_argument("--evals", type=int, default=12, help="test evaluations along each size's training")
    p.add_argument("--dense-until", type=int, default=DENSE_UNTIL,
                   help="also evaluate every second of the first this many training seconds (0: only --evals)")
    p.add_argument("--early-seconds", type=float, default=30.0, help="training seconds counted as early steps")
    p.add_argument("--rays", type=int, default=None, help="rays per batch (default: the trainer's)")
    p.add_argument("--early-max-samples", type=int, default=None,
                   help="training's early march budget (default: the trainer's; 0 = off, the full budget from step 0)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--in-process", action="store_true",
                   help="run every size in this process (peak RSS is then cumulative)")
    p.add_argument("--json", required=True, help="output JSON path (the plot goes beside it, .png)")
    p.add_argument("--device", default=None)


def plot(result: dict, path: Path) -> None:
    """Left: test PSNR against training seconds per size. Right: time to each target and steps/s against size."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4.2), dpi=110)
    for e in result["sizes"]:
        c = e["curve"]
        line, = a.plot([p["seconds"] for p in c], [p["psnr"] for p in c], "o-", ms=3, label=f"{e['size']} px")
        if e.get("content_size"):
            a.plot([p["seconds"] for p in c], [p["psnr_content"] for p in c], "--", color=line.get_color(), lw=1,
                   label=f"{e['size']} px on the {e['content_size']}-px images")
    targets = result.get("targets") or TARGETS
    for t in targets:
        a.axhline(t, color="gray", lw=0.8, ls=":")
    a.set_xlabel("training seconds (evaluation excluded)")
    a.set_ylabel("test PSNR (dB, bounded evaluation)")
    a.set_title(result["scene"]["name"])
    a.grid(alpha=0.3)
    a.legend(loc="lower right")
    sizes = [e["size"] for e in result["sizes"]]
    for t, mark in zip(targets, ("o-", "s-", "D-", "^-", "v-") * len(targets)):
        pts = [(s, e.get(f"seconds_to_{t:g}")) for s, e in zip(sizes, result["sizes"])]
        pts = [p for p in pts if p[1] is not None]
        if pts:
            b.plot(*zip(*pts), mark, label=f"s to {t:g} dB")
    b.set_xscale("log", base=2)
    b.set_xlabel("long side (px)")
    b.set_ylabel("seconds")
    b.grid(alpha=0.3)
    r = b.twinx()
    r.plot(sizes, [e["steps_per_s_early"] or 0 for e in result["sizes"]], "^--", color="C3", label="steps/s early")
    r.plot(sizes, [e["steps_per_s"] or 0 for e in result["sizes"]], "v--", color="C4", label="steps/s later")
    r.set_ylabel("steps/s")
    h1, l1 = b.get_legend_handles_labels()
    h2, l2 = r.get_legend_handles_labels()
    b.legend(h1 + h2, l1 + l2, loc="upper left", fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)


def _fmt(v, spec: str = ".1f") -> str:
    return "-" if v is None else format(v, spec)


def run(args: argparse.Namespace) -> int:
    from repaint_nerf.core.errors import UserError
    from repaint_nerf.core.workspace import atomic

    sizes = _sizes(args.sizes)
    targets = _targets(args.targets)
    if not args.seconds > 0:
        raise UserError(f"--seconds must be positive, got {args.seconds}")
    if args.evals < 1:
        raise UserError(f"--evals must be at least 1, got {args.evals}")
    if args.dense_until < 0:
        raise UserError(f"--dense-until must be 0 or more seconds, got {args.dense_until}")
    tmp = None
    if args.scene:
        scene_path = Path(args.scene)
    else:
        from repaint_nerf.core.synth.generate import make_scene

        size = args.size or max(sizes)
        tmp = tempfile.TemporaryDirectory(prefix="repaint-nerf-bench-")
        print(f"generating preset '{args.preset}' ({args.views} views, {size}px) ...")
        scene_path = make_scene(args.preset, Path(tmp.name) / args.preset, size=size, views=args.views,
                                seed=args.seed, test_views=args.test_views)
    heads = "".join(f" {'s->' + format(t, 'g'):>7}" for t in targets)
    heads += "".join(f" {'s->' + format(t, 'g') + '@' + str(min(sizes)):>11}" for t in targets)
    print(f"{'size':>5}{heads} {'ceiling':>7} {'st/s 0-30':>9} {'st/s':>6} {'spr':>6} {'render ms':>9} "
          f"{'eval s':>7} {'train s':>7} {'RSS MB':>7} {'PSNR':>6}", flush=True)

    out = Path(args.json)
    done: list[dict] = []

    def progress(e: dict) -> None:
        done.append(e)
        atomic.write_json(out, {"sizes": done, "partial": True})  # a long run keeps what it measured
        times = "".join(f" {_fmt(e[f'seconds_to_{t:g}']):>7}" for t in targets)
        times += "".join(f" {_fmt(e.get(f'seconds_to_{t:g}_content')):>11}" for t in targets)
        print(f"{e['size']:5d}{times} {_fmt(e.get('detail_ceiling_psnr'), '.2f'):>7} "
              f"{_fmt(e['steps_per_s_early'], '.2f'):>9} {_fmt(e['steps_per_s'], '.2f'):>6} "
              f"{_fmt(e['samples_per_ray']):>6} {e['render_ms']:9.0f} {e['eval_seconds']:7.2f} "
              f"{e['train_seconds']:7.1f} {e['peak_rss_mb']:7.0f} {e['final_psnr']:6.2f}", flush=True)

    try:
        result = measure(scene_path, sizes, args.seconds, args.evals, args.seed, args.device, args.rays,
                         args.early_seconds, args.early_max_samples, isolate=not args.in_process,
                         progress=progress, targets=targets, dense_until=args.dense_until)
    finally:
        if tmp is not None:
            tmp.cleanup()
    result["scene"].update(generated=tmp is not None, preset=None if args.scene else args.preset)
    atomic.write_json(out, result)
    png = out.with_suffix(".png")
    plot(result, png)
    print(f"PSNR: {result['psnr_measured']}")
    if len(sizes) > 1:
        print(f"s->T@{min(sizes)}: the same field scored on the {min(sizes)}-px images (the content every size holds); "
              f"ceiling: the {min(sizes)}-px images resized to the size, scored against its own (detail they lack)")
    print(f"wrote {out} and {png}")
    return 0
