"""Depth teachers: robust scale/shift alignment, sparse depth from known points, triangulation with
known poses on a synthetic scene against its ground-truth depth, DepthPriors lookups and storage,
and the ONNX monocular-depth backend."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from repaint_nerf.core.errors import ModelNotFoundError
from repaint_nerf.core.scene.cameras import Cameras, look_at
from repaint_nerf.core.teachers.align import align_inverse_depth, fit_scale_shift
from repaint_nerf.core.teachers.depth import DenseDepth, DepthPriors, SparseDepth
from repaint_nerf.core.teachers.depth_sparse import depth_from_points, project_points, triangulate_known_poses


def test_alignment_recovers_scale_and_shift_with_outliers():
    rng = np.random.default_rng(0)
    x = rng.uniform(0.1, 2.0, 500)
    y = 3.7 * x - 0.8 + rng.normal(0, 0.005, x.size)
    bad = rng.choice(x.size, 150, replace=False)  # 30% gross outliers
    y[bad] = rng.uniform(-5, 10, bad.size)
    s, t = fit_scale_shift(x, y)
    assert s == pytest.approx(3.7, rel=5e-3) and t == pytest.approx(-0.8, abs=1e-2)
    naive = np.polyfit(x, y, 1)
    assert abs(naive[0] - 3.7) > 0.05  # the outliers do matter: plain least squares misses


def test_inverse_depth_alignment_gives_metric_depth():
    rng = np.random.default_rng(1)
    z_true = rng.uniform(2.0, 6.0, (20, 30)).astype(np.float32)
    rel = ((1.0 / z_true) - 0.05) / 2.5  # relative inverse depth: unknown scale 2.5 and shift 0.05
    u, v = rng.uniform(0, 30, 80), rng.uniform(0, 20, 80)
    z = z_true[v.astype(int), u.astype(int)]
    depth, valid, (s, t) = align_inverse_depth(rel, u, v, z)
    assert valid.all()
    np.testing.assert_allclose(depth, z_true, rtol=1e-4)


def ring_cameras(n: int = 8, size: int = 64, radius: float = 4.0) -> Cameras:
    c2w = [look_at((radius * np.cos(a), radius * np.sin(a), 1.5), (0, 0, 0.3)) for a in
           np.linspace(0, 2 * np.pi, n, endpoint=False)]
    f = 0.5 * size / np.tan(0.4)
    return Cameras.create(np.stack(c2w), f, f, size / 2, size / 2, size, size)


def test_sparse_depth_from_points_is_the_analytic_z():
    cams = ring_cameras()
    rng = np.random.default_rng(2)
    pts = rng.uniform(-0.5, 0.5, (300, 3))
    for i in (0, 3):
        sp = project_points(pts, cams, i, visible=np.arange(len(pts)))
        c2w = cams.c2w[i].double().numpy()
        pc = (pts - c2w[:3, 3]) @ c2w[:3, :3]  # camera coordinates
        np.testing.assert_allclose(np.sort(sp.z), np.sort(-pc[:, 2]).astype(np.float32), rtol=1e-5)
        uv, z = cams.project(torch.from_numpy(pts).float(), i)
        np.testing.assert_allclose(np.sort(sp.u), np.sort(uv[:, 0].numpy()), atol=1e-3)
    # points behind the camera are dropped, occluded ones are removed by the z-buffer
    eye = cams.c2w[0, :3, 3].numpy().astype(np.float64)
    fwd = -cams.c2w[0, :3, 2].numpy().astype(np.float64)
    near, far, behind = eye + 1.0 * fwd, eye + 3.0 * fwd, eye - 1.0 * fwd
    sp = project_points(np.stack([near, far, behind]), cams, 0)
    np.testing.assert_allclose(sp.z, [1.0], rtol=1e-5)
    priors = depth_from_points(np.stack([near, far]), cams)
    assert len(priors) == len(cams) and priors.source == "sfm-points"


def test_depth_priors_gather_sample_and_store(tmp_path):
    dense = DenseDepth(np.arange(12, dtype=np.float32).reshape(3, 4), np.ones((3, 4), bool))
    dense.valid[0, 0] = False
    sparse = SparseDepth(np.array([1.5, 3.2], np.float32), np.array([0.5, 2.9], np.float32),
                         np.array([7.0, 9.0], np.float32))
    pri = DepthPriors([dense, sparse], [(3, 4), (3, 4)], "test")
    z, ok = pri.gather(torch.tensor([0, 0, 1, 1, 1]), torch.tensor([0, 3, 1, 3, 0]), torch.tensor([0, 2, 0, 2, 0]))
    assert ok.tolist() == [False, True, True, True, False]
    assert z[ok].tolist() == [11.0, 7.0, 9.0]
    img, u, v, zz = pri.sample(200, torch.Generator().manual_seed(0))
    for i, uu, vv, z_ in zip(img.tolist(), u.tolist(), v.tolist(), zz.tolist()):
        if i == 1:  # rays go through the sparse point exactly: u + 0.5 is its coordinate
            k = int(np.argmin(np.abs(sparse.u - (uu + 0.5))))
            assert sparse.v[k] == pytest.approx(vv + 0.5) and sparse.z[k] == z_
        else:
            assert dense.valid[int(vv), int(uu)] and dense.depth[int(vv), int(uu)] == z_
    assert pri.count() == 13
    pri.save(tmp_path / "depth.safetensors")
    back = DepthPriors.load(tmp_path / "depth.safetensors")
    assert back.source == "test" and back.sizes == pri.sizes
    np.testing.assert_array_equal(back.for_image(1).z, sparse.z)
    np.testing.assert_array_equal(back.for_image(0).valid, dense.valid)
    assert pri.to_field(0.5).for_image(1).z.tolist() == [3.5, 4.5]


def test_triangulation_with_known_poses_matches_ground_truth(scene_factory):
    from repaint_nerf.core.scene.loaders.detect import load_scene

    root = scene_factory("demo", size=128, views=12)
    scene = load_scene(root, splits=("train",))
    sp = scene.train
    pri = triangulate_known_poses(sp.images, sp.cameras)
    rel = []
    for i in range(len(sp)):
        p = pri.for_image(i)
        gt = np.load(root / "gt" / "train" / f"r_{i}_depth.npy")
        g = gt[np.floor(p.v).astype(int), np.floor(p.u).astype(int)]
        ok = g > 0
        rel.append(np.abs(p.z[ok] - g[ok]) / g[ok])
    rel = np.concatenate(rel)
    assert rel.size > 40
    assert np.median(rel) < 0.02


@pytest.fixture(scope="module")
def tiny_depth_onnx(tmp_path_factory):
    from tiny_onnx import export_depth_net

    # a fixed "network": relative inverse depth = 0.2 + mean intensity (channels averaged)
    return export_depth_net(tmp_path_factory.mktemp("depth") / "midas_tiny.onnx")


def test_onnx_depth_aligned_to_sparse_points(tiny_depth_onnx):
    from repaint_nerf.core.teachers.depth_onnx import OnnxDepthTeacher, aligned_monocular_depth

    teacher = OnnxDepthTeacher(tiny_depth_onnx, input_size=None, mean=(0, 0, 0), std=(1, 1, 1), multiple=1)
    rng = np.random.default_rng(0)
    img = rng.integers(0, 256, (24, 32, 3), dtype=np.uint8)
    rel = teacher(img)
    np.testing.assert_allclose(rel, img.astype(np.float32).mean(2) / 255.0 + 0.2, atol=1e-5)
    z_true = 1.0 / (0.5 * rel + 0.1)  # the metric depth the sparse points measure
    u, v = rng.uniform(0, 32, 60).astype(np.float32), rng.uniform(0, 24, 60).astype(np.float32)
    z = z_true[v.astype(int), u.astype(int)].astype(np.float32)
    sparse = DepthPriors([SparseDepth(u, v, z)], [(24, 32)], "points")
    dense = aligned_monocular_depth(teacher, [img], sparse).for_image(0)
    assert isinstance(dense, DenseDepth) and dense.valid.all()
    np.testing.assert_allclose(dense.depth, z_true, rtol=1e-3)


def test_onnx_depth_missing_model(tmp_path, monkeypatch):
    from repaint_nerf.core.teachers.depth_onnx import ENV_DEPTH_MODEL, OnnxDepthTeacher

    monkeypatch.delenv(ENV_DEPTH_MODEL, raising=False)
    with pytest.raises(ModelNotFoundError, match=ENV_DEPTH_MODEL):
        OnnxDepthTeacher(tmp_path / "nope.onnx")
