"""`repaint-nerf train SCENE --workspace WS`: stage-1 reconstruction with a progress bar, checkpoints
(Ctrl-C stops cleanly and saves; --resume continues) and a final test PSNR."""
from __future__ import annotations

import argparse
import signal
import sys
import threading
from pathlib import Path

NAME = "train"
HELP = "reconstruct a scene (stage 1) into a workspace; prints progress and the final test PSNR"


def add_arguments(p: argparse.ArgumentParser) -> None:
    from repaint_nerf.app.commands.info import add_sharpness_argument

    p.add_argument("scene", help="dataset or photo folder (NeRF-synthetic, nerfstudio, LLFF, COLMAP)")
    p.add_argument("--workspace", required=True, help="workspace folder (created if missing or empty)")
    budget = p.add_mutually_exclusive_group()
    budget.add_argument("--steps", type=int, default=None, help="total training steps (a resumed run finishes them)")
    budget.add_argument("--seconds", type=float, default=None,
                        help="seconds the whole command may take: loading, training, saving and the closing "
                             "evaluation (default 120 when neither is given); what does not fit is skipped and said")
    p.add_argument("--downscale", type=float, default=1.0, help="image downscale factor (2 halves the size)")
    p.add_argument("--max-size", type=int, default=None, metavar="PX",
                   help="longest image side trained on: larger photos are loaded smaller (default 512; "
                        "the paper trains LLFF at 504x378; 0 = full size)")
    p.add_argument("--full-eval", action="store_true",
                   help="close with an evaluation of every pixel of every test view (default: a bounded one, "
                        "8 views x a 48x48 grid of pixels spread over each, whose cost does not grow with the image "
                        "size)")
    p.add_argument("--kind", default=None, choices=("bounded", "forward", "unbounded"),
                   help="scene kind (default: the dataset's, else detected from the camera layout)")
    add_sharpness_argument(p)
    p.add_argument("--appearance", action=argparse.BooleanOptionalAction, default=None,
                   help="a per-image appearance code (exposure, white balance), as nerfacto's; held-out views and "
                        "renders use the mean code (default: on for real captures, off for synthetic scenes)")
    p.add_argument("--resume", action="store_true", help="continue from the workspace's checkpoint")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--rays", type=int, default=None, help="rays per batch (default 4096, as in the paper)")
    p.add_argument("--lr", type=float, default=None,
                   help="Adam learning rate (default 1e-2, as in the paper; on a CPU the hash grid takes up to 3x it "
                        "for images over 256 px)")
    p.add_argument("--max-samples", type=int, default=None,
                   help="steps across the field cube's diagonal (default: 2 per pixel of the images, 128..256; a long run may ask 512 or 1024)")
    p.add_argument("--distortion", type=float, default=None, metavar="W",
                   help="weight of mip-NeRF 360's distortion loss, which gathers each ray's density into one surface "
                        "instead of a fog: fewer samples per ray, faster renders (default: 0.01 for forward-facing "
                        "scenes, else 0 = off; docs/ARCHITECTURE.md has the figures)")
    p.add_argument("--no-features", action="store_true",
                   help="skip the semantic feature field (faster; the workspace then cannot be selected in)")
    p.add_argument("--no-depth", action="store_true", help="skip the sparse depth priors")
    p.add_argument("--feature-model", default=None, metavar="MODEL",
                   help="dense feature teacher: an ONNX export (LSeg, CLIP-dense, DINO), a transformers folder or a "
                        "model id in the local Hugging Face cache (DINOv2, SigLIP, or CLIP: MaskCLIP features that "
                        "also select by text), 'efficientnet-lite0' (ImageNet features; pip install 'repaint-nerf[lite]'), "
                        "'efficientnet-lite0+default' (both blended) or 'default' for the built-in one (default: "
                        "the workspace's choice, else $REPAINT_NERF_FEATURE_MODEL, else built-in); nothing is "
                        "downloaded")
    p.add_argument("--feature-size", default=None, metavar="WxH",
                   help="the feature model's input size in pixels (default: ONNX each image's own size; "
                        "transformers the model's image size on the short side, aspect kept, patch multiples)")
    p.add_argument("--feature-norm", default=None, choices=("imagenet", "clip"),
                   help="an ONNX feature model's input mean/std (default imagenet; clip for CLIP-space models); "
                        "transformers models bring their own")
    p.add_argument("--depth-model", default=None, metavar="MODEL",
                   help="monocular depth model aligned to the sparse depth: an ONNX export (MiDaS-style), a "
                        "transformers DPT / Depth Anything folder or cached model id, or 'none' (default: the "
                        "workspace's choice, else $REPAINT_NERF_DEPTH_MODEL, else sparse only)")
    p.add_argument("--checkpoint-every", type=float, default=120.0, help="seconds between checkpoints (0 = at the end)")
    p.add_argument("--device", default=None, help="cpu, cuda, cuda:1 (default: $REPAINT_NERF_DEVICE, else CUDA if present)")


