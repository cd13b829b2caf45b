"""Where a pretrained model lives: CLI flag > environment variable > workspace settings.

One resolver for every model kind, so every missing model produces the same clear message naming the
flag and environment variable to set (DESIGN.md, "Every pretrained network is loaded from a local path").
A value is a local path (file or folder) or a model id already in the local Hugging Face cache
('facebook/dinov2-small' -> $HF_HOME/hub/models--facebook--dinov2-small/snapshots/REV); nothing is downloaded.
"""
from __future__ import annotations

import json
import os
import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from repaint_nerf.core.errors import ModelNotFoundError

ROOT_ENV = "REPAINT_NERF_MODELS"


@dataclass(frozen=True)
class ModelKind:
    """How a user names one kind of model: its CLI flag, its environment variable, its settings key."""

    kind: str
    title: str
    flag: str
    env: str
    settings_key: str


KINDS: dict[str, ModelKind] = {
    "sd": ModelKind("sd", "Stable Diffusion model", "--sd-path", "REPAINT_NERF_SD_PATH", "sd_path"),
    "clip": ModelKind("clip", "CLIP model", "--clip-path", "REPAINT_NERF_CLIP_PATH", "clip_path"),
    "feature": ModelKind("feature", "feature model", "--feature-model", "REPAINT_NERF_FEATURE_MODEL",
                         "feature_model"),
    "depth": ModelKind("depth", "depth model", "--depth-model", "REPAINT_NERF_DEPTH_MODEL", "depth_model"),
    "sam": ModelKind("sam", "SAM model", "--sam-path", "REPAINT_NERF_SAM_PATH", "sam_path"),
}
_MODEL_ID = re.compile(r"[A-Za-z0-9][\w.-]*(/[A-Za-z0-9][\w.-]*)?")


def model_kind(kind: str) -> ModelKind:
    """The naming record of a model kind ('sd' or 'clip')."""
    try:
        return KINDS[kind]
    except KeyError:
        raise ValueError(f"unknown model kind {kind!r}; known: {sorted(KINDS)}") from None


def how_to_set(kind: str) -> str:
    """The one-line hint telling a user how to point the program at a model of this kind."""
    k = model_kind(kind)
    return (f"pass {k.flag} PATH (or a model id already in the local Hugging Face cache), or set the "
            f"environment variable {k.env}=PATH (or {ROOT_ENV}=DIR holding DIR/{k.kind}), or "
            f"'{k.settings_key}' in the workspace settings; nothing is downloaded")


def hf_hub_cache(environ: Mapping[str, str] | None = None) -> Path:
    """The local Hugging Face hub cache folder: $HF_HUB_CACHE, else $HF_HOME/hub, else ~/.cache/huggingface/hub."""
    env = os.environ if environ is None else environ
    if env.get("HF_HUB_CACHE"):
        return Path(env["HF_HUB_CACHE"]).expanduser()
    if env.get("HF_HOME"):
        return Path(env["HF_HOME"]).expanduser() / "hub"
    base = Path(env["XDG_CACHE_HOME"]).expanduser() if env.get("XDG_CACHE_HOME") else Path.home() / ".cache"
    return base / "huggingface" / "hub"


def is_model_id(value: str) -> bool:
    """Whether `value` reads as a hub model id ('org/name' or 'name'), not as a file-system path."""
    return bool(_MODEL_ID.fullmatch(str(value))) and not str(value).endswith((".onnx", ".safetensors", ".ckpt"))


def cached_snapshot(model_id: str, environ: Mapping[str, str] | None = None) -> Path | None:
    """The snapshot folder of `model_id` in the local hub cache (the revision refs/main names, else the only
    snapshot), or None when it is not there. Never touches the network."""
    if not is_model_id(model_id):
        return None
    repo = hf_hub_cache(environ) / ("models--" + str(model_id).replace("/", "--"))
    snapshots = repo / "snapshots"
    ref = repo / "refs" / "main"
    if ref.is_file():
        snap = snapshots / ref.read_text().strip()
        return snap if snap.is_dir() else None
    found = [d for d in snapshots.iterdir() if d.is_dir()] if snapshots.is_dir() else []
    return found[0] if len(found) == 1 else None


