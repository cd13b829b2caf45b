"""The built-in demo scene: generated on first use into a cache folder, atomically (temp folder, then rename)."""
from __future__ import annotations

import json
import os
import shutil
import tempfile
from pathlib import Path

from repaint_nerf.core.synth.generate import GENERATOR_VERSION, make_scene

ENV_CACHE = "REPAINT_NERF_CACHE"
DEMO_VIEWS = 100


def cache_root() -> Path:
    """$REPAINT_NERF_CACHE, else ~/.cache/repaint-nerf."""
    env = os.environ.get(ENV_CACHE)
    return Path(env) if env else Path.home() / ".cache" / "repaint-nerf"


def _is_current(path: Path) -> bool:
    try:
        meta = json.loads((path / "gt" / "objects.json").read_text())
    except (OSError, ValueError):
        return False
    return meta.get("generator_version") == GENERATOR_VERSION


def demo_scene_path(size: int = 128) -> Path:
    """Path of the demo scene at `size` pixels, generating it on first use (a few seconds)."""
    root = cache_root()
    target = root / f"demo-{size}"
    if _is_current(target):
        return target
    root.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".demo-{size}-", dir=root))
    try:
        make_scene("demo", tmp / "scene", size=size, views=DEMO_VIEWS, seed=0)
        if target.exists():  # an outdated scene, or one another process has just finished
            if _is_current(target):
                return target
            stale = root / f".stale-{target.name}-{os.getpid()}"
            target.rename(stale)
            shutil.rmtree(stale, ignore_errors=True)
        try:
            (tmp / "scene").rename(target)
        except OSError:
            if not _is_current(target):  # lost a race to a process that wrote something else
                raise
        return target
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
