"""Orbit/pan/zoom/snap produce valid OpenGL camera-to-world poses that look where they should."""
import math

import numpy as np
import torch

from repaint_nerf.app.camera_control import CameraControl
from repaint_nerf.core.scene.cameras import Cameras, look_at


def _is_rotation(m):
    r = m[:3, :3]
    return np.allclose(r @ r.T, np.eye(3), atol=1e-9) and math.isclose(np.linalg.det(r), 1.0, abs_tol=1e-9)


def test_looks_at_target_down_minus_z():
    c = CameraControl(target=np.array([0.2, -0.1, 0.3]), distance=2.0, yaw=0.7, pitch=0.4)
    m = c.c2w()
    assert _is_rotation(m)
    fwd = -m[:3, 2]
    to_target = c.target - m[:3, 3]
    assert np.allclose(fwd, to_target / np.linalg.norm(to_target))
    assert math.isclose(np.linalg.norm(to_target), 2.0)
    # The target projects to the image centre.
    cams = c.cameras(64, 48)
    uv, z = cams.project(torch.tensor(c.target[None], dtype=torch.float32), 0)
    assert torch.allclose(uv, torch.tensor([[32.0, 24.0]]), atol=1e-3) and z.item() > 0


def test_orbit_keeps_distance_and_moves_the_eye():
    c = CameraControl(distance=3.0)
    e0 = c.eye()
    c.orbit(50, 20)
    assert math.isclose(np.linalg.norm(c.eye() - c.target), 3.0)
    assert not np.allclose(c.eye(), e0)
    for _ in range(1000):
        c.orbit(0, 100)
    assert c.pitch < math.pi / 2 and _is_rotation(c.c2w())


def test_drag_right_turns_the_scene_right():
    """Dragging right moves a point right of the target further right in the image (scene follows the mouse)."""
    c = CameraControl(distance=3.0, pitch=0.2)
    probe = torch.tensor((c.target + c.c2w()[:3, 0] * 0.3)[None], dtype=torch.float32)
    u0 = c.cameras(100, 100).project(probe, 0)[0][0, 0]
    c.pan(20, 0, 100)
    u1 = c.cameras(100, 100).project(probe, 0)[0][0, 0]
    assert u1 > u0


def test_zoom_and_fov_are_bounded():
    c = CameraControl(distance=2.0)
    c.zoom(1)
    assert c.distance < 2.0
    c.zoom(-2)
    assert c.distance > 2.0
    c.set_fov(500)
    assert c.fov_y == 120.0


def test_snap_to_training_view_reproduces_its_pose_and_reset_returns_home():
    c = CameraControl(up=np.array([0.0, 0.0, 1.0]))
    pose = look_at([1.5, -2.0, 1.0], [0.1, 0.2, 0.0])
    c.snap_to(pose)
    assert np.allclose(c.c2w(), pose, atol=1e-6)
    c.reset()
    assert not np.allclose(c.c2w(), pose, atol=1e-3)


def test_framing_targets_the_point_the_cameras_look_at():
    poses = [look_at([2 * math.cos(a), 2 * math.sin(a), 0.8], [0.1, 0.0, 0.2]) for a in np.linspace(0, 6, 8)]
    cams = Cameras.create(np.stack(poses), 50, 50, 32, 32, 64, 64)
    c = CameraControl.framing(cams)
    assert np.allclose(c.target, [0.1, 0.0, 0.2], atol=1e-5)
    m = c.c2w()  # eye and viewing direction of the first view (roll follows the mean up vector)
    assert np.allclose(m[:3, 3], poses[0][:3, 3], atol=1e-5) and np.allclose(m[:3, 2], poses[0][:3, 2], atol=1e-5)
