"""`repaint-nerf repaint WS --prompt ... --guidance sd|recolor|remove|analytic`: edit the workspace's current
selection (paper stage 2) and save the result as a new version (undo goes back to the previous one)."""
from __future__ import annotations

import argparse
import dataclasses
import signal
import sys
import threading

from repaint_nerf.core.repaint import registry
from repaint_nerf.core.repaint.config import OPTIMIZERS, UNMASK_REDUCTIONS, RepaintConfig

NAME = "repaint"
HELP = "repaint the selected region (stage 2) under a guidance and save it as a new workspace version"


# RepaintConfig fields the command sets from its flags (--lambda-unmask -> lambda_unmask); each flag defaults to
# the field's default, so the CLI, the editor and the benchmarks share one set of defaults.
CONFIG_FLAGS = ("steps", "lambda_unmask", "unmask_ramp", "unmask_ramp_start", "unmask_reduction", "lambda_clip",
                "resolution", "optimizer", "lr", "mask_dilation", "seed", "sd_unet_precision", "sd_tiny_autoencoder",
                "sd_channels_last", "sd_token_merging", "sds_resolution", "t_schedule", "sd_config", "sd_family",
                "sd_prediction_type")


def add_arguments(p: argparse.ArgumentParser) -> None:
    d = RepaintConfig()
    p.add_argument("workspace", help="workspace folder with a trained field and a selection (`repaint-nerf select`)")
    p.add_argument("--prompt", default="", help="what the selection should become, e.g. 'a blue rose in leaves'")
    p.add_argument("--bg-prompt", default="", help="what the rest shows, e.g. 'leaves' (the CLIP background loss)")
    p.add_argument("--guidance", default="sd", choices=tuple(registry.GUIDANCES), help=registry.help_text())
    p.add_argument("--sd-path", default=None, help="local Stable Diffusion folder, .safetensors/.ckpt "
                        "file, or a model id in the local Hugging Face cache (else $REPAINT_NERF_SD_PATH)")
    p.add_argument("--sd-config", dest="sd_config", default=d.sd_config,
                   help="diffusers config folder for a single-file checkpoint (default: the shipped config of the "
                        "family its weights show: SD 1.x, 2.x base or 2.x 768-v)")
    p.add_argument("--sd-family", dest="sd_family", default=d.sd_family, choices=("sd1", "sd2-base", "sd2-768-v"),
                   help="the single-file checkpoint's family when its name does not tell 2.x base from 768-v "
                        "(a name with '768' or 'v-pred' is read as 768-v, else base)")
    p.add_argument("--prediction-type", dest="sd_prediction_type", default=d.sd_prediction_type,
                   choices=("epsilon", "v_prediction"),
                   help="what the UNet predicts, when its scheduler config says otherwise or nothing "
                        "(SD 2.x 768 models: v_prediction)")
    p.add_argument("--clip-path", default=None, help="local CLIP folder (else $REPAINT_NERF_CLIP_PATH)")
    p.add_argument("--steps", type=int, default=d.steps,
                   help=f"edit steps (default {d.steps}; the paper runs 10000; the estimated time is printed first)")
    p.add_argument("--lambda-unmask", type=float, default=d.lambda_unmask,
                   help=f"weight of the unmask loss, paper Eq. s2 (default {d.lambda_unmask:g})")
    p.add_argument("--unmask-ramp", type=float, default=d.unmask_ramp, metavar="FRACTION",
                   help="the unmask weight rises linearly to --lambda-unmask over this fraction of the steps, from "
                        f"--unmask-ramp-start x it, so the edit moves first and the rest is held after (default "
                        f"{d.unmask_ramp:g}; 0 = constant, as the paper)")
    p.add_argument("--unmask-ramp-start", type=float, default=d.unmask_ramp_start, metavar="FRACTION",
                   help="the unmask weight's share of --lambda-unmask at the first step "
                        f"(default {d.unmask_ramp_start:g})")
    p.add_argument("--unmask-reduction", choices=UNMASK_REDUCTIONS, default=d.unmask_reduction,
                   help="Eq. unmask summed over rays as the paper writes it (sum), or averaged over the whole image "
                        "with the masked pixels zeroed as the official code does (mean: the sum / 3HW, so far weaker "
                        f"at the same weight); default {d.unmask_reduction}")
    clip_defaults = ", ".join(f"{s.clip_weight:g} with --guidance {s.name}" for s in registry.GUIDANCES.values()
                              if s.clip_weight > 0)
    p.add_argument("--lambda-clip", type=float, default=d.lambda_clip,
                   help=f"weight of the CLIP background loss (default {clip_defaults}, else 0; 0 loads no CLIP)")
    p.add_argument("--resolution", type=int, default=d.resolution,
                   help="render long side in pixels (default: training size, at most 128 on CPU / 400 on CUDA)")
    p.add_argument("--color", default=None, help="recolour target as R,G,B (0-255) or #rrggbb (default: a colour "
                                                 "named in the prompt)")
    p.add_argument("--optimizer", default=d.optimizer, choices=OPTIMIZERS,
                   help="Adan decaying x0.1 over the edit; paper: 1e-3 -> 1e-4; official code: 5e-3 -> 5e-4 with "
                        f"10x on the grid (default {d.optimizer})")
    p.add_argument("--lr", type=float, default=d.lr, help="base learning rate (overrides the preset)")
    p.add_argument("--mask-dilation", type=int, default=d.mask_dilation, help="pixels to grow the mask by")
    p.add_argument("--seed", type=int, default=d.seed)
    p.add_argument("--sd-precision", dest="sd_unet_precision", default=d.sd_unet_precision,
                   choices=("auto", "fp32", "bf16", "fp16"),
                   help="precision of Stable Diffusion's UNet (no gradient flows through it): auto = fp16 on CUDA, "
                        "bf16 on a CPU with native bf16 (avx512_bf16/AMX), else fp32")
    p.add_argument("--tiny-autoencoder", dest="sd_tiny_autoencoder", default=d.sd_tiny_autoencoder,
                   metavar="PATH_OR_ID",
                   help="a TAESD tiny autoencoder (local folder, or a model id in the Hugging Face cache such as "
                        "madebyollin/taesd) encoding the render instead of SD's VAE: a much cheaper step on a CPU, "
                        "approximate latents")
    p.add_argument("--no-channels-last", dest="sd_channels_last", action="store_false",
                   help="keep Stable Diffusion's UNet in PyTorch's default memory layout (channels-last, the "
                        "default, runs oneDNN's CPU convolutions without reorders: ~1.15x faster per step)")
    p.add_argument("--token-merging", dest="sd_token_merging", type=float, default=d.sd_token_merging,
                   metavar="RATIO",
                   help="merge this ratio of the tokens in the self-attention of Stable Diffusion's highest-resolution "
                        f"UNet blocks (ToMe for SD; 0 = off, at most 0.75; default {d.sd_token_merging:g})")
    p.add_argument("--t-schedule", default=d.t_schedule, choices=("uniform", "annealed"),
                   help="Stable Diffusion timestep draw: uniform over 2-98%% of T (official), or annealed: the "
                        "upper bound falls to 50%% of T over the run (detail late, for shorter runs)")
    p.add_argument("--sds-resolution", type=int, default=d.sds_resolution,
                   help="side in pixels Stable Diffusion sees the render at (default: the model's, 512); 256 makes "
                        "a step ~4x cheaper, with less detail")
    p.add_argument("--device", default=None, help="cpu, cuda, cuda:1 (default: $REPAINT_NERF_DEVICE, else CUDA if present)")


