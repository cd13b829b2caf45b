"""Shared fixtures: a virtual display for GUI tests and small generated scenes (never committed)."""
from __future__ import annotations

import atexit
import os
import shutil
import tempfile
from pathlib import Path

import pytest

os.environ.setdefault("REPAINT_NERF_DEVICE", "cpu")
# The editor remembers per user which first-run hints were followed: tests never read or write the real ones.
os.environ["REPAINT_NERF_CONFIG_DIR"] = tempfile.mkdtemp(prefix="repaint-nerf-test-config-")
atexit.register(shutil.rmtree, os.environ["REPAINT_NERF_CONFIG_DIR"], True)  # not one folder left per run
ARTIFACTS = Path(__file__).parent / "artifacts"


@pytest.fixture(scope="session")
def artifacts_dir() -> Path:
    """Where tests leave screenshots and plots for a person (or CI) to look at."""
    ARTIFACTS.mkdir(exist_ok=True)
    return ARTIFACTS


@pytest.fixture(scope="session")
def xvfb_display():
    """A DISPLAY for real windows: the user's own if set, else an Xvfb started for the session."""
    if os.environ.get("DISPLAY"):
        yield os.environ["DISPLAY"]
        return
    from repaint_nerf.app.xvfb import start_xvfb

    try:
        proc, display = start_xvfb(99, 140)
    except FileNotFoundError as exc:
        pytest.fail(str(exc))
    try:
        yield display
    finally:
        proc.terminate()
        proc.wait(timeout=10)
        os.environ.pop("DISPLAY", None)


@pytest.fixture(scope="session")
def scene_factory(tmp_path_factory):
    """make(preset, size, views, seed) -> path of a generated synthetic scene, cached per session."""
    cache: dict = {}

    def make(preset: str = "demo", size: int = 32, views: int = 12, seed: int = 0, test_views: int = 4) -> Path:
        key = (preset, size, views, seed, test_views)
        if key not in cache:
            from repaint_nerf.core.synth.generate import make_scene

            out = tmp_path_factory.mktemp(f"scene_{preset}_{size}")
            cache[key] = make_scene(preset, out, size=size, views=views, seed=seed, test_views=test_views)
        return cache[key]

    return make
