"""The on-disk workspace of one scene: settings, checkpoints, teacher caches, selections, masks and
a linear edit history of versions with undo/redo (the first reconstruction is never overwritten).

Layout (format version `FORMAT_VERSION`)::

    WS/workspace.json        {"format": 1, "program": "repaint-nerf", "created": ..., "id": ...}
    WS/settings.json         user settings (scene path, downscale, model paths, ...)
    WS/checkpoints/          training checkpoints (overwritten atomically while training)
    WS/teachers/ selections/ masks/
    WS/versions/index.json   {"versions": {id: info}, "history": [ids], "current": i, "sha256": ...}
    WS/versions/<id>.safetensors   sealed, and stamped with its own index entry and the settings
    WS/damaged/              files `repair` set aside (core.workspace.repair); never read

Every file it reads is checked against its content hash (core.workspace.integrity) and refused when damaged,
with a WorkspaceDamaged error that offers `repaint-nerf repair`.
"""
from __future__ import annotations

import json
import re
import time
import uuid
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Protocol

from repaint_nerf.core.errors import WorkspaceDamaged, WorkspaceError
from repaint_nerf.core.workspace import atomic, integrity

FORMAT_VERSION = 1
MARKER = "workspace.json"
SUBDIRS = ("checkpoints", "teachers", "selections", "masks", "versions")


class SavableState(Protocol):
    """Anything that can write itself to a file (e.g. `core.train.checkpoint.Checkpoint`)."""

    def save(self, path: Path, stamp: dict | None = None) -> Any: ...


@dataclass
class VersionInfo:
    """One saved state of the scene's field: the reconstruction or an edit."""

    id: str
    name: str
    file: str  # relative to the workspace root
    created: float
    parent: str | None
    kind: str = "stage1"  # "stage1" (a reconstruction) or "edit"
    sha256: str | None = None  # the file's seal (core.workspace.integrity); None in indexes written before it
    stat: list | None = None  # the file's identity when saved or last checked (integrity.stat_key): unchanged, no hash


def _folder(name: str) -> property:
    """A read-only property: the workspace's folder `name` (one of SUBDIRS)."""
    return property(lambda self: self.root / name, doc=f"WS/{name}/")


def _read_json(path: Path) -> Any:
    return _parse(_read_text(path), path)


def _read_text(path: Path) -> str:
    try:
        return path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise
    except (OSError, UnicodeDecodeError) as exc:
        raise _damaged(f"cannot read this file: it is corrupt ({exc.__class__.__name__}: {exc})", path) from exc


def _parse(text: str, path: Path) -> Any:
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise _damaged(f"cannot read this file: it is corrupt ({exc.__class__.__name__}: {exc})", path) from exc


def _damaged(message: str, path: Path) -> WorkspaceDamaged:
    """A WorkspaceDamaged for a file of a workspace (it names the workspace to repair)."""
    return WorkspaceDamaged(message, path, workspace=integrity.workspace_of(path))


def _valid_index(data: Any) -> bool:
    """Whether a parsed versions/index.json has the shape the methods below rely on (found by fuzzing)."""
    if not isinstance(data, dict) or not {"versions", "history", "current"} <= set(data):
        return False
    versions, history, current = data["versions"], data["history"], data["current"]
    if not isinstance(versions, dict) or not isinstance(history, list) or type(current) is not int:
        return False
    names = {"id", "name", "file", "created", "parent", "kind", "sha256", "stat"}
    for vid, info in versions.items():
        if not (isinstance(info, dict) and {"id", "name", "file", "created", "parent"} <= set(info) <= names
                and info["id"] == vid and isinstance(info["file"], str)
                and isinstance(info.get("kind", "stage1"), str)
                and re.fullmatch(r"v\d+", vid)):
            return False
    return all(isinstance(v, str) and v in versions for v in history) and -1 <= current < len(history)


def new_marker() -> dict:
    """The content of a new workspace.json: format, program, creation time and a fresh identity."""
    return {"format": FORMAT_VERSION, "program": "repaint-nerf", "created": time.time(), "id": uuid.uuid4().hex}


