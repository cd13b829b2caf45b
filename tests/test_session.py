"""The one entry point (`core.session`) and the checkpoint header schema (`core.train.header`): a trained
workspace opens with its scene as trained, a field without a feature head is refused where selection needs
one, headers round-trip, and a workspace written in the older header format (1) still opens."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from repaint_nerf.core.errors import WorkspaceError
from repaint_nerf.core.train.checkpoint import HEADER_KEY, Checkpoint, read_header
from repaint_nerf.core.train.header import FORMAT_VERSION, CheckpointHeader, GridFacts
from repaint_nerf.core.workspace import atomic


@pytest.fixture(scope="module")
def trained_ws(scene_factory, tmp_path_factory):
    """A workspace with a 12-step stage-1 checkpoint and its reconstruction version (features on)."""
    from repaint_nerf.core.session import Teachers, start_reconstruction
    from repaint_nerf.core.train.stage1 import TrainConfig

    scene = scene_factory("demo", size=24, views=6, test_views=2)
    ws_root = tmp_path_factory.mktemp("ws")
    cfg = TrainConfig(rays_per_batch=256, grid_resolution=16, max_samples=64, grid_warmup_steps=4)
    rec = start_reconstruction(scene, ws_root, train_cfg=cfg, teachers=Teachers(depth=False), device="cpu")
    rec.trainer.train(steps=12)
    rec.trainer.save_checkpoint()
    rec.trainer.save_version("reconstruction")
    # Its teacher thread would go on caching features into the workspace, and a test's copytree of it failed when a
    # temporary file it listed had been renamed before it was copied (seen once in CI).
    rec.trainer.close()
    return ws_root, rec


def test_header_round_trip_and_newer_format_refused():
    h = CheckpointHeader(kind="stage1", field_config={"feature_dim": 8}, grid=GridFacts(16, 1, 1.0, {"a": 1}),
                         step=7, train_config={"max_samples": 99}, budget_steps=100)
    h.history.add({"step": 1, "loss": 0.5, "psnr": float("nan")})
    d = json.loads(json.dumps(h.to_dict()))  # through JSON, as in a file
    back = CheckpointHeader.from_dict(d)
    assert back.format == FORMAT_VERSION and back.step == 7 and back.grid == h.grid and back.feature_dim == 8
    assert back.max_samples == 99 and back.budget_steps == 100
    assert back.history.steps == [1.0] and back.history.loss == [0.5] and np.isnan(back.history.psnr[0])
    with pytest.raises(WorkspaceError, match="format version 3"):
        CheckpointHeader.from_dict({**d, "format": FORMAT_VERSION + 1}, "x.safetensors")
    with pytest.raises(WorkspaceError, match="malformed"):
        CheckpointHeader.from_dict({"format": FORMAT_VERSION, "kind": "stage1"})


def test_open_trained_restores_the_scene_as_trained(trained_ws):
    from repaint_nerf.core.session import open_trained

    ws_root, rec = trained_ws
    t = open_trained(ws_root, "cpu", need_features=True)
    assert t.header.kind == "stage1" and t.header.step == 12 and t.header.feature_dim > 0
    np.testing.assert_allclose(t.scene.norm.center, rec.scene.norm.center)
    assert t.scene.norm.scale == pytest.approx(rec.scene.norm.scale)
    assert len(t.header.history.steps) == 12  # the loss/PSNR curve travels with the field
    for k, v in rec.trainer.field.state_dict().items():
        torch.testing.assert_close(t.field.state_dict()[k], v)


def _copy(trained_ws, tmp_path, edit_header=None):
    """A copy of the trained workspace (the fixture stays untouched), its current version's raw header
    changed by `edit_header(dict)` when given."""
    import shutil

    from repaint_nerf.core.workspace.workspace import Workspace

    copy = tmp_path / "ws"
    shutil.copytree(trained_ws[0], copy)
    if edit_header is not None:
        ws = Workspace.open(copy)
        path = ws.version_path(ws.current_version)
        ck = Checkpoint.load(path)
        edit_header(ck.header)
        ck.save(path)
        _as_before_seals(copy)
    return copy


def _as_before_seals(root):
    """The version index as a program before content hashes wrote it (no digests): a version file rewritten in
    place, as these tests do to stand in for older files, is then not refused as not the one saved."""
    index = root / "versions" / "index.json"
    data = json.loads(index.read_text())
    data.pop("sha256", None)
    for info in data["versions"].values():
        info.pop("sha256", None)
        info.pop("stat", None)
    index.write_text(json.dumps(data))


def test_open_trained_uses_the_recorded_normalisation(trained_ws, tmp_path):
    """A field lives in the space it was trained in: the header's normalisation wins over a recomputed one."""
    from repaint_nerf.core.session import open_trained

    copy = _copy(trained_ws, tmp_path, lambda h: h["scene"].update(norm={"center": [0.25, -0.5, 1.0], "scale": 0.75}))
    t = open_trained(copy, "cpu")
    np.testing.assert_allclose(t.scene.norm.center, [0.25, -0.5, 1.0])
    assert t.scene.norm.scale == 0.75


