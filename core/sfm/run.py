"""Structure-from-motion on a folder of photos, cached in the workspace: `sfm_scene` -> a `Scene`.

Phases (each timed and reported): intake (core.sfm.images), features, matching, mapping (the largest
model kept; photos it could not register listed by name), undistortion. The result is a COLMAP
folder `WS/sfm/scene/` read back through the COLMAP loader, plus `WS/sfm/report.json`; a second
open with the same photos and options skips every phase. One process at a time runs it into a workspace
(`WS/sfm.lock`): another waits, then reuses the result.
"""
from __future__ import annotations

import json
import logging
import os
import shutil
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from filelock import FileLock, Timeout

from repaint_nerf.core.errors import SceneError
from repaint_nerf.core.scene.loaders.colmap import find_model, load_colmap, read_model
from repaint_nerf.core.scene.scene import SCENE_KINDS, Scene
from repaint_nerf.core.sfm import images as intake
from repaint_nerf.core.sfm import judge, pipeline
from repaint_nerf.core.sfm.judge import Verdict
from repaint_nerf.core.workspace import atomic

log = logging.getLogger("repaint_nerf.sfm")

CACHE_VERSION = 2  # 2: the report carries the model check's verdict
PHASES = ("intake", "features", "matching", "mapping", "retry", "undistortion")
Progress = Callable[[str, float, str], None]  # (phase, fraction of that phase done in [0, 1], message)


def default_workspace(photos_dir: Path) -> Path:
    """Where a photo folder's workspace goes when none is given (beside it, as the editor does)."""
    photos_dir = Path(photos_dir).resolve()
    return photos_dir.parent / f"{photos_dir.name}.repaint-nerf"


def _sfm_dir(workspace_dir: Path) -> Path:
    from repaint_nerf.core.workspace.workspace import Workspace

    return Workspace.open_or_create(workspace_dir).path("sfm")


def _options(matcher: str, max_side: int) -> dict:
    return {"version": CACHE_VERSION, "matcher": matcher, "max_side": max_side}