def config_from_args(args: argparse.Namespace) -> RepaintConfig:
    """The RepaintConfig the flags describe (RepaintConfig's defaults where no flag was given)."""
    return dataclasses.replace(RepaintConfig(), **{name: getattr(args, name) for name in CONFIG_FLAGS})


def check_args(args: argparse.Namespace) -> None:
    """Reject bad values with one clear message each (before anything is loaded)."""
    from repaint_nerf.core.errors import UserError

    if args.steps < 1:
        raise UserError(f"--steps must be at least 1, got {args.steps}")
    if args.lambda_unmask is not None and args.lambda_unmask < 0:
        raise UserError(f"--lambda-unmask must not be negative, got {args.lambda_unmask}")
    for flag, value in (("--unmask-ramp", args.unmask_ramp), ("--unmask-ramp-start", args.unmask_ramp_start)):
        if not 0.0 <= value <= 1.0:
            raise UserError(f"{flag} must lie between 0 and 1, got {value}")
    if args.lambda_clip is not None and args.lambda_clip < 0:
        raise UserError(f"--lambda-clip must not be negative, got {args.lambda_clip}")
    if args.resolution is not None and args.resolution < 8:
        raise UserError(f"--resolution must be at least 8 pixels, got {args.resolution}")
    if args.sds_resolution is not None and (args.sds_resolution < 64 or args.sds_resolution % 64):
        raise UserError(f"--sds-resolution must be a multiple of 64 pixels, got {args.sds_resolution}",
                        hint="use 256 (cheaper) or 512 (SD 1.5 / 2-base's own)")
    if args.mask_dilation < 0:
        raise UserError(f"--mask-dilation must not be negative, got {args.mask_dilation}")
    if registry.get(args.guidance).needs_prompt and not args.prompt.strip():
        raise UserError("--prompt is empty", hint="say what the selection should become, e.g. --prompt 'a blue rose'")
    from repaint_nerf.core.repaint.colors import resolve_color

    if args.color is not None:
        resolve_color("", args.color)
    elif registry.resolve(args.guidance, args.prompt).name == "recolor":  # also 'offline' read as a recolour
        resolve_color(args.prompt, None)


