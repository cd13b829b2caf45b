"""`repaint-nerf render WS --split test|train|turntable --out DIR`: PNGs of the workspace's current
version (optional depth colormaps); the turntable, or a nerfstudio camera path (`--camera-path FILE`), also as an
H.264 .mp4 (plays in browsers and chat tools) and, with --gif, a GIF."""
from __future__ import annotations

import argparse
from pathlib import Path

NAME = "render"
HELP = "render the workspace's current version for a split or a turntable into PNGs (and an mp4)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("workspace", help="workspace folder written by `repaint-nerf train`")
    p.add_argument("--split", default="test", choices=("test", "train", "turntable"))
    p.add_argument("--out", required=True, help="output folder for the PNGs (and turntable.mp4)")
    p.add_argument("--scale", type=float, default=1.0, help="resolution factor of the renders (0.5 = half size)")
    p.add_argument("--depth", action="store_true", help="also write z-depth as a colormap PNG per view")
    p.add_argument("--frames", type=int, default=60, help="turntable frames")
    p.add_argument("--fps", type=float, default=None, help="video frame rate (default 30, or the camera path's)")
    p.add_argument("--camera-path", default=None, metavar="FILE",
                   help="render along a nerfstudio camera_path.json (world units) instead of a split")
    p.add_argument("--gif", action="store_true", help="also write the video as a GIF")
    p.add_argument("--device", default=None, help="cpu, cuda, cuda:1 (default: $REPAINT_NERF_DEVICE, else CUDA if present)")


def depth_colormap(depth, lo: float | None = None, hi: float | None = None):
    """(H, W) depth -> uint8 (H, W, 3) RGB turbo colormap (near = red... far = blue), 2-98 percentile range."""
    import cv2
    import numpy as np

    d = np.asarray(depth, dtype=np.float32)
    fin = np.isfinite(d)
    if lo is None or hi is None:
        vals = d[fin] if fin.any() else np.zeros(1, np.float32)
        lo, hi = float(np.percentile(vals, 2)), float(np.percentile(vals, 98))
    t = np.clip((d - lo) / max(hi - lo, 1e-8), 0, 1)
    t[~fin] = 1.0
    bgr = cv2.applyColorMap((255 * (1 - t)).astype(np.uint8), cv2.COLORMAP_TURBO)
    return bgr[..., ::-1].copy()


def run(args: argparse.Namespace) -> int:
    import numpy as np
    import torch

    from repaint_nerf.app.camera_control import CameraControl
    from repaint_nerf.core.errors import UserError
    from repaint_nerf.core.render.renderer import render_camera
    from repaint_nerf.core.scene.cameras import Cameras
    from repaint_nerf.core.session import open_trained
    from repaint_nerf.core.train.metrics import psnr
    from repaint_nerf.core.train.stage1 import target_image

    if not args.scale > 0:
        raise UserError(f"--scale must be positive, got {args.scale}")
    if args.frames < 1:
        raise UserError(f"--frames must be at least 1, got {args.frames}")
    trained = open_trained(args.workspace, args.device)
    field, grid, scene = trained.field, trained.grid, trained.scene
    device = next(field.parameters()).device
    bg = torch.tensor(scene.background or (1.0, 1.0, 1.0), dtype=torch.float32, device=device)
    outputs = ("rgb", "depth") if args.depth else ("rgb",)
    opts = trained.render_options(outputs=outputs, background=bg, perturb=False)  # render as it was trained
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)

    import cv2

    video_name = "turntable" if args.split == "turntable" else None
    if args.camera_path:
        from repaint_nerf.core.export.camera_path import load_camera_path

        path = load_camera_path(args.camera_path)
        cams, images, video_name = path.cameras(scene.norm), None, "camera_path"
        args.split = "path"
        args.fps = args.fps or path.fps
    elif args.split == "turntable":
        train_cams = scene.field_cameras("train")
        ctl = CameraControl.framing(train_cams)  # orbit the point the training cameras look at
        w0, h0 = int(train_cams.width[0]), int(train_cams.height[0])
        start = ctl.yaw
        views = []
        for k in range(args.frames):
            ctl.yaw = start + 2 * np.pi * k / args.frames
            views.append(ctl.cameras(w0, h0))
        cams = Cameras.cat(views)
        images = None
    else:
        name = args.split if args.split in scene.splits else "train"
        if name != args.split:
            print(f"this scene has no {args.split} split; rendering train")
        cams = scene.field_cameras(name)
        images = scene.split(name).images
    cams = cams.to(device)
    frames, scores = [], []
    for i in range(len(cams)):
        with torch.no_grad():
            out = render_camera(field, grid, cams, i, opts, scale=args.scale)
        rgb = (out["rgb"].clamp(0, 1) * 255 + 0.5).byte().cpu().numpy()
        stem = f"{args.split}_{i:03d}"
        cv2.imwrite(str(out_dir / f"{stem}.png"), rgb[..., ::-1])
        frames.append(rgb)
        if args.depth:
            z = (out["depth"] / float(scene.norm.scale)).cpu().numpy()  # field units -> world units
            cv2.imwrite(str(out_dir / f"{stem}_depth.png"), depth_colormap(z)[..., ::-1])
        if images is not None and args.scale == 1.0:
            scores.append(psnr(out["rgb"].clamp(0, 1), target_image(images[i], bg)))
    print(f"wrote {len(frames)} PNGs to {out_dir}" + (f" (and depth colormaps)" if args.depth else ""))
    if scores:
        print(f"{args.split} PSNR {np.mean(scores):.2f} dB over {len(scores)} views")
    if video_name:
        from repaint_nerf.core.export.video import write_video

        for suffix in (".mp4", ".gif") if args.gif else (".mp4",):
            info = write_video(frames, out_dir / f"{video_name}{suffix}", args.fps or 30.0)
            print(f"wrote {info['path']} ({info['frames']} frames, {info['bytes'] / 1e3:.1f} kB)")
    return 0
