"""Shared onnxruntime plumbing for the ONNX teachers: locate the model, open a session, prepare input.

Providers: CUDAExecutionProvider first when core.device says CUDA and onnxruntime has it, else CPU.
"""
from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np

from repaint_nerf.core.device import is_cuda
from repaint_nerf.core.errors import ModelNotFoundError


def resolve_model(path: str | Path | None, env: str, flag: str, what: str) -> Path:
    """The ONNX file from the argument or `env` (a file, a folder holding one, or a cached model id holding
    one; core.models.paths.locate_model); a missing one is a ModelNotFoundError naming both."""
    from repaint_nerf.core.models.paths import locate_model

    raw = path if path not in (None, "") else os.environ.get(env)
    hint = f"pass {flag} PATH.onnx or set {env} to a local .onnx file (nothing is downloaded)"
    if raw in (None, ""):
        raise ModelNotFoundError(f"no {what} model was given", hint=hint)
    p = locate_model(what, raw, f"the {flag} flag" if path not in (None, "") else f"${env}")
    if p.is_dir():
        found = sorted(p.glob("*.onnx"))
        if len(found) != 1:
            raise ModelNotFoundError(f"folder holds {len(found)} .onnx files; name one {what} model", p, hint)
        p = found[0]
    if not p.is_file():
        raise ModelNotFoundError(f"{what} model file not found", p, hint)
    return p


def open_session(path: Path, flag: str, env: str, what: str):
    """An onnxruntime InferenceSession; an unreadable file is a ModelNotFoundError naming the path."""
    import onnxruntime as ort

    providers = ["CPUExecutionProvider"]
    if is_cuda() and "CUDAExecutionProvider" in ort.get_available_providers():
        providers.insert(0, "CUDAExecutionProvider")
    opts = ort.SessionOptions()
    opts.log_severity_level = 3
    try:
        return ort.InferenceSession(str(path), sess_options=opts, providers=providers)
    except Exception as exc:  # onnxruntime raises its own exception types for bad files
        raise ModelNotFoundError(f"cannot load this {what} model as ONNX ({type(exc).__name__}: "
                                 f"{str(exc).splitlines()[0][:200]})", path,
                                 f"check the file, or point {flag} / {env} at a valid .onnx export") from exc


def prepare_input(rgb: np.ndarray, size: tuple[int, int] | None, mean, std, multiple: int = 1) -> np.ndarray:
    """uint8 RGB (H, W, 3) -> float32 NCHW (1, 3, h, w): resized (bilinear), scaled to [0,1], normalised."""
    x = rgb.astype(np.float32) * np.float32(1.0 / 255.0)
    if size is not None:
        h, w = int(size[0]), int(size[1])
        x = cv2.resize(x, (w, h), interpolation=cv2.INTER_LINEAR)
    elif multiple > 1:
        h = max(multiple, int(round(x.shape[0] / multiple)) * multiple)
        w = max(multiple, int(round(x.shape[1] / multiple)) * multiple)
        if (h, w) != x.shape[:2]:
            x = cv2.resize(x, (w, h), interpolation=cv2.INTER_LINEAR)
    x = (x - np.asarray(mean, np.float32)) / np.asarray(std, np.float32)
    return np.ascontiguousarray(x.transpose(2, 0, 1)[None])


def resize_map(x: np.ndarray, height: int, width: int) -> np.ndarray:
    """(h, w, C) or (h, w) float32 -> (height, width, ...) bilinear (cv2's half-pixel centres)."""
    if x.shape[:2] == (height, width):
        return x.astype(np.float32, copy=False)
    out = [cv2.resize(np.ascontiguousarray(x[..., i:i + 128] if x.ndim == 3 else x), (width, height),
                      interpolation=cv2.INTER_LINEAR)
           for i in (range(0, x.shape[-1], 128) if x.ndim == 3 else [0])]
    if x.ndim == 2:
        return out[0]
    out = [o[..., None] if o.ndim == 2 else o for o in out]
    return np.concatenate(out, axis=-1)
