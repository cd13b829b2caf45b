"""Where a pretrained model lives: CLI flag > environment variable > workspace settings.

One resolver for every model kind, so every missing model produces the same clear message naming the
flag and environment variable to set (DESIGN.md, "Every pretrained network is loaded from a local path").
"""
from __future__ import annotations

import os
import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from core.errors import ModelNotFoundError

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
}


def model_kind(kind: str) -> ModelKind:
    """The naming record of a model kind ('sd' or 'clip')."""
    try:
        return KINDS[kind]
    except KeyError:
        raise ValueError(f"unknown model kind {kind!r}; known: {sorted(KINDS)}") from None


def how_to_set(kind: str) -> str:
    """The one-line hint telling a user how to point the program at a model of this kind."""
    k = model_kind(kind)
    return (f"pass {k.flag} PATH, or set the environment variable {k.env}=PATH "
            f"(or {ROOT_ENV}=DIR holding DIR/{k.kind}), or '{k.settings_key}' in the workspace settings")


def _from_settings(settings: Mapping[str, Any] | None, k: ModelKind) -> str | None:
    if not settings:
        return None
    value = settings.get(k.settings_key)
    if value is None and isinstance(settings.get("models"), Mapping):
        value = settings["models"].get(k.kind)
    return str(value) if value else None


def hub_cache_dir(environ: Mapping[str, str] | None = None) -> Path:
    """The local Hugging Face hub cache: $HF_HUB_CACHE, else $HF_HOME/hub, else ~/.cache/huggingface/hub."""
    env = os.environ if environ is None else environ
    if env.get("HF_HUB_CACHE"):
        return Path(env["HF_HUB_CACHE"]).expanduser()
    home = env.get("HF_HOME") or str(Path(env.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "huggingface")
    return Path(home).expanduser() / "hub"


def looks_like_model_id(name: str) -> bool:
    """'org/name' as the Hugging Face hub spells a model id (not a relative or absolute path)."""
    return re.fullmatch(r"[A-Za-z0-9][\w.-]*/[\w.-]+", name) is not None and not name.startswith(".")


def cached_snapshot(model_id: str, environ: Mapping[str, str] | None = None) -> Path | None:
    """The folder of `model_id`'s cached snapshot (refs/main) in the local HF cache, or None; never the network."""
    if not looks_like_model_id(model_id):
        return None
    from huggingface_hub import snapshot_download

    try:
        return Path(snapshot_download(model_id, cache_dir=str(hub_cache_dir(environ)), local_files_only=True))
    except Exception:  # not cached (LocalEntryNotFoundError) or a malformed cache entry: both mean "not here"
        return None


def resolve_model_path(kind: str, flag: str | os.PathLike | None = None,
                       settings: Mapping[str, Any] | None = None,
                       environ: Mapping[str, str] | None = None) -> Path:
    """The local path of a `kind` model: `flag` > $REPAINT_NERF_<KIND>_PATH > $REPAINT_NERF_MODELS/<kind> > settings.

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
    path = Path(value).expanduser()
    if not path.exists():
        snapshot = cached_snapshot(value, env)
        if snapshot is not None:
            return snapshot
        id_hint = (f"; {value!r} is not in the local Hugging Face cache ({hub_cache_dir(env)}) either: download it "
                   f"there on a machine with a network, or give a local folder" if looks_like_model_id(value) else "")
        raise ModelNotFoundError(f"the {k.title} given by {source} does not exist", path=path,
                                 hint=how_to_set(kind) + id_hint)
    return path