def open_workspace(path: str, device=None):
    """(workspace, scene, field, grid, masks, the field's sample budget (CheckpointHeader.trained_samples)) of a
    workspace's current version and its selection's masks."""
    from repaint_nerf.core.errors import WorkspaceError
    from repaint_nerf.core.select.masks import load_masks
    from repaint_nerf.core.session import open_trained, trained_path
    from repaint_nerf.core.workspace.workspace import Workspace

    ws = Workspace.open(path)
    trained_path(ws)  # no field: that error first
    if not (ws.masks_dir / "index.json").is_file():
        raise WorkspaceError("the workspace has no selection to repaint", ws.root,
                             hint=f"run `repaint-nerf select {ws.root} --view I --patch x0,y0,x1,y1` first")
    masks = load_masks(ws.masks_dir)
    t = open_trained(ws, device)
    return ws, t.scene, t.field, t.grid, masks, t.header.trained_samples


def run(args: argparse.Namespace) -> int:
    from repaint_nerf.core.repaint.estimate import format_duration
    from repaint_nerf.core.repaint.trainer import RepaintTrainer

    check_args(args)
    cfg = config_from_args(args)
    needed = registry.models_needed(args.guidance, cfg)
    if needed:  # name a missing model before the field and scene load
        from repaint_nerf.core.models.paths import resolve_model_path
        from repaint_nerf.core.workspace.workspace import Workspace

        settings = Workspace.open(args.workspace).settings
        for kind in needed:
            resolve_model_path(kind, {"sd": args.sd_path, "clip": args.clip_path}[kind], settings)
    ws, scene, field, grid, masks, samples = open_workspace(args.workspace, args.device)
    trainer = RepaintTrainer(scene, field, grid, workspace=ws, masks=masks, guidance=args.guidance,
                             prompt=args.prompt, bg_prompt=args.bg_prompt, config=cfg, sd_path=args.sd_path,
                             clip_path=args.clip_path, color=args.color, trained_samples=samples)
    h, w = trainer.size
    print(f"repaint ({trainer.kind}) of {sum(int(m.any()) for m in masks)}/{len(masks)} masked views at {w}x{h}, "
          f"{cfg.steps} steps on {trainer.device}")
    print(trainer.estimate().describe(), flush=True)

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
            print(f"step {n}/{cfg.steps} {parts} ({trainer.train_seconds:.1f} s, {trainer.skipped_steps} skipped, "
                  f"{format_duration(info.get('eta_s'))} left)", flush=True)

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