def test_selection_needs_a_feature_head(trained_ws, tmp_path):
    from repaint_nerf.core.session import open_trained

    copy = _copy(trained_ws, tmp_path, lambda h: h["field_config"].update(feature_dim=0))
    with pytest.raises(WorkspaceError, match="without a feature head"):
        open_trained(copy, "cpu", need_features=True)


def test_format_1_workspace_still_opens(trained_ws, tmp_path):
    """Rewrite every file's header as format 1 wrote it (no history): the workspace opens for rendering, the
    engine resumes it, and saving writes the current format."""
    from repaint_nerf.core.engine import Engine
    from repaint_nerf.core.session import open_trained
    from repaint_nerf.core.workspace.workspace import Workspace

    copy = _copy(trained_ws, tmp_path)
    ws = Workspace.open(copy)
    for path in [ws.version_path(ws.current_version), *ws.checkpoints_dir.glob("*.safetensors")]:
        ck = Checkpoint.load(path)
        raw = {k: v for k, v in ck.header.items() if k != "history"}
        raw["format"] = 1
        atomic.write_safetensors(path, ck.tensors, {HEADER_KEY: json.dumps(raw)})
        assert read_header(path).format == 1
    _as_before_seals(copy)
    t = open_trained(copy, "cpu")
    assert t.header.format == 1 and t.header.step == 12 and t.header.history.steps == []
    eng = Engine("cpu", features=True, depth=False)
    info = eng.load(copy)
    assert info["step"] == 12
    eng.train_for(0.01)
    eng.save()
    assert read_header(ws.checkpoints_dir / "stage1.safetensors").format == FORMAT_VERSION


def test_reopened_workspace_brings_its_training_history(trained_ws, tmp_path):
    """The editor's loss/PSNR plot after reopening shows the steps trained before, not one step's axis."""
    from repaint_nerf.core.engine import Engine

    rec = trained_ws[1]
    copy = _copy(trained_ws, tmp_path)
    info = Engine("cpu", depth=False).load(copy)
    h = info["history"]
    assert h.steps == [float(s) for s in range(1, 13)] and len(h.loss) == len(h.psnr) == 12
    assert h.loss == rec.trainer.history.loss[:12] and all(np.isfinite(h.psnr))


def test_training_starts_before_the_teacher_has_finished(scene_factory, tmp_path, monkeypatch):
    """The feature teacher runs beside stage 1 (core.teachers.feature_stream): a teacher that has not made one
    code yet does not hold up the first steps, its choice is saved at once, and its codes join as they come.
    (The built-in teacher is gated; the default blend runs it too.)"""
    import threading

    from repaint_nerf.core.session import Teachers, start_reconstruction
    from repaint_nerf.core.teachers.feature_default import DefaultFeatureTeacher
    from repaint_nerf.core.teachers.stage1_targets import default_feature_model
    from repaint_nerf.core.train.stage1 import TrainConfig

    gate, real = threading.Event(), DefaultFeatureTeacher.__call__

    def gated(self, image):  # the stream's look at the teacher's channels (this thread) goes through
        if threading.current_thread() is not threading.main_thread():  # a stream's thread, ours or one left running
            gate.wait(60)
        return real(self, image)

    monkeypatch.setattr(DefaultFeatureTeacher, "__call__", gated)
    scene = scene_factory("demo", size=24, views=6, test_views=2)
    cfg = TrainConfig(rays_per_batch=256, grid_resolution=16, max_samples=64, grid_warmup_steps=4)
    rec = start_reconstruction(scene, tmp_path / "ws", train_cfg=cfg, teachers=Teachers(depth=False), device="cpu")
    tr = rec.trainer
    assert rec.workspace.settings["feature_model"] == default_feature_model().to_setting()
    assert "feature" not in tr.step() and tr.feature_stream is not None and not bool(tr.feature_ready.any())
    gate.set()
    assert tr.feature_stream.wait(timeout=60) is not None
    info = tr.step()
    assert "feature" in info and tr.feature_stream is None
    assert len(list((tmp_path / "ws").rglob("teachers/*/*/*.safetensors"))) == 6  # every view's codes, cached