def cached_report(photos_dir: Path, workspace_dir: Path, matcher: str = "auto",
                  max_side: int = intake.MAX_SIDE) -> dict | None:
    """The saved report when the cache matches these photos and options (and its model exists), else None."""
    sfm = Path(workspace_dir) / "sfm"
    try:
        report = json.loads((sfm / "report.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    trusted = (report.get("verdict") or {}).get("trusted", False)
    if report.get("options") != _options(matcher, max_side) or \
            report.get("fingerprint") != intake.fingerprint(photos_dir) or \
            (trusted and find_model(sfm / "scene") is None):
        return None  # a rejected model has no scene folder: its report alone answers (with the same error)
    report["scene_dir"] = str(sfm / "scene")  # where it is now (a workspace may have moved since)
    return report


def _link_or_copy(src: str, dst: str) -> None:
    try:
        os.link(src, dst)  # the same files, no second copy on disk
    except OSError:
        shutil.copy2(src, dst)


def adopt_cache(photos_dir: Path, workspace_dir: Path, matcher: str = "auto",
                max_side: int = intake.MAX_SIDE) -> dict | None:
    """The result `repaint-nerf sfm` left beside the photos (default_workspace), brought into `workspace_dir` when
    it matches these photos and options: `sfm PHOTOS` then `train PHOTOS --workspace WS` runs SfM once, not twice
    (a 97-photo capture's 3.4 minutes came out of train's --seconds). Only the report and the final model with its
    undistorted images are brought, hard-linked where the file system allows. None when there is nothing to adopt."""
    beside = default_workspace(photos_dir)
    if beside.resolve() == Path(workspace_dir).resolve() or cached_report(photos_dir, beside, matcher,
                                                                           max_side) is None:
        return None
    sfm = _sfm_dir(workspace_dir)
    shutil.rmtree(sfm, ignore_errors=True)
    sfm.mkdir(parents=True)
    if (beside / "sfm" / "scene").is_dir():
        shutil.copytree(beside / "sfm" / "scene", sfm / "scene", copy_function=_link_or_copy)
    shutil.copy2(beside / "sfm" / "report.json", sfm / "report.json")
    return cached_report(photos_dir, workspace_dir, matcher, max_side)


def run_sfm(photos_dir: str | Path, workspace_dir: str | Path | None = None, progress: Progress | None = None,
            matcher: str = "auto", max_side: int = intake.MAX_SIDE, force: bool = False) -> dict:
    """Run (or reuse) structure-from-motion; returns the report.

    Report: {"total", "registered", "unregistered": [names], "skipped": [names], "notes": [...],
    "seconds": {phase: s}, "matcher", "cached", "scene_dir", "points", "verdict", "attempts"}.
    The model is judged (core.sfm.judge); an implausible one is mapped again with one camera per photo
    and the better kept. A model that stays implausible is a `SceneError` with its reasons (cached too).
    """
    photos_dir = Path(photos_dir)
    workspace_dir = Path(workspace_dir) if workspace_dir is not None else default_workspace(photos_dir)
    intake.photos_folder(photos_dir)  # a missing folder is a SceneError before anything is created
    lock = _sfm_lock(workspace_dir, progress)
    try:
        return _run_sfm_locked(photos_dir, workspace_dir, progress, matcher, max_side, force)
    finally:
        lock.release()


def _sfm_lock(workspace_dir: Path, progress: Progress | None) -> FileLock:
    """The lock, held, of structure-from-motion into `workspace_dir`: two at once (the editor and `train` on the
    same photos, or two benches) deleted each other's databases, and one ended in pycolmap's "file does not
    exist". A second waits, saying so, then finds the first one's result cached."""
    from repaint_nerf.core.workspace.workspace import Workspace

    lock = FileLock(str(Workspace.open_or_create(workspace_dir).path("sfm.lock")))
    try:
        lock.acquire(timeout=0.5)
    except Timeout:
        if progress:
            progress("waiting", 0.0, f"waiting for another structure-from-motion into {workspace_dir} to finish")
        lock.acquire()
    return lock


def _run_sfm_locked(photos_dir: Path, workspace_dir: Path, progress: Progress | None, matcher: str, max_side: int,
                    force: bool) -> dict:
    if not force:
        report, where = cached_report(photos_dir, workspace_dir, matcher, max_side), workspace_dir
        if report is None:
            report, where = adopt_cache(photos_dir, workspace_dir, matcher, max_side), default_workspace(photos_dir)
        if report is not None:
            report["cached"] = True
            if progress:
                progress("cached", 1.0, f"reusing structure-from-motion from {where}")
            return _trusted_or_raise(report, photos_dir)
    sfm = _sfm_dir(workspace_dir)
    say = progress or (lambda phase, frac, msg: None)
    seconds: dict[str, float] = {}

    def phase(name: str, fn, msg: str):
        say(name, 0.0, msg)
        t0 = time.perf_counter()
        out = fn()
        seconds[name] = round(time.perf_counter() - t0, 3)
        log.info("sfm %s: %.2f s", name, seconds[name])
        say(name, 1.0, f"{name} done in {seconds[name]:.1f} s")
        return out

    shutil.rmtree(sfm, ignore_errors=True)
    sfm.mkdir(parents=True)
    img_dir = sfm / "images"
    photos = phase("intake", lambda: intake.prepare_photos(photos_dir, img_dir, max_side), "reading photos")
    n = len(photos.names)
    kind = pipeline.choose_matcher(matcher, n)
    groups: dict[tuple[int, int], list[str]] = {}
    for k in photos.names:
        groups.setdefault(photos.sizes[k], []).append(photos.prepared[k])

    def on_image(k: int) -> None:
        say("mapping", min(k / n, 1.0), f"registered {min(k, n)} of {n}")

    def attempt(per_image: bool) -> tuple[object, Verdict]:
        """Features, matching and mapping with shared or per-photo cameras; the model and its verdict."""
        label = "per-image" if per_image else "shared"
        db = sfm / f"database-{label}.db"
        extract = lambda: pipeline.extract(db, img_dir, list(groups.values()), per_image=per_image)  # noqa: E731
        mapping = lambda: pipeline.reconstruct(db, img_dir, sfm / f"models-{label}", n, photos_dir,  # noqa: E731
                                               on_image)
        if per_image:  # timed as one "retry" phase
            extract()
            pipeline.match(db, kind)
            rec = mapping()
        else:
            phase("features", extract, f"extracting features from {n} photos")
            phase("matching", lambda: pipeline.match(db, kind), f"matching features ({kind})")
            rec = phase("mapping", mapping, "incremental mapping")
        return rec, judge.judge(judge.facts_of(rec, n, photos.exif_focal), cameras=label)

    rec, verdict = attempt(per_image=False)
    say("check", 1.0, f"model check: {verdict.summary()}")
    tried = [verdict]
    if not verdict.trusted:
        try:
            rec2, verdict2 = phase("retry", lambda: attempt(per_image=True),
                                   "the shared-camera model is implausible: mapping again with one camera per photo")
        except SceneError as exc:  # no model at all this time: the first one stands
            say("check", 1.0, f"one camera per photo: {exc}")
        else:
            say("check", 1.0, f"model check (one camera per photo): {verdict2.summary()}")
            tried.append(verdict2)
            if verdict2.score() > verdict.score():
                rec, verdict = rec2, verdict2
    model_dir = sfm / "sparse"
    model_dir.mkdir()
    rec.write(str(model_dir))
    if verdict.trusted:
        phase("undistortion", lambda: pipeline.undistort(model_dir, img_dir, sfm / "scene"), "undistorting")
    original = photos.original_of()
    registered = {original.get(im.name, im.name) for im in rec.images.values() if _has_pose(im)}
    unregistered = [k for k in photos.names if k not in registered]
    report = {"total": n, "registered": len(registered), "unregistered": unregistered,
              "skipped": photos.skipped, "notes": photos.notes, "seconds": seconds, "matcher": kind,
              "points": int(rec.num_points3D()), "scene_dir": str(sfm / "scene"), "names": original,
              "options": _options(matcher, max_side), "fingerprint": intake.fingerprint(photos_dir),
              "verdict": verdict.to_dict(), "attempts": [v.to_dict() for v in tried], "cached": False}
    if unregistered and verdict.trusted:
        msg = (f"{len(unregistered)} of {n} photos could not be registered and were dropped: "
               f"{', '.join(unregistered[:10])}{' ...' if len(unregistered) > 10 else ''}")
        report["notes"].append(msg)
        log.warning("sfm: %s", msg)
        say("mapping", 1.0, msg)
    for tmp in sfm.glob("database-*"):  # only the final model and images are needed to reopen
        tmp.unlink(missing_ok=True)
    for tmp in sfm.glob("models-*"):
        shutil.rmtree(tmp, ignore_errors=True)
    atomic.write_json(sfm / "report.json", report)
    return _trusted_or_raise(report, photos_dir)


def _trusted_or_raise(report: dict, photos_dir: Path) -> dict:
    """The report when its model passed the check (core.sfm.judge); else a SceneError with the reasons."""
    verdict = Verdict.from_dict(report.get("verdict") or {"trusted": True})
    if verdict.trusted:
        return report
    tried = " and ".join(a.get("cameras", "shared") for a in report.get("attempts", [])) or verdict.cameras
    raise SceneError(f"structure-from-motion found no plausible model of these {report['total']} photos "
                     f"(tried {tried} cameras; {report['registered']} registered): "
                     + "; ".join(verdict.reasons), photos_dir,
                     hint="photos taken with one fixed zoom, overlapping by more than half, with textured "
                          "surfaces in view, register reliably; photos that keep their EXIF focal length help")


def _has_pose(im) -> bool:
    flag = getattr(im, "has_pose", None)
    return bool(flag if flag is not None else getattr(im, "registered", True))


def _visibility(model_dir: Path, names: list[str]) -> list[np.ndarray]:
    """Per image in `names`: indices into the loader's point array of the points that image observes."""
    rec = read_model(model_dir)
    index = {pid: i for i, pid in enumerate(rec.points3D.keys())}  # the loader's order
    by_name = {im.name: im for im in rec.images.values()}
    out = []
    for name in names:
        im = by_name[name]
        ids = [p.point3D_id for p in im.points2D if p.has_point3D()]
        out.append(np.unique(np.asarray([index[i] for i in ids if i in index], dtype=np.int64)))
    return out


def sfm_scene(photos_dir: str | Path, workspace_dir: str | Path | None = None, progress: Progress | None = None,
              matcher: str = "auto", downscale: float = 1.0, kind: str | None = None, splits=None,
              force: bool = False, max_size: int = 0) -> Scene:
    """A scene from a folder of photos: SfM (cached in `workspace_dir`, default beside the photos).

    The scene keeps the SfM points (with per-image visibility of the train split, for sparse depth),
    its kind is chosen from the camera layout unless `kind` is given, and `extra['sfm']` holds the report.
    """
    from repaint_nerf.core.scene.kinds import detect_kind
    from repaint_nerf.core.scene.normalize import normalize_scene

    if kind is not None and kind not in SCENE_KINDS:
        raise SceneError(f"unknown scene kind {kind!r}", hint=f"use one of {', '.join(SCENE_KINDS)}")
    report = run_sfm(photos_dir, workspace_dir, progress, matcher, force=force)
    scene_dir = Path(report["scene_dir"])
    scene = load_colmap(scene_dir, downscale=downscale, splits=splits, max_size=max_size)
    scene.root = Path(photos_dir)
    scene.format = "photos"
    originals = report.get("names", {})
    for split in scene.splits.values():
        split.names = [originals.get(nm, nm) for nm in split.names]
    if "train" in scene.splits and scene.points is not None:
        prepared = {v: k for k, v in originals.items()}
        scene.extra["visibility"] = _visibility(find_model(scene_dir),
                                                [prepared.get(nm, nm) for nm in scene.train.names])
    scene.extra["sfm"] = {k: v for k, v in report.items() if k not in ("fingerprint", "names")}
    if kind is None:
        kind, why = detect_kind(scene)
        scene.extra["kind_reason"] = why
    scene.kind = kind
    normalize_scene(scene)  # a scene is always handed out in field space, whoever asks for it
    return scene
