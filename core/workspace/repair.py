"""`repair`: bring a damaged workspace back to one that opens, keeping every version whose file is whole.

Like `git fsck` it hashes every file (open only hashes what it reads). What is damaged, foreign or unreadable
is moved under WS/damaged/ (never deleted); workspace.json, the version index and settings.json are rebuilt
from the version files' own stamps; the newest good version stays current; masks and teacher caches that were
set aside are recomputed from the saved selection and the photos (core.workspace.recompute). Each action is one
line of the returned list; a healthy workspace gives an empty list and is not written to.
"""
from __future__ import annotations

import json
import shutil
from collections import Counter
from dataclasses import fields
from pathlib import Path
from typing import Any

from repaint_nerf.core.errors import WorkspaceError
from repaint_nerf.core.workspace import atomic, integrity
from repaint_nerf.core.workspace.rebuild import rebuild_index
from repaint_nerf.core.workspace.workspace import (FORMAT_VERSION, MARKER, SUBDIRS, VersionInfo, Workspace,
                                                   _valid_index, new_marker)

DAMAGED = "damaged"
_INFO_KEYS = {f.name for f in fields(VersionInfo)}


class _Repair:
    """One repair run over `root`: collects the action lines and the follow-up work (what to recompute)."""

    def __init__(self, root: Path):
        self.root = root
        self.actions: list[str] = []
        self.recompute: set[str] = set()

    def say(self, line: str) -> None:
        self.actions.append(line)

    def set_aside(self, path: Path, why: str) -> None:
        """Move `path` under WS/damaged/ (keeping its relative path; a number added when taken) and say so."""
        rel = path.relative_to(self.root)
        dest = self.root / DAMAGED / rel
        n = 0
        while dest.exists():
            n += 1
            dest = self.root / DAMAGED / rel.with_name(f"{rel.name}.{n}")
        dest.parent.mkdir(parents=True, exist_ok=True)
        shutil.move(str(path), str(dest))
        self.say(f"{rel}: {why}; set aside as {dest.relative_to(self.root)}")


def _first_line(exc: BaseException) -> str:
    text = str(exc).splitlines()[0] if str(exc) else exc.__class__.__name__
    return text.split(": ", 1)[1] if text.startswith("/") and ": " in text else text


def _read_json(path: Path) -> tuple[Any, str | None]:
    """(parsed JSON, None) or (None, what is wrong with the file: unreadable, empty, not JSON, altered)."""
    try:
        data = path.read_bytes()
    except OSError as exc:
        return None, f"cannot be read ({exc.strerror or exc})"
    if not data.strip():
        return None, "it is empty"
    try:
        text = data.decode("utf-8")
        obj = json.loads(text)
    except (UnicodeDecodeError, ValueError):
        return None, "it is not valid JSON (truncated or altered)"
    if integrity.check_json_text(text, obj) is False:
        return None, "its content hash does not match (altered)"
    return obj, None


# -- version files ---------------------------------------------------------------------------------------
def _check_version(path: Path, root: Path, ws_id: str | None, indexed: dict | None) -> tuple[dict | None, str]:
    """(the version's index entry, '') for a whole version file of this workspace, else (None, the problem)."""
    from repaint_nerf.core.train.checkpoint import Checkpoint, read_header

    _refuse_newer(path)
    try:
        digest = integrity.verify_file(path, full=True)
        stamp = integrity.read_stamp(path)
        header = read_header(path)
        if digest is None:  # a file from before the seals: whole when every tensor reads
            Checkpoint.load(path)
    except (integrity.IntegrityError, OSError, WorkspaceError) as exc:
        return None, _first_line(exc)
    if stamp and ws_id and stamp.get("workspace") not in (None, ws_id):
        return None, "it belongs to another workspace"
    if stamp and stamp.get("id") != path.stem:
        return None, f"it is version {stamp.get('id')} of its workspace, not {path.stem}"
    if indexed and indexed.get("sha256") and indexed["sha256"] != digest:
        return None, "it is not the file this workspace saved (its content hash differs from the index)"
    info = dict(indexed or {k: v for k, v in (stamp or {}).items() if k in _INFO_KEYS})
    if "id" not in info:  # neither indexed nor stamped: what the header says
        info = {"id": path.stem, "name": "recovered", "created": path.stat().st_mtime, "parent": None,
                "kind": header.kind}
    info.update(file=str(path.relative_to(root)), sha256=digest, stat=integrity.stat_key(path))
    return info, ""


def _without_stats(index: dict) -> dict:
    """The index without its seal and the files' recorded identities (what a copied workspace changes)."""
    return {**{k: v for k, v in index.items() if k != integrity.JSON_SEAL},
            "versions": {v: {k: x for k, x in info.items() if k != "stat"} for v, info in index["versions"].items()}}


