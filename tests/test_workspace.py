"""Workspace: atomic writes keep the old file on failure; versions with undo/redo; clear errors."""
from __future__ import annotations

import json

import pytest
import torch

from repaint_nerf.core.errors import WorkspaceError
from repaint_nerf.core.train.checkpoint import Checkpoint
from repaint_nerf.core.workspace import atomic
from repaint_nerf.core.workspace.workspace import FORMAT_VERSION, Workspace


def _leftovers(folder):
    return [p.name for p in folder.iterdir() if p.name.endswith(".tmp")]


def test_atomic_open_failure_keeps_old_file(tmp_path):
    path = tmp_path / "settings.json"
    atomic.write_json(path, {"a": 1})
    with pytest.raises(RuntimeError):
        with atomic.atomic_open(path, "wb") as f:
            f.write(b"{\"a\": 2, half written")
            raise RuntimeError("disk full (simulated)")
    assert json.loads(path.read_text()) == {"a": 1}
    assert _leftovers(tmp_path) == []


def test_atomic_json_unserialisable_keeps_old_file(tmp_path):
    path = tmp_path / "x.json"
    atomic.write_json(path, [1, 2])
    with pytest.raises(TypeError):
        atomic.write_json(path, {"bad": object()})
    assert json.loads(path.read_text()) == [1, 2]
    assert _leftovers(tmp_path) == []


def test_atomic_safetensors_failure_keeps_old_file(tmp_path, monkeypatch):
    path = tmp_path / "w.safetensors"
    atomic.write_safetensors(path, {"x": torch.arange(4.0)})
    before = path.read_bytes()
    import safetensors.torch as st

    def broken(tensors, filename, metadata=None):
        with open(filename, "wb") as f:
            f.write(b"\x00" * 10)  # a partial write, then the failure
        raise OSError("simulated crash midway")

    monkeypatch.setattr(st, "save_file", broken)
    with pytest.raises(OSError):
        atomic.write_safetensors(path, {"x": torch.zeros(4)})
    assert path.read_bytes() == before
    assert _leftovers(tmp_path) == []


def test_atomic_write_replaces(tmp_path):
    path = tmp_path / "sub" / "b.bin"
    atomic.write_bytes(path, b"one")
    atomic.write_bytes(path, b"two")
    assert path.read_bytes() == b"two"


def _state(value: float) -> Checkpoint:
    return Checkpoint({"field.w": torch.full((3,), value)}, {"kind": "test", "value": value})


def test_versions_undo_redo(tmp_path):
    ws = Workspace.create(tmp_path / "ws", {"scene": "x"})
    assert ws.current_version is None and ws.undo() is None and ws.redo() is None
    v1 = ws.save_version("reconstruction", _state(1.0), kind="stage1")
    v2 = ws.save_version("edit a", _state(2.0))
    v3 = ws.save_version("edit b", _state(3.0))
    assert [v.id for v in ws.versions] == [v1.id, v2.id, v3.id]
    assert ws.current_version.id == v3.id and v3.parent == v2.id
    assert ws.undo().id == v2.id
    assert ws.undo().id == v1.id
    assert ws.undo() is None  # the reconstruction is the floor
    assert ws.current_version.id == v1.id
    assert ws.redo().id == v2.id
    # A new edit after an undo drops the undone one from the redo line, but never its file.
    v4 = ws.save_version("edit c", _state(4.0))
    assert [v.id for v in ws.versions] == [v1.id, v2.id, v4.id]
    assert ws.redo() is None and not ws.can_redo and ws.can_undo
    assert (ws.root / v3.file).exists()
    # The original reconstruction is intact and reloads.
    assert ws.original_version.id == v1.id
    ck = Checkpoint.load(ws.version_path(ws.original_version))
    assert torch.equal(ck.tensors["field.w"], torch.full((3,), 1.0)) and ck.header["value"] == 1.0
    # The state survives reopening.
    again = Workspace.open(ws.root)
    assert again.current_version.id == v4.id and again.settings["scene"] == "x"


def test_layout_and_settings(tmp_path):
    ws = Workspace.create(tmp_path / "ws")
    for sub in ("checkpoints", "teachers", "selections", "masks", "versions"):
        assert (ws.root / sub).is_dir()
    assert json.loads((ws.root / "workspace.json").read_text())["format"] == FORMAT_VERSION
    ws.update_settings(downscale=2.0)
    ws.update_settings(scene="/data/x")
    assert Workspace.open(ws.root).settings == {"downscale": 2.0, "scene": "/data/x"}


def test_bad_workspaces(tmp_path):
    with pytest.raises(WorkspaceError, match="no workspace folder"):
        Workspace.open(tmp_path / "missing")
    (tmp_path / "plain").mkdir()
    (tmp_path / "plain" / "photo.png").write_bytes(b"x")
    with pytest.raises(WorkspaceError, match="not a repaint-nerf workspace"):
        Workspace.open(tmp_path / "plain")
    with pytest.raises(WorkspaceError, match="not empty"):
        Workspace.create(tmp_path / "plain")
    (tmp_path / "afile").write_text("x")
    with pytest.raises(WorkspaceError, match="a file"):
        Workspace.create(tmp_path / "afile")
    ws = Workspace.create(tmp_path / "ws")
    atomic.write_json(ws.root / "workspace.json", {"format": FORMAT_VERSION + 1})
    with pytest.raises(WorkspaceError, match="format version"):
        Workspace.open(ws.root)
    (ws.root / "workspace.json").write_text("{not json")
    with pytest.raises(WorkspaceError, match="corrupt"):
        Workspace.open(ws.root)
