"""The public real captures the benchmarks use (issue 32): where each lives (repository, commit, folder inside), what
kind of scene it is and its licence. The captures themselves never enter this repository: `capture_prepare.py`
copies one from a fetched snapshot into a local folder (default ~/.cache/repaint-nerf/captures/NAME).
"""
from __future__ import annotations

import os
from dataclasses import asdict, dataclass
from pathlib import Path

from repaint_nerf.core.errors import UserError


@dataclass(frozen=True)
class Capture:
    """One public capture: a folder `path` inside `repo` at `commit`, opened by `load_scene` as it ships."""

    name: str
    repo: str  # owner/name on GitHub
    commit: str
    path: str  # folder inside the repository ("" = its root)
    kind: str  # "object in its room", "forward-facing", "360 degrees"
    layout: str  # the file that describes it
    images: str  # count x size as shipped
    licence: str
    note: str = ""

    def to_dict(self) -> dict:
        return asdict(self)


CAPTURES = (
    Capture("fox", "NVlabs/instant-ngp", "abe236ee00cf90cfca6e36e65c00435d5b21f50a", "data/nerf/fox",
            "object in its room (handheld phone, portrait)", "instant-ngp transforms.json, aabb_scale 4, OpenCV "
            "distortion, per-frame sharpness", "50 x 1080x1920 JPEG (67 frames listed, 17 of them without an image)",
            "NVIDIA Source Code License (non-commercial), the repository's LICENSE.txt",
            "the capture issue 32 describes; opens only if missing frames are skipped"),
    Capture("fern", "luo-ziyuan/CopyRNeRF-code", "454f028b606be4eb69c629aa4019b501504fb12b",
            "data/nerf_llff_data/fern", "forward-facing", "LLFF poses_bounds.npy",
            "20 x 4032x3024 JPEG, with images_4/ and images_8/ shipped beside",
            "not stated in that repository (the NeRF paper's LLFF 'fern' scene, Mildenhall et al.)",
            "its sparse/0/images.bin and database.db are absent from the snapshot; poses_bounds.npy is what opens it"),
    Capture("ethiopian_head", "vork/ethiopianHead", "a7061eb314f07ca6ab8415c3a01bb9bc5fd76b50", "",
            "360 degrees of an object on a turntable (the room behind it stays put)", "LLFF poses_bounds.npy (NeRD)",
            "66 x 4000x4000 JPEG, with 66 masks in masks/", "CC BY-NC-SA 4.0 (the repository's LICENSE.md)",
            "the poses circle about 340 degrees of azimuth around the object, but the background is the same in "
            "every photo: the masks it ships make the object a cut-out (without them 18 dB on its own training "
            "views)"),
    Capture("snowmiku", "noname0310/snowmiku2023plush-splat", "70fedae4fe163642ef71489e7e445f21ec0783e2", "input",
            "360 degrees of an object in its room (a plush on a bed, handheld phone)", "photos only: posed by our SfM",
            "97 x 3958x2968 JPEG", "MIT (the repository's LICENSE)",
            "a 3D Gaussian Splatting capture whose sparse/0/images.bin and undistorted images/ are absent from the "
            "snapshot; its photos as taken (input/) open through structure-from-motion (93 of 97 registered, about "
            "3.5 minutes on 2 cores, cached)"),
    Capture("kermit", "snavely/bundler_sfm", "a35a8f589b7b8419f43f9e41553a84522faa6f9e", "examples/kermit",
            "an object in its room, few photos (a plush on a chair, a dark room behind it)", "photos only: posed by "
            "our SfM", "11 x 640x480 JPEG (a 2002 Canon PowerShot A10)", "GPL (Bundler's README)",
            "Bundler's example set: 11 photos along an arc of about 90 degrees, 11 of 11 registered in 6 s; 1% of "
            "its SfM points lie beyond the cameras, 11% of its pixels look past the box they fill"),
)


def default_root() -> Path:
    """Where prepared captures go: $REPAINT_NERF_CAPTURES, else ~/.cache/repaint-nerf/captures (never the repo)."""
    env = os.environ.get("REPAINT_NERF_CAPTURES")
    return Path(env).expanduser() if env else Path.home() / ".cache" / "repaint-nerf" / "captures"


def find_capture(name: str, registry: tuple[Capture, ...] = CAPTURES) -> Capture:
    """The registered capture called `name`; a `UserError` listing the names otherwise."""
    for cap in registry:
        if cap.name == name:
            return cap
    raise UserError(f"no capture called {name!r}", hint="`repaint-nerf bench captures --list` shows them: "
                    + ", ".join(c.name for c in registry))


def _method_row(d: dict) -> dict:
    """One method's figures from its bench JSON (bench recon or bench nerfacto): PSNR/SSIM at the report times,
    the longest run's last scored point, samples per ray, steps per second, and what bench recon trained."""
    at = {k: (None if v is None else {"psnr": v.get("psnr"), "ssim": v.get("ssim"), "step": v.get("step"),
                                      "seconds": v.get("seconds")}) for k, v in (d.get("at") or {}).items()}
    scored = [v for v in at.values() if v and v.get("psnr") is not None]
    longest = max(scored, key=lambda v: v["seconds"] or 0.0, default=None)
    spr = d.get("samples_per_ray")
    trains = d.get("trains")  # bench recon: "colour alone ..." or, with --as-train, {"as": "the train command ..."}
    return {"at": at, "longest": longest, "steps_per_s": d.get("steps_per_s"),
            "trains": trains.get("as") if isinstance(trains, dict) else trains,
            "samples_per_ray": spr.get("with_grid") if isinstance(spr, dict) else spr,
            "measured": d.get("measured"), "command": d.get("command")}


METHODS = ("ours", "ours_as_train", "nerfacto")  # a row's methods, in the table's order


def side_by_side(ours: dict, nerfacto: dict | None) -> dict:
    """A capture's row of the side-by-side table: this project's bench recon JSON and nerfstudio's (bench
    nerfacto), each reduced to the figures issue 32 compares, plus the capture's size and views. A recon run
    with --as-train (what the `train` command trains) fills `ours_as_train`, a colour-alone one (as nerfacto
    trains) `ours`; the other stays None."""
    scene = ours.get("scene", {})
    key = "ours_as_train" if isinstance(ours.get("trains"), dict) else "ours"
    row = {"scene": {k: scene.get(k) for k in ("name", "kind", "size", "train_views", "test_views")},
           **{m: None for m in METHODS}, "nerfacto": None if nerfacto is None else _method_row(nerfacto)}
    row[key] = _method_row(ours)
    return row