class Workspace:
    """A workspace folder. Use `Workspace.open` (must exist) or `Workspace.create` / `open_or_create`."""

    def __init__(self, root: str | Path):
        self.root = Path(root)

    # -- opening -------------------------------------------------------------------------------
    @classmethod
    def create(cls, root: str | Path, settings: dict | None = None) -> "Workspace":
        """Create a new workspace in an empty or missing folder (an existing workspace is opened instead)."""
        root = Path(root)
        if root.exists() and not root.is_dir():
            raise WorkspaceError("this is a file, not a workspace folder", root,
                                 hint="pass a folder path for --workspace")
        if (root / MARKER).exists():
            ws = cls.open(root)
            if settings:
                ws.update_settings(**settings)
            return ws
        if root.exists() and any(root.iterdir()):
            raise WorkspaceError("the folder is not empty and is not a repaint-nerf workspace", root,
                                 hint="choose a new or empty folder for the workspace")
        try:
            root.mkdir(parents=True, exist_ok=True)
            for sub in SUBDIRS:
                (root / sub).mkdir(exist_ok=True)
            atomic.write_json(root / "settings.json", dict(settings or {}))
            atomic.write_json(root / MARKER, new_marker())
        except OSError as exc:
            raise WorkspaceError(f"cannot create the workspace ({exc.strerror or exc})", root,
                                 hint="choose a folder you can write to") from exc
        return cls(root)

    @classmethod
    def open(cls, root: str | Path) -> "Workspace":
        """Open an existing workspace; a missing folder, a non-workspace or another format version is a WorkspaceError."""
        root = Path(root)
        if not root.is_dir():
            raise WorkspaceError("no workspace folder here", root,
                                 hint="train first: repaint-nerf train SCENE --workspace " + str(root))
        marker = root / MARKER
        if not marker.exists() and (root / "versions").is_dir():
            raise WorkspaceDamaged("workspace.json is missing from this workspace", root, workspace=root)
        if not marker.exists():
            raise WorkspaceError("this folder is not a repaint-nerf workspace (no workspace.json)", root,
                                 hint="pass the folder given to `repaint-nerf train --workspace`")
        info = _read_json(marker)
        if not isinstance(info, dict):
            raise _damaged("workspace.json is not a JSON object", marker)
        fmt = info.get("format")
        if fmt != FORMAT_VERSION:
            raise WorkspaceError(f"workspace format version {fmt!r}; this program reads version {FORMAT_VERSION}",
                                 marker, hint="use the repaint-nerf version that wrote it, or train a new workspace")
        for sub in SUBDIRS:
            (root / sub).mkdir(exist_ok=True)
        for folder in (root, *(root / sub for sub in SUBDIRS)):
            atomic.sweep_stale_temps(folder)  # debris of saves killed midway; the files they replace are intact
        return cls(root)

    @classmethod
    def open_or_create(cls, root: str | Path, settings: dict | None = None) -> "Workspace":
        """Open the workspace at `root`, creating it if the folder is missing or empty."""
        return cls.create(root, settings)

    # -- folders and settings -----------------------------------------------------------------
    def path(self, *parts: str) -> Path:
        return self.root.joinpath(*parts)

    @property
    def id(self) -> str | None:
        """The workspace's identity (stamped into its versions, so a file from another workspace is told apart);
        None for a workspace created before it had one (`repair` gives it one)."""
        try:
            info = json.loads((self.root / MARKER).read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return None
        return info.get("id") if isinstance(info, dict) else None

    checkpoints_dir = _folder("checkpoints")
    teachers_dir = _folder("teachers")
    selections_dir = _folder("selections")
    masks_dir = _folder("masks")
    versions_dir = _folder("versions")

    @property
    def settings(self) -> dict:
        """The saved settings (a fresh dict; change them with `update_settings`)."""
        path = self.root / "settings.json"
        if not path.exists():
            if self._index_path().exists():  # every workspace is created with one: it was lost
                raise _damaged("settings.json is missing", path)
            return {}
        data = _read_json(path)
        if not isinstance(data, dict):
            raise _damaged("settings.json is not a JSON object", path)
        return data

    def update_settings(self, **values: Any) -> dict:
        """Merge `values` into settings.json (atomically) and return the result."""
        data = self.settings
        data.update(values)
        atomic.write_json(self.root / "settings.json", data)
        return data

    # -- versions ------------------------------------------------------------------------------
    def _index_path(self) -> Path:
        return self.versions_dir / "index.json"

    def _index(self) -> dict:
        path = self._index_path()
        if not path.exists():
            if any(self.versions_dir.glob("v*.safetensors")):  # versions saved, their index lost
                raise _damaged("the version index is missing (the version files are here)", path)
            return {"versions": {}, "history": [], "current": -1}
        text = _read_text(path)
        data = _parse(text, path)
        if not _valid_index(data):
            raise _damaged("the version index is malformed", path)
        if integrity.check_json_text(text, data) is False:
            raise _damaged("the version index is damaged (its content hash does not match)", path)
        return data

    def _write_index(self, data: dict) -> None:
        for info in data["versions"].values():  # versions checked since they were saved (e.g. in a copied workspace)
            key = integrity.checked_key(self.root / info["file"], info.get("sha256"))
            if key is not None:
                info["stat"] = key
        atomic.write_sealed_json(self._index_path(), data)

    @property
    def versions(self) -> list[VersionInfo]:
        """Versions on the undo/redo line, oldest first (the current one is `current_version`)."""
        idx = self._index()
        return [VersionInfo(**idx["versions"][v]) for v in idx["history"]]

    @property
    def current_version(self) -> VersionInfo | None:
        idx = self._index()
        if idx["current"] < 0:
            return None
        return VersionInfo(**idx["versions"][idx["history"][idx["current"]]])

    @property
    def original_version(self) -> VersionInfo | None:
        """The first reconstruction saved in this workspace (never overwritten by edits)."""
        idx = self._index()
        for info in sorted(idx["versions"].values(), key=lambda v: v["id"]):
            if info.get("kind") == "stage1":
                return VersionInfo(**info)
        return None

    def version_path(self, info: VersionInfo) -> Path:
        """The version's file, checked to be there and to be the file this workspace saved (its seal against the
        index: a header read); an entry outside the workspace, a missing or a foreign file is a WorkspaceError."""
        p = (self.root / str(info.file)).resolve()
        if Path(str(info.file)).is_absolute() or not p.is_relative_to(self.root.resolve()):
            raise _damaged(f"version {info.id} points outside the workspace ({info.file!r})", self._index_path())
        if integrity.trust(p, info.stat, info.sha256):  # the file as saved: its reader skips the hash
            return p
        where = f"version {info.id} ({info.name!r})"
        if not p.is_file():
            raise _damaged(f"{where}: its file is missing", p)
        if info.sha256 is not None:
            try:
                stored = integrity.stored_digest(p)
            except (integrity.IntegrityError, OSError) as exc:
                raise _damaged(f"{where} is refused: {exc}", p) from exc
            if stored != info.sha256:
                raise _damaged(f"{where} is refused: the file is not the one this workspace saved (its content "
                               "hash differs from the index)", p)
        return p

    def save_version(self, name: str, state: SavableState, kind: str = "edit") -> VersionInfo:
        """Write `state` as a new version after the current one and make it current.

        Versions after the current one (undone edits) leave the redo line; their files stay on disk.
        """
        idx = self._index()
        n = 1 + max((int(v[1:]) for v in idx["versions"]), default=0)
        vid = f"v{n:04d}"
        rel = f"versions/{vid}.safetensors"
        parent = idx["history"][idx["current"]] if idx["current"] >= 0 else None
        info = VersionInfo(id=vid, name=name, file=rel, created=time.time(), parent=parent, kind=kind)
        # the file carries its own index entry and the settings, so `repair` can rebuild both from the versions
        stamp = {**asdict(info), "workspace": self.id, "settings": self.settings}
        del stamp["sha256"], stamp["stat"]
        state.save(self.root / rel, stamp=stamp)
        info.sha256 = integrity.stored_digest(self.root / rel)
        info.stat = integrity.stat_key(self.root / rel)
        integrity.remember(self.root / rel, info.stat, info.sha256)
        idx["versions"][vid] = asdict(info)
        idx["history"] = idx["history"][: idx["current"] + 1] + [vid]
        idx["current"] = len(idx["history"]) - 1
        self._write_index(idx)
        return info

    @property
    def can_undo(self) -> bool:
        return self._index()["current"] > 0

    @property
    def can_redo(self) -> bool:
        idx = self._index()
        return idx["current"] < len(idx["history"]) - 1

    def undo(self) -> VersionInfo | None:
        """Step back to the previous version and return it; None (and no change) when there is none."""
        idx = self._index()
        if idx["current"] <= 0:
            return None
        idx["current"] -= 1
        self._write_index(idx)
        return self.current_version

    def redo(self) -> VersionInfo | None:
        """Step forward to the next (undone) version and return it; None when there is none."""
        idx = self._index()
        if idx["current"] >= len(idx["history"]) - 1:
            return None
        idx["current"] += 1
        self._write_index(idx)
        return self.current_version
