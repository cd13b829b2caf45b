"""Videos that play everywhere: H.264 in yuv420p (.mp4; browsers, chat tools and phones decode it) through
imageio-ffmpeg, which ships its own ffmpeg (no system install), and GIFs through imageio + Pillow for quick
sharing. Frames stream in (a generator of renders), the file is written atomically."""
from __future__ import annotations

from pathlib import Path
from typing import Iterable

import numpy as np

from repaint_nerf.core.errors import UserError
from repaint_nerf.core.export.common import atomic_output, check_output_file

VIDEO_SUFFIXES = (".mp4", ".gif")
MP4_QUALITY = 8  # imageio-ffmpeg's 0..10 scale (x264 crf ~ 18): small files, no visible blocking on renders


def even_size(frame: np.ndarray) -> np.ndarray:
    """Pad a frame by edge pixels to even width and height (yuv420p halves the chroma in both)."""
    h, w = frame.shape[:2]
    return np.pad(frame, ((0, h % 2), (0, w % 2), (0, 0)), mode="edge") if h % 2 or w % 2 else frame


def _rgb(frame) -> np.ndarray:
    f = np.asarray(frame)
    if f.dtype != np.uint8:
        f = (np.clip(f, 0, 1) * 255 + 0.5).astype(np.uint8)
    return np.ascontiguousarray(f[..., :3])


def _write_mp4(frames: Iterable, tmp: Path, fps: float) -> int:
    import imageio_ffmpeg

    writer, n, size = None, 0, None
    try:
        for frame in frames:
            f = even_size(_rgb(frame))
            if writer is None:
                size = (f.shape[1], f.shape[0])
                writer = imageio_ffmpeg.write_frames(str(tmp), size, fps=float(fps), codec="libx264",
                                                     pix_fmt_in="rgb24", pix_fmt_out="yuv420p", quality=MP4_QUALITY,
                                                     macro_block_size=1, ffmpeg_log_level="error",
                                                     output_params=["-f", "mp4", "-movflags", "+faststart"])
                writer.send(None)
            if (f.shape[1], f.shape[0]) != size:
                raise UserError(f"frame {n} is {f.shape[1]}x{f.shape[0]} px, the video's frames {size[0]}x{size[1]}")
            writer.send(f)
            n += 1
    finally:
        if writer is not None:
            writer.close()
    return n


def _write_gif(frames: Iterable, tmp: Path, fps: float) -> int:
    import imageio.v3 as iio

    frames = [_rgb(f) for f in frames]
    if frames:
        iio.imwrite(tmp, np.stack(frames), extension=".gif", duration=1000.0 / fps, loop=0)
    return len(frames)


def write_video(frames: Iterable, path: str | Path, fps: float = 30.0) -> dict:
    """Write frames (uint8 or float in [0, 1], (H, W, 3|4)) as H.264 .mp4 or .gif; returns path, frames, bytes."""
    path = check_output_file(path, VIDEO_SUFFIXES, "video")
    if not fps > 0:
        raise UserError(f"the frame rate must be positive, got {fps}")
    with atomic_output(path, "video") as tmp:
        n = (_write_gif if path.suffix.lower() == ".gif" else _write_mp4)(frames, tmp, fps)
        if n == 0:
            raise UserError("no frames to write", path, hint="give at least one camera")
    return {"path": str(path), "frames": n, "bytes": path.stat().st_size}
