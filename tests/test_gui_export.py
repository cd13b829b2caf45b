"""The editor's Export section in a real window under Xvfb (injected imgui input): an export reports where its file
went, a long one shows progress and is cancelled with no file left, key views become a nerfstudio camera path and a
video along it that decodes as H.264."""
from __future__ import annotations

import json
import time
from pathlib import Path
from types import SimpleNamespace

import imageio_ffmpeg
import numpy as np
import pytest

from repaint_nerf.core.engine import Engine
from repaint_nerf.core.export.common import checkpoint
from repaint_nerf.core.scene.scene import Normalization
from test_gui_editor import AnalyticEngine, click, frames, run_until

pytestmark = pytest.mark.gui


class ExportingEngine(AnalyticEngine):
    """The analytic double with exports: the real camera-path and video code, a mesh written by trimesh, and a slow
    dataset export that honours cancel."""

    export_camera_path = Engine.export_camera_path
    export_turntable = Engine.export_turntable
    _keys_world = Engine._keys_world
    _need_scene = Engine._need_scene

    def __init__(self):
        super().__init__()
        self.scene = SimpleNamespace(norm=Normalization(np.array([1.0, 0.0, 0.0]), 0.5))

    def render(self, cameras, scale=1.0, outputs=("rgb",), cancel=None, full=False, stride=1.0):
        return super().render(cameras, scale, outputs, cancel)

    def export_mesh(self, path, selection=False, resolution=256, cancel=None, progress=None):
        import trimesh

        from repaint_nerf.core.export.mesh import write_mesh

        for i in range(5):
            checkpoint(cancel, progress, i / 5, "sampling the density")
        out = write_mesh(trimesh.creation.icosphere(subdivisions=2), path)
        return {"path": str(out), "vertices": 162, "faces": 320, "bytes": out.stat().st_size}

    def export_dataset(self, folder, cancel=None, progress=None):
        for i in range(400):  # ~8 s unless cancelled
            checkpoint(cancel, progress, i / 400, f"rendering view {i + 1}/400")
            time.sleep(0.02)
        Path(folder).mkdir(parents=True)
        return {"path": str(folder), "frames": 400, "bytes": 0}


@pytest.fixture(scope="module")
def editor(xvfb_display):
    from repaint_nerf.app.editor import EditorApp
    from repaint_nerf.app.window import Window

    window = Window(width=1000, height=960)
    app = EditorApp(window, ExportingEngine(), None, worker_kwargs={"train_budget_s": 0.02, "rest_s": 0.05,
                                                                    "preview_interval_s": 0.05})
    run_until(app, lambda: app.camera is not None and app.last_frame is not None)
    app.set_training(False)
    click(app, "export_section")
    yield app
    app.close()
    window.close()


def _said(app, text):
    return any(text in m for _, m in app.state.messages)


def test_mesh_export_names_where_the_file_went(editor, tmp_path):
    editor.state.mesh_path = str(tmp_path / "sub" / "mesh.ply")
    frames(editor, 2)
    click(editor, "export_mesh")
    run_until(editor, lambda: _said(editor, "mesh.ply"))
    assert _said(editor, f"wrote {tmp_path / 'sub' / 'mesh.ply'} (162 vertices, 320 faces")
    assert (tmp_path / "sub" / "mesh.ply").stat().st_size > 0 and editor.state.export_job is None


def test_long_export_shows_progress_and_cancels(editor, tmp_path):
    editor.state.dataset_path = str(tmp_path / "dataset")
    frames(editor, 2)
    click(editor, "export_dataset")
    run_until(editor, lambda: editor.state.export_job is not None and editor.state.export_job.fraction > 0.05)
    assert "rendering view" in editor.state.export_job.text
    click(editor, "export_cancel")
    run_until(editor, lambda: editor.state.export_job is None)
    assert _said(editor, "export cancelled") and not (tmp_path / "dataset").exists()


def test_key_views_make_a_camera_path_and_a_video_along_it(editor, tmp_path):
    s = editor.state
    s.path_keys.clear()
    for yaw in (0.0, 40.0, 80.0):
        editor.camera.orbit(yaw, 0.0)
        frames(editor, 2)
        click(editor, "path_add")
    assert len(s.path_keys) == 3
    s.video_height = 64
    s.path_frames, s.camera_path_file, s.export_video_path = 12, str(tmp_path / "path.json"), str(tmp_path / "path.mp4")
    frames(editor, 2)
    click(editor, "path_save")
    run_until(editor, lambda: _said(editor, "path.json"))
    meta = json.loads((tmp_path / "path.json").read_text())
    assert len(meta["camera_path"]) == 12 and len(meta["keyframes"]) == 3 and meta["render_height"] == 64
    first = np.asarray(meta["camera_path"][0]["camera_to_world"]).reshape(4, 4)
    assert np.allclose(first[:3, 3], editor.engine.scene.norm.to_world(s.path_keys[0][0][:3, 3]))  # world units
    click(editor, "export_video")
    assert editor.state.export_job is not None or _said(editor, "path.mp4"), (editor.cache["items"]["export_video"],
                                                                              editor.state.messages)
    run_until(editor, lambda: _said(editor, "path.mp4"), timeout=60)
    meta = next(imageio_ffmpeg.read_frames(str(tmp_path / "path.mp4")))
    assert meta["size"][1] == 64 and meta["size"][0] % 2 == 0
    assert meta["codec"] == "h264" and imageio_ffmpeg.count_frames_and_secs(str(tmp_path / "path.mp4"))[0] == 12
