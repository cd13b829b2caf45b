"""The camera model: rays at pixel centres, projection, the OpenCV <-> OpenGL convention, scaling."""
from __future__ import annotations

import numpy as np
import torch

from repaint_nerf.core.scene.cameras import Cameras, look_at, opencv_to_opengl


def _cams(n=4, w=40, h=30, seed=0) -> Cameras:
    rng = np.random.default_rng(seed)
    poses = [look_at(rng.uniform(-4, 4, 3) + [0, 0, 5], rng.uniform(-0.3, 0.3, 3)) for _ in range(n)]
    return Cameras.create(np.stack(poses), rng.uniform(30, 50, n), rng.uniform(30, 50, n),
                          rng.uniform(15, 25, n), rng.uniform(12, 18, n), w, h)


def test_ray_through_pixel_centre_hits_the_projected_point():
    cams = _cams()
    g = torch.Generator().manual_seed(1)
    for i in range(len(cams)):
        pts = torch.randn(50, 3, generator=g) * 0.5
        uv, z = cams.project(pts, i)
        assert torch.all(z > 0)
        # uv are continuous coordinates with pixel centres at +0.5, so pixel index = uv - 0.5
        o, d, dz = cams.rays(torch.full((50,), i), uv[:, 0] - 0.5, uv[:, 1] - 0.5)
        t = z / dz  # z-depth -> distance along the ray
        assert torch.allclose(o + t[:, None] * d, pts, atol=1e-4)
        assert torch.allclose(d.norm(dim=-1), torch.ones(50), atol=1e-6)


def test_pixel_ray_projects_back_to_the_pixel_centre():
    cams = _cams(n=2)
    idx = torch.zeros(6, dtype=torch.long)
    u = torch.tensor([0, 39, 0, 39, 20, 7])
    v = torch.tensor([0, 0, 29, 29, 15, 3])
    o, d, dz = cams.rays(idx, u, v)
    z = torch.linspace(1.0, 6.0, 6)
    uv, depth = cams.project(o + (z / dz)[:, None] * d, 0)
    assert torch.allclose(uv, torch.stack([u, v], -1).float() + 0.5, atol=1e-3)
    assert torch.allclose(depth, z, atol=1e-4)


def test_opencv_opengl_round_trip_and_meaning():
    rng = np.random.default_rng(3)
    gl = np.stack([look_at(rng.uniform(-3, 3, 3) + [0, 0, 4], [0, 0, 0]) for _ in range(5)])
    cv = opencv_to_opengl(gl)
    assert np.allclose(opencv_to_opengl(cv), gl)
    # OpenCV pinhole projection (x right, y down, z forward) must agree with Cameras.project on the OpenGL pose.
    fx, fy, cx, cy = 35.0, 33.0, 19.0, 14.0
    cams = Cameras.create(gl, fx, fy, cx, cy, 40, 30)
    pts = rng.uniform(-0.5, 0.5, (20, 3))
    for i in range(5):
        w2c = np.linalg.inv(cv[i])
        pc = pts @ w2c[:3, :3].T + w2c[:3, 3]
        assert np.all(pc[:, 2] > 0)  # OpenCV: in front means +z
        ref = np.stack([fx * pc[:, 0] / pc[:, 2] + cx, fy * pc[:, 1] / pc[:, 2] + cy], -1)
        uv, z = cams.project(torch.tensor(pts, dtype=torch.float32), i)
        assert np.allclose(uv.numpy(), ref, atol=1e-3)
        assert np.allclose(z.numpy(), pc[:, 2], atol=1e-4)


def test_look_at_looks_down_minus_z_with_up_up():
    m = look_at([0, -5, 0], [0, 0, 0], up=(0, 0, 1))
    assert np.allclose(-m[:3, 2], [0, 1, 0])
    assert np.allclose(m[:3, 1], [0, 0, 1])
    assert np.isclose(np.linalg.det(m[:3, :3]), 1.0)


def test_scaled_cameras_keep_pixel_areas():
    cams = _cams(n=1, w=40, h=30)
    half = cams.scaled(0.5)
    assert (int(half.width[0]), int(half.height[0])) == (20, 15)
    # the centre of half-res pixel (u, v) is the corner between full-res pixels 2u..2u+1, 2v..2v+1
    u = torch.tensor([0, 5, 19])
    v = torch.tensor([0, 7, 14])
    _, d_half, _ = half.rays(torch.zeros(3, dtype=torch.long), u, v)
    _, d_full, _ = cams.rays(torch.zeros(3, dtype=torch.long), 2 * u + 0.5, 2 * v + 0.5)
    assert torch.allclose(d_half, d_full, atol=1e-6)


def test_in_image_is_in_front_and_inside_each_views_frame():
    """Cameras.in_image against plain comparisons: two views of different sizes, points behind, on the edges and
    just outside; the left/top edges count as inside, the right/bottom ones do not."""
    cams = Cameras.create(np.stack([look_at((0, 0, 3), (0, 0, 0), up=(0, 1, 0)),
                                    look_at((3, 0, 0), (0, 0, 0), up=(0, 1, 0))]), 20.0, 20.0, 8.0, 6.0,
                          [16, 32], [12, 24])
    views = torch.tensor([0, 1])
    uv = torch.tensor([[[0.0, 0.0], [15.99, 11.99], [16.0, 5.0], [-0.01, 5.0], [8.0, 12.0]]] * 2)
    z = torch.tensor([[1.0, 1.0, 1.0, 1.0, 1.0], [1.0, 1.0, 1.0, 1.0, -1.0]])
    got = cams.in_image(uv, z, views)
    assert got.tolist() == [[True, True, False, False, False], [True, True, True, False, False]]
    pts = torch.randn(200, 3)
    uv, z = cams.project_views(pts, views)
    w, h = torch.tensor([[16.0], [32.0]]), torch.tensor([[12.0], [24.0]])
    plain = (z > 0) & (uv[..., 0] >= 0) & (uv[..., 0] < w) & (uv[..., 1] >= 0) & (uv[..., 1] < h)
    assert torch.equal(cams.in_image(uv, z, views), plain)
