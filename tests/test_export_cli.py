"""The export interface other tools script against, end to end on a tiny trained workspace: `export mesh|points|
dataset`, `render --split turntable` writing H.264 .mp4 (+ GIF), `render --camera-path`, and clear errors."""
from __future__ import annotations

import json

import imageio_ffmpeg
import numpy as np
import pytest
import trimesh

from repaint_nerf.app.cli import main


@pytest.fixture(scope="module")
def workspace(tmp_path_factory):
    from repaint_nerf.core.synth.generate import make_scene

    root = tmp_path_factory.mktemp("export_cli")
    scene = make_scene("demo", root / "demo", size=24, views=6, seed=0, test_views=2)
    ws = root / "ws"
    assert main(["train", str(scene), "--workspace", str(ws), "--steps", "30", "--rays", "1024",
                 "--max-samples", "128", "--no-features"]) == 0
    return ws


def _field_box_world(ws):
    from repaint_nerf.core.export.dataset import field_aabb
    from repaint_nerf.core.export.source import open_workspace

    return np.asarray(field_aabb(open_workspace(ws, "cpu")))


def test_export_mesh_points_and_dataset(workspace, tmp_path, capsys):
    out = tmp_path / "scene.glb"
    assert main(["export", "mesh", str(workspace), "--out", str(out), "--resolution", "32", "--level", "1"]) == 0
    text = capsys.readouterr().out
    assert f"wrote {out}" in text and "world units" in text
    mesh = trimesh.load(out, force="mesh")
    lo, hi = _field_box_world(workspace)
    margin = 0.06 * (hi - lo)  # the box's fitting margin
    assert len(mesh.vertices) > 0 and np.all(mesh.bounds[0] >= lo - margin) and np.all(mesh.bounds[1] <= hi + margin)
    assert main(["export", "points", str(workspace), "--out", str(tmp_path / "p.ply"), "--max-points", "500"]) == 0
    assert 0 < len(trimesh.load(tmp_path / "p.ply").vertices) <= 500
    assert main(["export", "dataset", str(workspace), "--out", str(tmp_path / "ds")]) == 0
    meta = json.loads((tmp_path / "ds" / "transforms.json").read_text())
    assert len(meta["frames"]) == 6 and "mask_path" not in meta["frames"][0]  # nothing selected yet


def test_export_bad_input(workspace, tmp_path, capsys):
    assert main(["export", "mesh", str(workspace), "--out", str(tmp_path / "m.ply"), "--resolution", "16",
                 "--level", "1e12"]) == 2
    assert "no surface at density level" in capsys.readouterr().err
    assert main(["export", "mesh", str(workspace), "--out", str(tmp_path / "m.ply"), "--selection"]) == 2
    assert "nothing is selected" in capsys.readouterr().err
    assert main(["export", "mesh", str(workspace), "--out", str(tmp_path / "m.stl")]) == 2
    assert ".ply, .obj, .glb" in capsys.readouterr().err
    assert main(["export", "mesh", str(tmp_path / "nows"), "--out", str(tmp_path / "m.ply")]) == 2
    assert list(tmp_path.iterdir()) == []


def test_render_turntable_h264_and_camera_path(workspace, tmp_path, capsys):
    tt = tmp_path / "tt"
    assert main(["render", str(workspace), "--split", "turntable", "--out", str(tt), "--frames", "5", "--gif"]) == 0
    meta = next(imageio_ffmpeg.read_frames(str(tt / "turntable.mp4")))
    assert meta["codec"] == "h264" and meta["pix_fmt"].startswith("yuv420p") and meta["size"] == (24, 24)
    assert imageio_ffmpeg.count_frames_and_secs(str(tt / "turntable.mp4"))[0] == 5
    assert (tt / "turntable.gif").stat().st_size > 0
    from repaint_nerf.core.export.camera_path import CameraPath, interpolate, save_camera_path
    from repaint_nerf.core.scene.cameras import look_at

    keys = np.stack([look_at((4 * np.cos(a), 4 * np.sin(a), 2), (0, 0, 0.3)) for a in (0.0, 1.0, 2.0)])
    c2w, fov = interpolate(keys, [40.0, 40.0, 50.0], frames=4)
    save_camera_path(CameraPath(c2w, fov, 20, 16, fps=8), tmp_path / "camera_path.json")
    out = tmp_path / "path"
    assert main(["render", str(workspace), "--camera-path", str(tmp_path / "camera_path.json"), "--out", str(out)]) == 0
    assert len(list(out.glob("path_*.png"))) == 4
    meta = next(imageio_ffmpeg.read_frames(str(out / "camera_path.mp4")))
    assert meta["size"] == (20, 16) and meta["fps"] == 8