def _positive(name: str, value, allow_none=True):
    from repaint_nerf.core.errors import UserError

    if value is None and allow_none:
        return
    if value is None or not value > 0:
        raise UserError(f"{name} must be positive, got {value}")


def parse_size(text: str | None, flag: str = "--feature-size") -> tuple[int, int] | None:
    """'WxH' -> (H, W) pixels (the order the teachers take); malformed or non-positive is a UserError."""
    import re

    from repaint_nerf.core.errors import UserError

    if text is None:
        return None
    m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", str(text))
    if not m or int(m.group(1)) <= 0 or int(m.group(2)) <= 0:
        raise UserError(f"{flag} '{text}' is not WIDTHxHEIGHT in positive pixels",
                        hint=f"give the model's input size, e.g. {flag} 384x384")
    return int(m.group(2)), int(m.group(1))


def check_model_flags(args: argparse.Namespace) -> None:
    """Fail on a missing --feature-model / --depth-model (file, folder or cached id) before any workspace is
    touched; a broken one fails when its teacher loads, also before the workspace changes."""
    from repaint_nerf.core.models.paths import locate_model, model_type
    from repaint_nerf.core.models.depth import check_depth_model
    from repaint_nerf.core.models.vision import check_backbone
    from repaint_nerf.core.teachers.stage1_targets import NAMED_FEATURES, NO_DEPTH_MODEL, named_feature_teacher

    if args.feature_model in NAMED_FEATURES and not args.no_features:
        named_feature_teacher(args.feature_model)  # the lite ones: a missing package names the pip command
    elif args.feature_model and not args.no_features:
        path = locate_model("feature", args.feature_model)
        if model_type(path) != "onnx":
            check_backbone(path)
    if args.depth_model and args.depth_model != NO_DEPTH_MODEL and not args.no_depth:
        path = locate_model("depth", args.depth_model)
        if model_type(path) != "onnx":
            check_depth_model(path)


def run(args: argparse.Namespace) -> int:
    from repaint_nerf.core.errors import SceneError
    from repaint_nerf.core.scene.loaders.common import DEFAULT_MAX_SIZE, check_max_size
    from repaint_nerf.core.session import LoadAs, Teachers, start_reconstruction
    from repaint_nerf.core.train.budget import CommandBudget
    from repaint_nerf.core.train.progress import ProgressBar
    from repaint_nerf.core.train.stage1 import TrainConfig, check_distortion_weight

    scene_path = Path(args.scene)
    if not scene_path.exists():
        raise SceneError("no such scene folder", scene_path, hint="pass a dataset or photo folder")
    for name in ("--steps", "--seconds", "--rays", "--lr", "--max-samples"):
        _positive(name, getattr(args, name[2:].replace("-", "_")))
    seconds = args.seconds if args.seconds is not None or args.steps is not None else 120.0
    budget = CommandBudget(None if args.steps else seconds)
    max_size = check_max_size(DEFAULT_MAX_SIZE if args.max_size is None else args.max_size)
    feature_size = parse_size(args.feature_size)
    check_model_flags(args)
    cfg = TrainConfig(seed=args.seed, checkpoint_every_s=args.checkpoint_every)
    if args.rays:
        cfg.rays_per_batch = args.rays
    if args.lr:
        cfg.lr = args.lr
    if args.max_samples:
        cfg.max_samples = args.max_samples
    if args.appearance is not None:
        cfg.appearance = "on" if args.appearance else "off"
    if args.distortion is not None:
        cfg.lambda_distortion = check_distortion_weight(args.distortion)
    teachers = Teachers(features=not args.no_features, depth=not args.no_depth,  # paper Eq. s1
                        feature_model=args.feature_model, feature_size=feature_size, feature_norm=args.feature_norm,
                        depth_model=args.depth_model)

    rec = start_reconstruction(scene_path, args.workspace, train_cfg=cfg, prefer_saved_config=False,
                               teachers=teachers, load_as=LoadAs(args.downscale, args.kind, max_size,
                                                                args.sharpness_discard), device=args.device,
                               resume=args.resume, at_current_version=False)
    scene, trainer = rec.scene, rec.trainer
    for note in rec.notes:
        print(note, file=sys.stderr)
    if args.resume:
        if rec.resumed:
            print(f"resumed at step {trainer.step_count} ({trainer.train_seconds:.0f} s trained)")
        else:
            print("no checkpoint to resume from; starting from scratch")
    train_s = budget.training_seconds()  # what loading left, less the closing reserve
    trained_before = trainer.train_seconds
    if train_s is not None:
        train_s = trainer.train_seconds + max(train_s, 1e-3)  # a total: a resumed run counts its past seconds
    trainer.plan(args.steps, train_s)
    n_img = len(scene.train)
    h, w = scene.train.images[0].shape[:2]
    print(f"scene {scene_path} ({scene.format}): {n_img} training images {w}x{h}; device {trainer.device}")
    if budget.bounded:
        print(f"--seconds {seconds:g}: {budget.elapsed():.1f} s loading, {train_s - trainer.train_seconds:.1f} s "
              f"training, the rest saving and evaluating")

    stop = threading.Event()
    interrupted = {"n": 0}

    def on_sigint(signum, frame):
        interrupted["n"] += 1
        if interrupted["n"] > 1:
            raise KeyboardInterrupt
        stop.set()

    bar = ProgressBar(total_steps=args.steps, total_seconds=None if args.steps else train_s)
    ema = {"psnr": None, "dt": 0.0}

    def on_step(info):
        ema["dt"] = info["seconds"]
        p = info["psnr"]
        ema["psnr"] = p if ema["psnr"] is None else 0.9 * ema["psnr"] + 0.1 * p
        bar.update(info["step"], ema["psnr"], info["loss"])

    in_main = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGINT, on_sigint) if in_main else None
    try:
        # under --seconds no step starts that the last one's duration says would end past the allotment
        trainer.train(steps=args.steps, seconds=train_s, callback=on_step,
                      stop=lambda: stop.is_set() or (train_s is not None and trainer.step_count > 0
                                                     and trainer.train_seconds + ema["dt"] > train_s))
    finally:
        if in_main:
            signal.signal(signal.SIGINT, previous)
        bar.close(trainer.step_count, ema["psnr"])
    path = trainer.save_checkpoint()
    pending = trainer.feature_stream
    if pending is not None:  # a run shorter than the teacher: what it made stays cached for --resume
        trainer.close()
        print(f"teacher features reached {pending.received} of {len(pending)} views during training; "
              f"a --resume run distils the rest", file=sys.stderr)
    if stop.is_set():
        print(f"stopped at step {trainer.step_count}; checkpoint saved to {path}\n"
              f"continue with: repaint-nerf train {args.scene} --workspace {args.workspace} --resume", file=sys.stderr)
        return 130
    version = trainer.save_version("reconstruction")
    print(f"trained {trainer.step_count} steps in {trainer.train_seconds:.1f} s "
          f"({trainer.step_count / max(trainer.train_seconds, 1e-9):.1f} steps/s); saved version {version.id}")
    closing_evaluation(trainer, budget, args.full_eval, trainer.train_seconds - trained_before)
    return 0


