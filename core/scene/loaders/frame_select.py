"""Which frames of a transforms JSON are used, as instant-ngp decides: those whose image exists and, on request,
those not blurrier than their neighbours.

instant-ngp skips a frame whose image file is missing, and with `sharpness_discard_threshold` t (a key of the
JSON; 0 keeps all) it keeps a frame only when its `sharpness` (variance of the Laplacian, written per frame by
colmap2nerf) is at least t times the mean sharpness of the frames around it in file order (3 on each side). We
do the same, say it in one warning per reason that counts the frames, and keep the facts for `info`.
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from repaint_nerf.core.errors import SceneError, SceneWarning, UserError
from repaint_nerf.core.scene.loaders.common import as_float

SHARPNESS_NEIGHBOURS = 3  # frames on each side whose mean sharpness a frame is compared with (instant-ngp's)


@dataclass
class FrameSelection:
    """The frames kept (indices into the JSON's list, in the given order) and those skipped, by reason."""

    kept: list[int]
    missing: list[str] = field(default_factory=list)  # file_path of frames whose image is not there
    blurry: list[str] = field(default_factory=list)  # file_path of frames discarded by sharpness
    threshold: float = 0.0  # the sharpness discard threshold applied (0 = none)

    def report(self) -> dict:
        """JSON-ready facts for `info`: counts, a few names, the threshold."""
        return {"missing": len(self.missing), "blurry": len(self.blurry), "threshold": self.threshold,
                "examples": {"missing": self.missing[:3], "blurry": self.blurry[:3]}}


def check_sharpness_discard(value) -> float:
    """Validate a --sharpness-discard fraction (0 keeps every frame; 0.8 drops frames under 80% of their
    neighbours' mean sharpness)."""
    v = as_float(value)
    if not math.isfinite(v) or not 0.0 <= v < 10.0:
        raise UserError(f"--sharpness-discard must be a number >= 0 (a fraction of the neighbours' mean "
                        f"sharpness), got {value!r}", hint="e.g. --sharpness-discard 0.8; 0 keeps every frame")
    return v


def _sharpness(frame: dict) -> float | None:
    v = as_float(frame.get("sharpness"))
    return v if math.isfinite(v) else None


def blurry_frames(frames: list[dict], order: list[int], threshold: float) -> set[int]:
    """Indices (into `frames`) whose sharpness is below `threshold` x the mean of their neighbours in `order`.

    Frames without a `sharpness` are kept and left out of their neighbours' means; threshold 0 keeps all.
    """
    if threshold <= 0.0:
        return set()
    values = [_sharpness(frames[i]) for i in order]
    out = set()
    for k, i in enumerate(order):
        if values[k] is None:
            continue
        around = [v for v in values[max(0, k - SHARPNESS_NEIGHBOURS):k + SHARPNESS_NEIGHBOURS + 1] if v is not None]
        if values[k] < threshold * float(np.mean(around)):
            out.add(i)
    return out


def select_frames(meta: dict, frames: list[dict], order: list[int], find, path: Path,
                  sharpness_discard: float | None = None) -> FrameSelection:
    """Keep the frames of `order` whose image `find(i)` locates (None = missing) and that pass the sharpness rule.

    `sharpness_discard` overrides the JSON's `sharpness_discard_threshold` (None: the JSON's, else 0). A
    `SceneError` when no frame is left, naming why.
    """
    threshold = sharpness_discard
    if threshold is None:
        threshold = check_sharpness_discard(meta.get("sharpness_discard_threshold", 0.0))
    blurry = blurry_frames(frames, order, threshold)
    sel = FrameSelection([], threshold=threshold)
    for i in order:
        name = str(frames[i].get("file_path"))
        if find(i) is None:
            sel.missing.append(name)
        elif i in blurry:
            sel.blurry.append(name)
        else:
            sel.kept.append(i)
    if not sel.kept:
        if len(sel.missing) == len(order):
            raise SceneError(f"none of the {len(order)} frames has its image (e.g. '{sel.missing[0]}' is missing)",
                             path, hint="put the images where file_path says, relative to this file's folder")
        raise SceneError(f"every frame with an image is blurrier than --sharpness-discard {threshold:g} allows",
                         path, hint="lower --sharpness-discard (0 keeps every frame)")
    return sel


def warn_skipped(sel: FrameSelection, total: int, path: Path) -> None:
    """One warning per reason, counting the frames skipped (instant-ngp skips them the same way)."""
    if sel.missing:
        warnings.warn(f"{path}: skipped {len(sel.missing)} of {total} frames whose image is missing "
                      f"(e.g. '{sel.missing[0]}')", SceneWarning, stacklevel=2)
    if sel.blurry:
        warnings.warn(f"{path}: discarded {len(sel.blurry)} of {total} frames as blurry (sharpness below "
                      f"{sel.threshold:g}x their neighbours' mean)", SceneWarning, stacklevel=2)


def merge_reports(reports: list[dict]) -> dict | None:
    """The skipped-frame facts of several JSON files (a NeRF-synthetic scene's splits) as one; None if none."""
    reports = [r for r in reports if r]
    if not reports:
        return None
    return {"missing": sum(r["missing"] for r in reports), "blurry": sum(r["blurry"] for r in reports),
            "threshold": max(r["threshold"] for r in reports),
            "examples": {k: [n for r in reports for n in r["examples"][k]][:3] for k in ("missing", "blurry")}}