def locate_model(kind: str, value: str | os.PathLike, source: str | None = None,
                 environ: Mapping[str, str] | None = None) -> Path:
    """The local file or folder a model value names: an existing path, else a model id in the local hub cache.
    Anything else is a ModelNotFoundError naming `source` (default: the kind's flag) and how to set it."""
    k = model_kind(kind)
    path = Path(value).expanduser()
    if path.exists():
        return path
    snap = cached_snapshot(str(value), environ)
    if snap is not None:
        return snap
    where = source or f"the {k.flag} flag"
    cache = f" (nor is it a model id in the local Hugging Face cache {hf_hub_cache(environ)})" \
        if is_model_id(str(value)) else ""
    raise ModelNotFoundError(f"the {k.title} given by {where} does not exist{cache}", path=path,
                             hint=how_to_set(kind))


def model_type(path: str | os.PathLike) -> str:
    """'onnx' for an ONNX file (or a folder of one without config.json), else config.json's model_type
    ('dinov2', 'clip', 'siglip', 'dpt', 'depth_anything', 'sam', ...); unreadable is a ModelNotFoundError."""
    path = Path(path)
    if path.is_file():
        if path.suffix.lower() == ".onnx":
            return "onnx"
        raise ModelNotFoundError("not a model: expected an .onnx file or a transformers folder with config.json",
                                 path=path, hint="point at the .onnx file or at the model's folder")
    cfg = path / "config.json"
    if not cfg.is_file():
        if any(path.glob("*.onnx")):
            return "onnx"
        raise ModelNotFoundError("not a model folder: it has neither config.json nor an .onnx file", path=path,
                                 hint="point at a folder saved by transformers (save_pretrained) or at an .onnx file")
    try:
        kind = json.loads(cfg.read_text(encoding="utf-8")).get("model_type")
    except (OSError, ValueError, AttributeError) as exc:
        raise ModelNotFoundError(f"unreadable config.json ({exc})", path=cfg,
                                 hint="fix the file or point at another model") from exc
    if not kind:
        raise ModelNotFoundError("config.json names no model_type", path=cfg,
                                 hint="point at a folder saved by transformers (save_pretrained)")
    return str(kind)


def _from_settings(settings: Mapping[str, Any] | None, k: ModelKind) -> str | None:
    if not settings:
        return None
    value = settings.get(k.settings_key)
    if value is None and isinstance(settings.get("models"), Mapping):
        value = settings["models"].get(k.kind)
    return str(value) if value else None


def resolve_model_path(kind: str, flag: str | os.PathLike | None = None,
                       settings: Mapping[str, Any] | None = None,
                       environ: Mapping[str, str] | None = None) -> Path:
    """The local path of a `kind` model: `flag` > $REPAINT_NERF_<KIND>_PATH > $REPAINT_NERF_MODELS/<kind> > settings,
    each a path or a model id in the local hub cache (`locate_model`).

    A value that is no existing path but a model id ('org/name') resolves to its snapshot in the local
    Hugging Face cache (offline).

    Raises ModelNotFoundError (naming the flag and environment variable) when nothing is configured or
    the configured path does not exist.
    """
    k = model_kind(kind)
    env = os.environ if environ is None else environ
    candidates: list[tuple[str, str]] = []
    if flag:
        candidates.append((f"the {k.flag} flag", str(flag)))
    elif env.get(k.env):
        candidates.append((f"${k.env}", env[k.env]))
    else:
        root = env.get(ROOT_ENV)
        if root and (Path(root).expanduser() / k.kind).exists():
            candidates.append((f"${ROOT_ENV}/{k.kind}", str(Path(root) / k.kind)))
        else:
            setting = _from_settings(settings, k)
            if setting:
                candidates.append((f"the workspace setting '{k.settings_key}'", setting))
    if not candidates:
        looked = f" ({ROOT_ENV}={env[ROOT_ENV]} has no '{k.kind}' folder)" if env.get(ROOT_ENV) else ""
        raise ModelNotFoundError(f"no {k.title} is configured{looked}", hint=how_to_set(kind))
    source, value = candidates[0]
    return locate_model(kind, value, source, env)