def _refuse_newer(path: Path) -> None:
    """A version written by a newer program is not damage: repair stops rather than set it aside."""
    from repaint_nerf.core.train.header import FORMAT_VERSION as HEADER_FORMAT, HEADER_KEY

    try:
        fmt = json.loads(integrity.read_metadata(path).get(HEADER_KEY, "{}")).get("format")
    except (integrity.IntegrityError, OSError, ValueError, AttributeError):
        return  # unreadable: the checks that follow say how
    if isinstance(fmt, int) and fmt > HEADER_FORMAT:
        raise WorkspaceError(f"this version was written by a newer repaint-nerf (format {fmt}); nothing was changed",
                             path, hint="repair the workspace with the program version that wrote it")


def _old_index(rep: _Repair) -> dict | None:
    """The version index when it is readable and whole, else None (a damaged one is set aside)."""
    path = rep.root / "versions" / "index.json"
    if not path.exists():
        return None
    data, problem = _read_json(path)
    if problem is None and not _valid_index(data):
        problem = "it is not a valid version index"
    if problem:
        rep.set_aside(path, problem)
        return None
    return data


def _repair_versions(rep: _Repair, ws_id: str | None) -> dict[str, dict]:
    """Check every version file, set aside the bad ones and rewrite the index over the good; returns the good."""
    root = rep.root
    old = _old_index(rep)
    indexed = dict(old["versions"]) if old else {}
    files = {p.stem: p for p in sorted((root / "versions").glob("v*.safetensors")) if p.stem[1:].isdigit()}
    good: dict[str, dict] = {}
    for vid, path in files.items():
        info, problem = _check_version(path, root, ws_id, indexed.get(vid))
        if info is None:
            rep.set_aside(path, problem)
        else:
            good[vid] = info
    for vid in sorted(set(indexed) - set(files)):
        rep.say(f"version {vid} ({indexed[vid].get('name')!r}): its file is missing; it leaves the index")
    new = rebuild_index(good, old)
    if old is not None and _without_stats(new) == _without_stats(old) and integrity.JSON_SEAL in old:
        if new != {k: v for k, v in old.items() if k != integrity.JSON_SEAL}:  # only the files' identities moved
            atomic.write_sealed_json(root / "versions" / "index.json", new)  # (a copy): no repair
    elif good or old is not None:
        atomic.write_sealed_json(root / "versions" / "index.json", new)
        cur = new["history"][new["current"]] if new["current"] >= 0 else None
        rep.say(f"versions/index.json: {'rebuilt' if old is None else 'updated'} over {len(good)} good "
                f"version(s)" + (f", current {cur} ({good[cur]['name']!r})" if cur else ""))
    return good


# -- workspace.json and settings.json ----------------------------------------------------------------------
def _stamps(root: Path) -> list[dict]:
    """The stamps of the version files that have one (newest first), read from their headers only."""
    out = []
    for p in sorted((root / "versions").glob("v*.safetensors"), reverse=True):
        try:
            stamp = integrity.read_stamp(p)
        except (integrity.IntegrityError, OSError):
            continue
        if stamp:
            out.append(stamp)
    return out


def _repair_marker(rep: _Repair) -> str | None:
    """workspace.json made readable (rewritten with the identity its versions carry); returns the identity."""
    path = rep.root / MARKER
    data, problem = _read_json(path) if path.exists() else (None, "it is missing")
    if problem is None and not isinstance(data, dict):
        problem = "it is not a JSON object"
    if problem is None:
        fmt = data.get("format")
        if fmt != FORMAT_VERSION:
            raise WorkspaceError(f"workspace format version {fmt!r}; this program repairs version {FORMAT_VERSION}",
                                 path, hint="use the repaint-nerf version that wrote it")
        if data.get("id"):
            return str(data["id"])
    ids = Counter(s["workspace"] for s in _stamps(rep.root) if s.get("workspace"))
    marker = {**(data if problem is None else {}), **new_marker()}
    if ids:
        marker["id"] = ids.most_common(1)[0][0]  # the identity its own versions were saved under
    if problem and path.exists():
        rep.set_aside(path, problem)
    atomic.write_json(path, marker)
    rep.say(f"{MARKER}: " + ("rewritten" if problem else "given an identity") + " (workspace id " + marker["id"][:8]
            + "...)")
    return marker["id"]


def _migrate_settings(settings: dict) -> list[str]:
    """Bring settings of an older format up to date in place (the nested 'models' map became one key per model
    kind); returns what changed."""
    from repaint_nerf.core.models.paths import KINDS

    changed = []
    models = settings.pop("models", None)
    if models is not None:
        for kind, value in (models.items() if isinstance(models, dict) else ()):
            if kind in KINDS and value and KINDS[kind].settings_key not in settings:
                settings[KINDS[kind].settings_key] = value
                changed.append(f"models.{kind} -> {KINDS[kind].settings_key}")
        changed = changed or ["dropped the empty 'models' map"]
    return changed


