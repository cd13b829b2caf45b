"""Videos decode with an independent reader (ffmpeg for H.264 .mp4, Pillow for GIF) with the right codec, frame
count and size; camera paths interpolate through their key views and survive a save/load in nerfstudio's layout."""
from __future__ import annotations

import json

import imageio.v3 as iio
import imageio_ffmpeg
import numpy as np
import pytest
import torch

from repaint_nerf.core.errors import UserError
from repaint_nerf.core.export.camera_path import CameraPath, interpolate, load_camera_path, save_camera_path
from repaint_nerf.core.export.video import write_video
from repaint_nerf.core.scene.cameras import look_at
from repaint_nerf.core.scene.scene import Normalization


def _frames(n=7, h=21, w=33):
    return [np.full((h, w, 3), (30 * i, 255 - 30 * i, 128), np.uint8) for i in range(n)]


def test_mp4_is_h264_yuv420p_with_every_frame(tmp_path):
    info = write_video(iter(_frames()), tmp_path / "v.mp4", fps=12)
    reader = imageio_ffmpeg.read_frames(str(tmp_path / "v.mp4"))
    meta = next(reader)
    decoded = [np.frombuffer(f, np.uint8).reshape(22, 34, 3) for f in reader]
    assert meta["codec"] == "h264" and meta["pix_fmt"].startswith("yuv420p") and meta["size"] == (34, 22)
    assert meta["fps"] == 12 and info["frames"] == len(decoded) == 7
    assert np.abs(decoded[3][:21, :33].astype(int) - _frames()[3]).mean() < 6  # colours survive the encoding


def test_gif_decodes_with_pillow(tmp_path):
    write_video([f.astype(np.float32) / 255 for f in _frames(5)], tmp_path / "v.gif", fps=10)
    frames = iio.imread(tmp_path / "v.gif", index=None)
    assert frames.shape[:3] == (5, 21, 33)
    assert np.abs(frames[2][..., :3].astype(int) - _frames(5)[2]).mean() < 8


def test_a_failed_or_empty_video_leaves_no_file(tmp_path):
    def broken():
        yield _frames(1)[0]
        raise KeyboardInterrupt  # killed midway

    with pytest.raises(KeyboardInterrupt):
        write_video(broken(), tmp_path / "v.mp4")
    with pytest.raises(UserError, match="no frames"):
        write_video([], tmp_path / "v.gif")
    with pytest.raises(UserError, match="format"):
        write_video(_frames(1), tmp_path / "v.avi")
    assert list(tmp_path.iterdir()) == []


def _keys():
    eyes = [(3, 0, 1), (0, 3, 1.5), (-3, 0, 1), (0, -3, 0.5)]
    return np.stack([look_at(e, (0, 0, 0)) for e in eyes]), np.array([40.0, 50.0, 40.0, 30.0])


def test_interpolation_passes_through_the_keys_smoothly():
    keys, fov = _keys()
    c2w, f = interpolate(keys, fov, frames=13)  # key k lands on frame 4k
    assert np.allclose(c2w[::4], keys, atol=1e-9) and np.allclose(f[::4], fov)
    rot = c2w[:, :3, :3]
    assert np.allclose(rot @ rot.transpose(0, 2, 1), np.eye(3), atol=1e-9)
    steps = np.linalg.norm(np.diff(c2w[:, :3, 3], axis=0), axis=1)
    assert steps.max() < 2.0 * steps.min()  # no jumps between frames
    loop, _ = interpolate(keys, fov, frames=16, loop=True)
    assert np.allclose(loop[::4], keys, atol=1e-9)
    assert np.linalg.norm(loop[-1, :3, 3] - keys[0, :3, 3]) < 2.0 * np.linalg.norm(loop[1, :3, 3] - loop[0, :3, 3])


def test_camera_path_json_round_trip_and_cameras(tmp_path):
    keys, fov = _keys()
    c2w, f = interpolate(keys, fov, frames=9)
    save_camera_path(CameraPath(c2w, f, 64, 48, fps=24), tmp_path / "camera_path.json")
    meta = json.loads((tmp_path / "camera_path.json").read_text())
    assert meta["render_width"] == 64 and len(meta["camera_path"]) == 9
    assert len(meta["camera_path"][0]["camera_to_world"]) == 16
    path = load_camera_path(tmp_path / "camera_path.json")
    assert np.allclose(path.c2w, c2w) and np.allclose(path.fov, f) and path.fps == 24
    norm = Normalization(np.array([1.0, 0.0, 0.0]), 0.25)
    cams = path.cameras(norm)
    # the world origin seen by key 0 (at frame 0) projects to the image centre; vertical fov sets fy
    uv, z = cams.project(torch.as_tensor(norm.to_field(np.zeros((1, 3))), dtype=torch.float32), 0)
    assert torch.allclose(uv, torch.tensor([[32.0, 24.0]]), atol=1e-3)
    assert float(cams.fy[0]) == pytest.approx(24 / np.tan(np.radians(fov[0]) / 2))
    bad = {"camera_path": [{"fov": 40}], "render_width": 4, "render_height": 4}
    (tmp_path / "bad.json").write_text(json.dumps(bad))
    with pytest.raises(UserError, match="frame 0 needs"):
        load_camera_path(tmp_path / "bad.json")
    with pytest.raises(UserError, match="no such camera path"):
        load_camera_path(tmp_path / "missing.json")
