"""The README a new user meets: its first screen is the picture, one paragraph and the two commands; every
picture it shows exists, is small, and is one the screenshot script regenerates (or a generated page's)."""
from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()
COMMANDS = ("bash install.sh && .venv/bin/repaint-nerf", "bash install.sh && .venv/bin/python -m pytest -q")


def test_the_first_screen_is_the_picture_a_paragraph_and_the_two_commands():
    first = README.split("\n## ", 1)[0]
    assert first.count("![") == 1 and "docs/screenshot.png" in first
    for command in COMMANDS:
        assert command in first
    assert not re.search(r"\d+(\.\d+)? ?(dB|ms|steps/s|IoU)\b", first), "no figures on the first screen"


def test_every_picture_exists_is_small_and_is_regenerated_by_one_command():
    from repaint_nerf.app.screenshot import PICTURES

    shown = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", README)
    assert len(shown) >= 8
    for path in shown:
        f = ROOT / path
        assert f.is_file(), path
        assert f.stat().st_size < 300_000, f"{path}: {f.stat().st_size} bytes"
        assert f.name in PICTURES, f"{path} is not made by python -m repaint_nerf.app.screenshot"
    assert "python -m repaint_nerf.app.screenshot" in README


def test_the_figures_are_generated_and_the_readme_names_the_command():
    table = README.split("<!-- figures:begin -->")[1].split("<!-- figures:end -->")[0]
    assert table.strip().startswith("| figure |") and "repaint-nerf docs" in table
