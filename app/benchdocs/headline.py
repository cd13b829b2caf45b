"""The README's short table: each headline figure of this build beside its anchor, with the bench command and
the date it was measured. A figure whose JSON is missing says so and names the command that measures it."""
from __future__ import annotations

import re
from typing import Any, Callable

from repaint_nerf.app.benchdocs.sources import SOURCES, Measured
from repaint_nerf.app.benchdocs.text import num, table

HEADER = ("figure", "this build", "anchor", "measured")


def _recon_time(d: dict) -> tuple[str, str]:
    fin, t25 = d["final"], d.get("seconds_to_25_4")
    reached = f"{t25:.0f} s" if t25 is not None else f"not reached in {fin['seconds']:.0f} s"
    ref = d["reference"]["nerfacto"]
    return (f"{reached}; {fin['psnr']:.1f} dB after {fin['seconds']:.0f} s",
            f"nerfacto: {ref['seconds_to_25_4']:.0f} s (run side by side once, issue 3)")


def _recon_render(d: dict) -> tuple[str, str]:
    return (f"{d['render_ms_128']:.0f} ms", f"nerfacto: {d['reference']['nerfacto']['render_s_128']:.1f} s")


def _viewport(d: dict) -> tuple[str, str]:
    return (f"{num(d.get('move_to_first_frame_ms_p50'), 0)} / {num(d.get('ui_frame_ms_p99'), 1)} / "
            f"{num(d.get('patch_to_mask_ms'), 0)} ms", "goal: 50 / 16.7 / 50 ms (a 60 Hz UI)")


def _mask(d: dict) -> tuple[str, str]:
    f = d["final"]
    if "presets" in d:
        best = [p["final"]["best_iou"] for p in d["presets"].values()]
        seeds = d.get("seeds") or [0]
        runs = f"{len(best)} presets" if len(seeds) == 1 else \
            f"{len(best)} runs: {len(best) // len(seeds)} preset{'s' if len(best) > len(seeds) else ''} x {len(seeds)} seeds"
        return (f"mean {f['mean_iou']:.3f}, worst {f['iou']:.3f} ({runs})",
                f"fixed threshold 0.5: worst {f['min_iou_fixed']:.3f}; best threshold read from the ground truth: "
                f"mean {sum(best) / len(best):.3f}")
    return (f"{f['iou']:.3f} ({d.get('scene', {}).get('name', 'one preset')})",
            f"fixed threshold 0.5: {f['iou_fixed']:.3f}; best threshold read from the ground truth: "
            f"{f['best_iou']:.3f}")


def _sdcost(d: dict) -> tuple[str, str]:
    opts = d["options"]

    def fastest(res: int) -> tuple[str, float] | None:
        at = [(n, o["step_seconds"]) for n, o in opts.items() if o["settings"].get("sds_resolution") == res]
        return min(at, key=lambda x: x[1]) if at else None

    f512, f256 = fastest(512), fastest(256)
    ours = f"{f512[1]:.2f} s at 512 px ({f512[0]})" if f512 else "-"
    if f256:
        ours += f"; {f256[1]:.2f} s at 256 px"
    base = opts.get("baseline")
    return ours, ("-" if base is None else f"{base['step_seconds']:.1f} s: fp32 UNet and VAE at 512 px "
                                           "(the paper's setting)")


# (source, what the row measures, how its figures are read)
ROWS: tuple[tuple[str, str, Callable[[dict], tuple[str, str]]], ...] = (
    ("recon", "Reconstruction: time to 25.4 dB test PSNR (demo scene)", _recon_time),
    ("recon", "Render a 128x128 view of the trained field", _recon_render),
    ("viewport", "Viewport: camera move to new frame / UI frame p99 / patch to mask", _viewport),
    ("mask", "Selection: mask IoU from one patch, automatic threshold", _mask),
    ("sdcost", "Stable Diffusion edit step (SDS, UNet forward and backward)", _sdcost),
)


def short_command(command: str) -> str:
    """The command without its output paths (--json, --plot, --png), as the table shows it."""
    return re.sub(r"\s--(json|plot|png)(=|\s+)\S+", "", command).strip()


def _where(m: Measured) -> str:
    device = m.data.get("device")
    return f"{m.date}{f', {device}' if device else ''}: `{short_command(m.command)}`"


def rows(known: dict[str, Measured | str]) -> list[tuple[str, str, str, str]]:
    """One (figure, this build, anchor, measured) per headline row; a missing source's row says how to measure."""
    out = []
    for source, what, read in ROWS:
        m: Any = known.get(source, "not measured")
        if isinstance(m, Measured):
            try:
                ours, anchor = read(m.data)
                out.append((what, ours, anchor, _where(m)))
                continue
            except (KeyError, TypeError, ValueError, IndexError, ZeroDivisionError) as exc:
                m = f"unreadable ({type(exc).__name__}: {exc})"
        out.append((what, m, "-", f"run `{SOURCES[source].command}`"))
    return out


def markdown(known: dict[str, Measured | str]) -> str:
    """The headline table as markdown."""
    return table(HEADER, rows(known))