def closing_evaluation(trainer, budget, full: bool, trained_s: float | None = None) -> dict | None:
    """The closing test evaluation within the command's budget: bounded by default, and to EVAL_SHARE of the
    `trained_s` seconds this command trained (its grid and views sized from the training step's time); the full
    one when asked and when its estimate (from the bounded one's seconds per pixel) fits. Prints what it did or
    skipped."""
    from repaint_nerf.core.train.budget import EVAL_SHARE
    from repaint_nerf.core.train.stage1 import EVAL_GRID

    if budget.left() <= 0:
        print(budget.skip("the closing evaluation"), file=sys.stderr)
        return None
    allowed = None if trained_s is None else budget.evaluation_seconds(trained_s)
    by_share = allowed is not None and allowed < budget.left()  # else the --seconds budget is the tighter limit
    ev = trainer.evaluate(with_ssim=True, deadline=budget.deadline(), seconds=allowed)
    _print_eval(ev)
    grid = ev.get("grid") or EVAL_GRID
    if ev["skipped_views"] or grid < EVAL_GRID:
        what = f"{ev['skipped_views']} of the evaluation's {ev['views'] + ev['skipped_views']} views"
        if grid < EVAL_GRID:
            what += f" and all but a {grid}x{grid} grid of each view's {EVAL_GRID}x{EVAL_GRID} pixels"
        print(f"skipped {what}: the closing evaluation takes at most {EVAL_SHARE:.0%} of the training time "
              f"({allowed:.1f} s of {trained_s:.1f} s)" if by_share else budget.skip(what), file=sys.stderr)
    if full:
        cams = trainer.scene.field_cameras(ev["split"])
        total_px = float((cams.width * cams.height).sum())
        estimate = ev["seconds"] / max(1, ev["pixels"]) * total_px * 2.0  # no sample cap there: say twice
        if budget.fits(estimate):
            ev = trainer.evaluate(with_ssim=True, full=True, deadline=budget.deadline())
            _print_eval(ev)
        else:
            print(budget.skip(f"the full evaluation (about {estimate:.0f} s for {ev['views_total']} views)"),
                  file=sys.stderr)
    return ev


def _print_eval(ev: dict) -> None:
    what = (f"all pixels of {ev['views']} of {ev['views_total']} views" if ev["full"] else
            f"{ev['views']} of {ev['views_total']} views, {ev['pixels']} pixels spread over them (--full-eval for all)")
    print(f"{ev['split']} PSNR {ev['psnr']:.2f} dB, SSIM {ev['ssim']:.4f} over {what}; {ev['seconds']:.1f} s")
