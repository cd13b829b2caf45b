"""The figures `bench compare` reads from two runs of the same benchmark (a base and a change) and their ratios.

Each figure names the JSON path it is read from and whether lower or higher is better, so a ratio says at a
glance which side won: `ratio` is head / base, and `better` says whether the head improved on the base.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from repaint_nerf.core.bench.scale import goal_target, size_ratio


@dataclass(frozen=True)
class Figure:
    """One number of a benchmark's JSON: a dotted path (list items by index, or `sizes[SIZE]` by image size)."""

    label: str
    path: str
    lower_is_better: bool = True
    unit: str = ""


# What a change to the field, the renderer, the trainer or the selection must not make worse.
FIGURES: dict[str, list[Figure]] = {
    "recon": [
        Figure("final test PSNR", "final.psnr", False, "dB"),
        Figure("seconds to 25.4 dB", "seconds_to_25_4", True, "s"),
        Figure("steps per second", "steps_per_s", False, "/s"),
        Figure("first 50 steps / later step", "fog.ratio", True, "x"),
        Figure("render 128x128", "render_ms_128", True, "ms"),
        Figure("samples per ray (trained grid)", "samples_per_ray.with_grid", True, ""),
        Figure("peak RSS", "peak_rss_mb", True, "MB"),
    ],
    "viewport": [
        Figure("UI frame p99", "ui_frame_ms_p99", True, "ms"),
        Figure("UI frame p50", "ui_frame_ms_p50", True, "ms"),
        Figure("move to first frame p50", "move_to_first_frame_ms_p50", True, "ms"),
        Figure("move to first frame p99", "move_to_first_frame_ms_p99", True, "ms"),
        Figure("patch to mask", "patch_to_mask_ms", True, "ms"),
        Figure("patch to mask while the views vote", "patch_during_vote_ms", True, "ms"),
        Figure("tool to first feature frame", "tool_to_first_feature_frame_ms", True, "ms"),
        Figure("tool to sharp feature frame", "tool_to_feature_frame_ms", True, "ms"),
        Figure("frames per second while dragging", "drag_frames_per_s", False, "/s"),
    ],
    "scale": [
        Figure("{size} px: seconds to {target} dB", "sizes[{size}].seconds_to_{target}", True, "s"),
        Figure("{size} px: seconds to {target} dB on the smallest size's images",
               "sizes[{size}].seconds_to_{target}_content", True, "s"),
        Figure("{size} px: steps per second", "sizes[{size}].steps_per_s", False, "/s"),
        Figure("{size} px: samples per ray", "sizes[{size}].samples_per_ray", True, ""),
        Figure("{size} px: render", "sizes[{size}].render_ms", True, "ms"),
        Figure("{size} px: final PSNR", "sizes[{size}].final_psnr", False, "dB"),
    ],
}


def lookup(data: Any, path: str) -> float | None:
    """The number at a dotted `path` of a benchmark's JSON (None when absent or not a number).
    `sizes[256]` picks the entry of a list whose 'size' is 256 (bench scale's per-size entries)."""
    cur = data
    for part in path.split("."):
        key, _, sel = part.partition("[")
        if not isinstance(cur, dict) or key not in cur:
            return None
        cur = cur[key]
        if sel:
            want = sel.rstrip("]")
            items = [e for e in cur if isinstance(e, dict) and str(e.get("size")) == want] if isinstance(cur, list) else []
            if not items:
                return None
            cur = items[0]
    return float(cur) if isinstance(cur, (int, float)) and not isinstance(cur, bool) else None


def scale_sizes(*results: dict) -> list[int]:
    """The image sizes bench scale measured in any of `results`, sorted."""
    return sorted({int(e["size"]) for r in results for e in (r or {}).get("sizes", []) if "size" in e})


def compare(bench: str, base: dict | None, head: dict | None) -> list[dict]:
    """Rows (label, unit, base, head, ratio head/base, better) for one benchmark's two results; a side that did
    not run (None) or lacks a figure gives None there, and no ratio."""
    figures = FIGURES[bench]
    if bench == "scale":
        t = f"{goal_target(head or base):g}"
        figures = [Figure(f.label.format(size=s, target=t), f.path.format(size=s, target=t), f.lower_is_better, f.unit)
                   for s in scale_sizes(base or {}, head or {}) for f in figures]
    rows = [_row(f.label, f.unit, None if base is None else lookup(base, f.path),
                 None if head is None else lookup(head, f.path), f.lower_is_better) for f in figures]
    if bench == "scale":
        rows += size_ratio_rows(base, head)
    return rows


def size_ratio_rows(base: dict | None, head: dict | None) -> list[dict]:
    """Time to the goal PSNR (30 dB unless the runs were told other targets) at each size over that at the smallest
    (issue 33's targets: 2x at 256, 4x at 512 px of 128)."""
    sizes = scale_sizes(base or {}, head or {})
    t = goal_target(head or base)
    return [_row(f"time to {t:g} dB, {s} px / {sizes[0]} px", "x",
                 *(None if r is None else size_ratio(r, s, sizes[0], t) for r in (base, head)), lower_is_better=True)
            for s in sizes[1:]]


def _row(label: str, unit: str, a: float | None, b: float | None, lower_is_better: bool) -> dict:
    """One row: both sides' figure, head / base, and whether the head did better (None where a side lacks it)."""
    ratio = b / a if a not in (None, 0.0) and b is not None else None
    better = None if a is None or b is None else (b < a if lower_is_better else b > a)
    return {"label": label, "unit": unit, "base": a, "head": b, "ratio": ratio, "better": better}


def format_rows(bench: str, rows: list[dict]) -> str:
    """A plain-text table of `compare`'s rows."""
    def num(v):
        return "-" if v is None else f"{v:.3g}" if abs(v) < 100 else f"{v:.0f}"

    lines = [f"{bench}:", f"  {'figure':40s} {'base':>9s} {'head':>9s} {'head/base':>9s}"]
    for r in rows:
        mark = "" if r["better"] is None else ("  better" if r["better"] else "  worse")
        unit = f" {r['unit']}" if r["unit"] else ""
        lines.append(f"  {r['label'] + unit:40s} {num(r['base']):>9s} {num(r['head']):>9s} "
                     f"{'-' if r['ratio'] is None else format(r['ratio'], '.3f'):>9s}{mark}")
    return "\n".join(lines)
