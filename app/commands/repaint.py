"""`repaint-nerf repaint WS --prompt ... --guidance sd|recolor|remove|analytic`: edit the workspace's current
selection (paper stage 2) and save the result as a new version (undo goes back to the previous one)."""
from __future__ import annotations

import argparse
import signal
import sys
import threading

NAME = "repaint"
HELP = "repaint the selected region (stage 2) under a guidance and save it as a new workspace version"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("workspace", help="workspace folder with a trained field and a selection (`repaint-nerf select`)")
    p.add_argument("--prompt", default="", help="what the selection should become, e.g. 'a blue rose in leaves'")
    p.add_argument("--bg-prompt", default="", help="what the rest shows, e.g. 'leaves' (the CLIP background loss)")
    p.add_argument("--guidance", default="sd", choices=("sd", "recolor", "remove", "analytic"),
                   help="sd: Stable Diffusion score distillation; recolor / remove: offline, no model; "
                        "analytic: exact denoiser of a synthetic scene's edited/ variant (measurement)")
    p.add_argument("--sd-path", default=None, help="local Stable Diffusion folder or .safetensors "
                                                   "(else $REPAINT_NERF_SD_PATH)")
    p.add_argument("--clip-path", default=None, help="local CLIP folder (else $REPAINT_NERF_CLIP_PATH)")
    p.add_argument("--steps", type=int, default=None, help="edit steps (default 300 on CPU; the paper runs 10000)")
    p.add_argument("--lambda-unmask", type=float, default=100.0, help="weight of the unmask loss (paper: 100)")
    p.add_argument("--unmask-reduction", choices=("mean", "sum"), default="mean",
                   help="the unmask loss averaged over pixels (official code, default) or summed over rays (the "
                        "paper's Eq.; holds the background far more firmly at the same weight)")
    p.add_argument("--lambda-clip", type=float, default=None,
                   help="weight of the CLIP background loss (default 0.01 with --guidance sd, else 0; 0 loads no CLIP)")
    p.add_argument("--resolution", type=int, default=None,
                   help="render long side in pixels (default: training size, at most 128 on CPU / 400 on CUDA)")
    p.add_argument("--color", default=None, help="recolour target as R,G,B (0-255) or #rrggbb (default: a colour "
                                                 "named in the prompt)")
    p.add_argument("--optimizer", default="paper", choices=("paper", "official"),
                   help="paper: Adan 1e-3 -> 1e-4; official code: 5e-3 with 10x on the grid")
    p.add_argument("--lr", type=float, default=None, help="base learning rate (overrides the preset)")
    p.add_argument("--mask-dilation", type=int, default=0, help="pixels to grow the mask by")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--device", default=None, help="cpu, cuda, cuda:1 (default: $REPAINT_NERF_DEVICE, else CUDA if present)")


def check_args(args: argparse.Namespace) -> None:
    """Reject bad values with one clear message each (before anything is loaded)."""
    from core.errors import UserError

    if args.steps is not None and args.steps < 1:
        raise UserError(f"--steps must be at least 1, got {args.steps}")
    if args.lambda_unmask < 0:
        raise UserError(f"--lambda-unmask must not be negative, got {args.lambda_unmask}")
    if args.lambda_clip is not None and args.lambda_clip < 0:
        raise UserError(f"--lambda-clip must not be negative, got {args.lambda_clip}")
    if args.resolution is not None and args.resolution < 8:
        raise UserError(f"--resolution must be at least 8 pixels, got {args.resolution}")
    if args.mask_dilation < 0:
        raise UserError(f"--mask-dilation must not be negative, got {args.mask_dilation}")
    if args.guidance == "sd" and not args.prompt.strip():
        raise UserError("--prompt is empty", hint="say what the selection should become, e.g. --prompt 'a blue rose'")
    if args.guidance == "recolor" and args.color is None:
        from core.repaint.colors import resolve_color

        resolve_color(args.prompt, None)
    elif args.color is not None:
        from core.repaint.colors import resolve_color

        resolve_color("", args.color)


def open_workspace(path: str, device=None):
    """(workspace, scene, field, grid, masks) of a workspace's current version and its selection's masks."""
    from core.errors import WorkspaceError
    from core.select.masks import load_masks
    from core.session import open_trained, trained_path
    from core.workspace.workspace import Workspace

    ws = Workspace.open(path)
    trained_path(ws)  # no field: that error first
    if not (ws.masks_dir / "index.json").is_file():
        raise WorkspaceError("the workspace has no selection to repaint", ws.root,
                             hint=f"run `repaint-nerf select {ws.root} --view I --patch x0,y0,x1,y1` first")
    masks = load_masks(ws.masks_dir)
    t = open_trained(ws, device)
    return ws, t.scene, t.field, t.grid, masks


def run(args: argparse.Namespace) -> int:
    from core.repaint.trainer import RepaintConfig, RepaintTrainer

    check_args(args)
    lambda_clip = args.lambda_clip if args.lambda_clip is not None else (0.01 if args.guidance == "sd" else 0.0)
    if args.guidance == "sd":  # name a missing model before the field and scene load
        from core.models.paths import resolve_model_path
        from core.workspace.workspace import Workspace

        settings = Workspace.open(args.workspace).settings
        resolve_model_path("sd", args.sd_path, settings)
        if lambda_clip > 0:
            resolve_model_path("clip", args.clip_path, settings)
    ws, scene, field, grid, masks = open_workspace(args.workspace, args.device)
    cfg = RepaintConfig(lambda_unmask=args.lambda_unmask, unmask_reduction=args.unmask_reduction,
                        lambda_clip=lambda_clip, resolution=args.resolution,
                        optimizer=args.optimizer, lr=args.lr, mask_dilation=args.mask_dilation, seed=args.seed)
    if args.steps is not None:
        cfg.steps = args.steps
    trainer = RepaintTrainer(scene, field, grid, workspace=ws, masks=masks, guidance=args.guidance,
                             prompt=args.prompt, bg_prompt=args.bg_prompt, config=cfg, sd_path=args.sd_path,
                             clip_path=args.clip_path, color=args.color)
    h, w = trainer.size
    print(f"repaint ({trainer.kind}) of {sum(int(m.any()) for m in masks)}/{len(masks)} masked views at {w}x{h}, "
          f"{cfg.steps} steps on {trainer.device}")

    stop = threading.Event()

    def on_sigint(signum, frame):
        if stop.is_set():
            raise KeyboardInterrupt
        stop.set()
        trainer.cancel()

    def on_step(info):
        n = info["step"]
        if n == 1 or n % max(1, cfg.steps // 20) == 0 or info.get("done"):
            parts = " ".join(f"{k} {info[k]:.4g}" for k in ("loss", "guidance", "unmask", "clip") if k in info)
            print(f"step {n}/{cfg.steps} {parts} ({trainer.train_seconds:.1f} s, {trainer.skipped_steps} skipped)",
                  flush=True)

    in_main = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGINT, on_sigint) if in_main else None
    try:
        trainer.run(callback=on_step)
    finally:
        if in_main:
            signal.signal(signal.SIGINT, previous)
    if trainer.cancelled:
        print("cancelled: the workspace is unchanged", file=sys.stderr)
        return 130
    print(f"saved version {trainer.version.id} ({trainer.version.name}); "
          f"{trainer.skipped_steps} non-finite steps skipped; undo returns to the previous version")
    return 0
