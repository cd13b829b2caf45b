"""Which bench JSON files the generated pages read, the command that writes each, and loading them with the date
and command each was measured with (stamped into the JSON by `repaint-nerf bench`)."""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

DEFAULT_DIR = Path("docs/bench")


@dataclass(frozen=True)
class Source:
    """A bench JSON the pages read: its file name in the bench folder and the command that writes it."""

    name: str
    file: str
    command: str


SOURCES: dict[str, Source] = {s.name: s for s in (
    Source("recon", "recon.json", "repaint-nerf bench recon --seconds 180 --json docs/bench/recon.json "
                                  "--plot docs/bench/recon.png"),
    Source("viewport", "viewport.json", "repaint-nerf bench viewport --json docs/bench/viewport.json"),
    Source("mask", "mask.json", "repaint-nerf bench mask --preset all --json docs/bench/mask.json"),
    Source("sdcost", "sdcost.json", "repaint-nerf bench sdcost --json docs/bench/sdcost.json"),
    Source("scale", "scale.json", "repaint-nerf bench scale --preset bread --views 100 --sizes 128,256,512 "
                                  "--seconds 300 --json docs/bench/scale.json"),
    Source("scale_capture", "scale_capture.json", "repaint-nerf bench scale --scene "
                                                  "~/.cache/repaint-nerf/captures/ethiopian_head --sizes 128,256,512 "
                                                  "--seconds 300 --evals 60 --targets 24,25 --json docs/bench/scale_capture.json"),
    Source("captures", "captures.json", "repaint-nerf bench recon --scene CAPTURE --seconds 300 and bench nerfacto "
                                        "--scene CAPTURE on each prepared capture, then bench captures --table"),
)}


@dataclass
class Measured:
    """One bench JSON as read: its figures, when and by what command it was measured, where it lies."""

    data: dict[str, Any]
    date: str
    command: str
    path: Path


def load(path: Path, fallback_command: str) -> Measured | str:
    """The file's figures, or a sentence saying why there are none (missing, unreadable)."""
    if not path.is_file():
        return "not measured"
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        return f"unreadable ({type(exc).__name__})"
    if not isinstance(data, dict):
        return "unreadable (not a JSON object)"
    date = data.get("measured") or "date not recorded"  # not the file's mtime: a checkout would change the pages
    return Measured(data, str(date), str(data.get("command") or fallback_command), path)


def load_all(folder: Path) -> tuple[dict[str, Measured | str], dict[str, Measured | str]]:
    """(the known sources by name, every other *.json in `folder` by file stem), each loaded or a reason."""
    known = {name: load(folder / s.file, s.command) for name, s in SOURCES.items()}
    taken = {s.file for s in SOURCES.values()}
    others = {p.stem: load(p, f"repaint-nerf bench {p.stem.split('_')[0]} --json {p}")
              for p in sorted(folder.glob("*.json")) if p.name not in taken}
    return known, others