def _repair_settings(rep: _Repair, good: dict[str, dict]) -> None:
    """settings.json readable and current: rebuilt from the newest good version's stamp when damaged, an older
    format migrated, the scene filled in from the version headers when it went missing."""
    path = rep.root / "settings.json"
    data, problem = _read_json(path) if path.exists() else (None, "it is missing")
    if problem is None and not isinstance(data, dict):
        problem = "it is not a JSON object"
    if problem is None:
        notes = _migrate_settings(data)
        if notes:
            atomic.write_json(path, data)
            rep.say(f"settings.json: older format brought up to date ({', '.join(notes)})")
        if data.get("scene") or not good:
            return
    settings = {} if problem else data
    source = None
    for stamp in _stamps(rep.root):
        if stamp.get("id") in good and isinstance(stamp.get("settings"), dict):
            settings, source = {**stamp["settings"], **settings}, stamp["id"]
            break
    if not settings.get("scene"):
        settings.update(_scene_from_headers(rep.root, good))
        source = source or "the version headers"
    if problem and path.exists():
        rep.set_aside(path, problem)
    _migrate_settings(settings)
    atomic.write_json(path, settings)
    rep.say(f"settings.json: {'rebuilt' if problem else 'scene filled in'} from {source or 'defaults'}")


def _scene_from_headers(root: Path, good: dict[str, dict]) -> dict:
    """{'scene': ..., 'kind': ...} from the newest good version whose header records its scene."""
    from repaint_nerf.core.train.checkpoint import read_header

    for vid in sorted(good, reverse=True):
        facts = read_header(root / good[vid]["file"]).scene
        if facts is not None and facts.root:
            return {"scene": facts.root, "kind": facts.kind}
    return {}


# -- selections, masks, caches, the training checkpoint ----------------------------------------------------
def _repair_selections(rep: _Repair) -> None:
    from repaint_nerf.core.select.selection import Selection

    for path in sorted((rep.root / "selections").glob("*.json")):
        data, problem = _read_json(path)
        if problem is None:
            try:
                Selection.from_dict(data)
            except (ValueError, KeyError, TypeError, AttributeError) as exc:
                problem = f"it is not a selection ({exc})"
        if problem:
            rep.set_aside(path, problem)


def _repair_masks(rep: _Repair) -> None:
    """Masks that do not read back whole are set aside together (they are one computation) and recomputed."""
    from repaint_nerf.core.select.masks import MASK_INDEX, load_masks

    folder = rep.root / "masks"
    files = sorted(p for p in folder.iterdir() if p.is_file()) if folder.is_dir() else []
    if not files:
        return
    try:
        load_masks(folder)
        return
    except WorkspaceError as exc:
        problem = _first_line(exc) if (folder / MASK_INDEX).is_file() else "the masks index is missing"
    for path in files:
        rep.set_aside(path, f"the masks do not read back whole ({problem})")
    rep.recompute.add("masks")


def _repair_sealed_files(rep: _Repair, folder: str, pattern: str, consequence: str, redo: str | None) -> None:
    """Set aside the safetensors files under WS/`folder` whose seal does not match or that are unreadable."""
    for path in sorted((rep.root / folder).glob(pattern)):
        try:
            integrity.verify_file(path, full=True)
            integrity.read_metadata(path)
        except (integrity.IntegrityError, OSError) as exc:
            rep.set_aside(path, f"{exc}; {consequence}")
            if redo:
                rep.recompute.add(redo)


def repair_files(root: str | Path) -> tuple[list[str], set[str]]:
    """The file part of `repair` (no scene needed): (action lines, what is left to recompute)."""
    root = Path(root)
    if not root.is_dir():
        raise WorkspaceError("no workspace folder here", root, hint="pass the folder of a repaint-nerf workspace")
    if not (root / MARKER).exists() and not (root / "versions").is_dir():
        raise WorkspaceError("this folder is not a repaint-nerf workspace (no workspace.json, no versions/)", root,
                             hint="pass the folder given to `repaint-nerf train --workspace`")
    rep = _Repair(root)
    for sub in SUBDIRS:
        (root / sub).mkdir(exist_ok=True)
    ws_id = _repair_marker(rep)
    for folder in (root, *(root / sub for sub in SUBDIRS)):
        for tmp in atomic.sweep_stale_temps(folder, older_than_s=-1.0):
            rep.say(f"{tmp.relative_to(root)}: removed (the unfinished temporary file of an interrupted save)")
    good = _repair_versions(rep, ws_id)
    _repair_settings(rep, good)
    _repair_sealed_files(rep, "checkpoints", "*.safetensors", "training resumes from the current version", None)
    _repair_sealed_files(rep, "teachers", "**/*.safetensors", "recomputed from the photos", "teachers")
    _repair_selections(rep)
    _repair_masks(rep)
    return rep.actions, rep.recompute


def repair_workspace(root: str | Path, recompute: bool = True) -> list[str]:
    """Repair the workspace at `root` (see the module docstring); returns one line per action, [] when healthy."""
    actions, todo = repair_files(root)
    if recompute and todo:
        from repaint_nerf.core.workspace.recompute import recompute_missing

        actions += recompute_missing(Workspace.open(root), todo)
    return actions

