"""Loaders round-trip: scenes written from known cameras load with those cameras, images and points."""
from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from repaint_nerf.core.scene.cameras import Cameras, look_at
from repaint_nerf.core.scene.loaders.detect import detect_format, load_scene
from repaint_nerf.core.scene.loaders.images import apply_orientation, read_image
from repaint_nerf.core.scene.normalize import normalize_scene
from repaint_nerf.core.scene.scene import SceneSplit
from scene_writers import pattern, ring_poses, write_blender, write_colmap, write_image, write_llff

ATOL_POSE = 1e-5


def _c2w(split) -> np.ndarray:
    return split.cameras.c2w.double().numpy()


# ---------------------------------------------------------------- NeRF-synthetic / Blender


def test_blender_round_trip_exact(tmp_path):
    truth = write_blender(tmp_path, w=24, h=16, fl=30.0, extra={"background": [1, 1, 1],
                                                                "aabb": [[-1, -1, -0.5], [1, 1, 0.5]]})
    scene = load_scene(tmp_path)
    assert scene.format == "blender" and scene.kind == "bounded"
    assert set(scene.splits) == {"train", "test"}
    for split in ("train", "test"):
        poses, imgs = truth[split]
        sp = scene.splits[split]
        assert np.allclose(_c2w(sp), poses, atol=ATOL_POSE)
        assert torch.allclose(sp.cameras.fx, torch.tensor(30.0)) and torch.allclose(sp.cameras.fy, torch.tensor(30.0))
        assert float(sp.cameras.cx[0]) == 12.0 and float(sp.cameras.cy[0]) == 8.0
        assert sp.cameras.width.tolist() == [24] * len(poses) and sp.cameras.height.tolist() == [16] * len(poses)
        for a, b in zip(sp.images, imgs):
            assert a.shape == (16, 24, 4) and np.array_equal(a, b)  # alpha kept for the renderer
        assert sp.has_alpha and scene.extra["alpha"]
        assert not SceneSplit(sp.cameras, [a[..., :3] for a in sp.images], sp.names).has_alpha
        assert sp.names == [f"{split}/r_{i}.png" for i in range(len(poses))]
    assert scene.background == (1.0, 1.0, 1.0)
    # the aabb fills the cube (with a small margin), centred
    corners = np.array([[-1, -1, -0.5], [1, 1, 0.5]])
    f = scene.norm.to_field(corners)
    assert np.all(np.abs(f) <= 1.0) and np.abs(f).max() > 0.9
    assert scene.extra["normalization"]["rule"] == "aabb"


def test_blender_per_frame_intrinsics_and_extensions(tmp_path):
    write_blender(tmp_path, counts={"train": 3}, angle=False, rgba=False, fl=20.0)
    meta = json.loads((tmp_path / "transforms_train.json").read_text())
    meta["frames"][1].update({"fl_x": 22.0, "fl_y": 21.0, "cx": 11.0, "cy": 7.5})
    meta["frames"][2]["file_path"] = "train/r_2.png"
    (tmp_path / "transforms_train.json").write_text(json.dumps(meta))
    scene = load_scene(tmp_path / "transforms_train.json")
    cams = scene.train.cameras
    assert cams.fx.tolist() == [20.0, 22.0, 20.0] and cams.fy.tolist() == [20.0, 21.0, 20.0]
    assert cams.cx.tolist() == [12.0, 11.0, 12.0] and cams.cy.tolist() == [8.0, 7.5, 8.0]
    assert scene.background is None and scene.train.images[0].shape == (16, 24, 3)
    assert "test" not in scene.splits


def test_downscale_resizes_with_area_and_scales_intrinsics(tmp_path):
    truth = write_blender(tmp_path, counts={"train": 2}, w=24, h=16, fl=30.0)
    full = load_scene(tmp_path)
    half = load_scene(tmp_path, downscale=2)
    assert half.train.images[0].shape == (8, 12, 4)
    ref = cv2.resize(truth["train"][1][0], (12, 8), interpolation=cv2.INTER_AREA)
    assert np.array_equal(half.train.images[0], ref)
    c = half.train.cameras
    assert torch.allclose(c.fx, torch.tensor(15.0)) and torch.allclose(c.cx, torch.tensor(6.0))
    assert np.allclose(_c2w(half.train), _c2w(full.train))
    # normalisation does not depend on the image size
    assert np.allclose(half.norm.center, full.norm.center) and math.isclose(half.norm.scale, full.norm.scale)


def test_splits_argument_reads_only_those(tmp_path):
    write_blender(tmp_path)
    scene = load_scene(tmp_path, splits=["test"])
    assert list(scene.splits) == ["test"]


# ---------------------------------------------------------------- nerfstudio


def _nerfstudio(root: Path, n: int = 10, w: int = 20, h: int = 14, **meta_extra) -> np.ndarray:
    poses = ring_poses(n, seed=5)
    frames = []
    for i, m in enumerate(poses):
        write_image(root / "images" / f"frame_{i:05d}.png", pattern(h, w, i))
        frames.append({"file_path": f"images/frame_{i:05d}.png", "transform_matrix": m.tolist()})
    meta = {"fl_x": 18.0, "fl_y": 19.0, "cx": 10.5, "cy": 6.5, "w": w, "h": h, "frames": frames, **meta_extra}
    (root / "transforms.json").write_text(json.dumps(meta))
    return poses


def test_nerfstudio_every_eighth_is_test(tmp_path):
    poses = _nerfstudio(tmp_path, n=10)
    scene = load_scene(tmp_path)
    assert scene.format == "nerfstudio"
    assert scene.splits["test"].names == ["images/frame_00000.png", "images/frame_00008.png"]
    assert len(scene.train) == 8
    assert np.allclose(_c2w(scene.splits["test"]), poses[[0, 8]], atol=ATOL_POSE)
    c = scene.train.cameras
    assert (float(c.fx[0]), float(c.fy[0]), float(c.cx[0]), float(c.cy[0])) == (18.0, 19.0, 10.5, 6.5)


def test_nerfstudio_split_lists(tmp_path):
    _nerfstudio(tmp_path, n=6, train_filenames=[f"images/frame_{i:05d}.png" for i in (0, 1, 2, 3)],
                test_filenames=["./images/frame_00005.png"])
    scene = load_scene(tmp_path)
    assert len(scene.train) == 4 and scene.splits["test"].names == ["images/frame_00005.png"]


def test_nerfstudio_distortion_is_undistorted(tmp_path):
    import pycolmap

    w, h = 40, 30
    params = [30.0, 31.0, 20.0, 15.0, -0.2, 0.05, 0.001, -0.002]
    cam = pycolmap.Camera.create_from_model_name(1, "OPENCV", 1.0, w, h)
    cam.params = params
    # Distorted image whose colour is a function of the ideal (undistorted) normalised coordinates.
    vv, uu = np.mgrid[0:h, 0:w] + 0.5
    xy = cam.cam_from_img(np.stack([uu.ravel(), vv.ravel()], 1)).reshape(h, w, 2)
    def colour(xy):
        return np.stack([128 + 100 * xy[..., 0], 128 + 100 * xy[..., 1], np.full(xy.shape[:2], 50.0)], -1)

    write_image(tmp_path / "images" / "a.png", np.clip(colour(xy) + 0.5, 0, 255).astype(np.uint8))
    meta = {"fl_x": 30.0, "fl_y": 31.0, "cx": 20.0, "cy": 15.0, "w": w, "h": h, "k1": -0.2, "k2": 0.05,
            "p1": 0.001, "p2": -0.002, "camera_model": "OPENCV",
            "frames": [{"file_path": "images/a.png", "transform_matrix": np.eye(4).tolist()}]}
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    scene = load_scene(tmp_path)
    c = scene.train.cameras
    new = pycolmap.undistort_camera(pycolmap.UndistortCameraOptions(), cam)
    assert (int(c.width[0]), int(c.height[0])) == (new.width, new.height)
    assert math.isclose(float(c.fx[0]), new.focal_length_x, rel_tol=1e-6)
    img = scene.train.images[0].astype(np.float64)
    H, W = img.shape[:2]
    vv, uu = np.mgrid[0:H, 0:W] + 0.5
    ideal = np.stack([(uu - float(c.cx[0])) / float(c.fx[0]), (vv - float(c.cy[0])) / float(c.fy[0])], -1)
    err = np.abs(img - colour(ideal))[2:-2, 2:-2, :2]
    assert np.median(err) < 1.0 and err.max() < 4.0


# ---------------------------------------------------------------- LLFF


def _forward_poses(n: int) -> np.ndarray:
    return np.stack([look_at([0.3 * math.cos(i), 0.2 * math.sin(i), 4.0], [0, 0, 0], up=(0, 1, 0)) for i in range(n)])


def test_llff_round_trip(tmp_path):
    poses = _forward_poses(9)
    bounds = np.stack([np.linspace(2.0, 2.5, 9), np.linspace(6.0, 7.0, 9)], 1)
    imgs = write_llff(tmp_path, poses, h=12, w=16, focal=14.0, bounds=bounds)
    scene = load_scene(tmp_path)
    assert scene.format == "llff" and scene.kind == "forward"
    assert len(scene.train) == 7 and len(scene.splits["test"]) == 2
    assert np.allclose(_c2w(scene.splits["test"]), poses[[0, 8]], atol=ATOL_POSE)
    assert np.allclose(_c2w(scene.train), poses[[1, 2, 3, 4, 5, 6, 7]], atol=ATOL_POSE)
    c = scene.train.cameras
    assert (float(c.fx[0]), float(c.fy[0]), float(c.cx[0]), float(c.cy[0])) == (14.0, 14.0, 8.0, 6.0)
    assert np.array_equal(scene.splits["test"].images[1], imgs[8])
    assert math.isclose(scene.near, 0.9 * 2.0) and math.isclose(scene.far, 1.1 * 7.0)
    # the cameras look at the origin: the image centre ray of a camera stays inside the field cube
    # between near and far, and the cameras themselves are outside the fitted region
    assert scene.extra["normalization"]["rule"] == "frustum"
    o, d, _ = c.rays(torch.tensor([0]), torch.tensor([8]), torch.tensor([6]))
    for t in (2.0, 4.0, 7.0):
        assert np.all(np.abs(scene.norm.to_field((o + t * d).double().numpy())) <= 1.0)


def _llff_with_copy(root, factor: int, h: int, w: int, focal: float) -> list:
    """An LLFF scene of 3 views at h x w plus an images_<factor>/ copy shrunk by factor; returns the copy's images."""
    poses, bounds = _forward_poses(3), np.tile([2.0, 6.0], (3, 1))
    write_llff(root, poses, h=h, w=w, focal=focal, bounds=bounds)
    small = write_llff(root / "s", poses, h=h // factor, w=w // factor, focal=focal / factor, bounds=bounds,
                       folder=f"images_{factor}")
    (root / f"images_{factor}").mkdir()
    for i, im in enumerate(small):
        write_image(root / f"images_{factor}" / f"IMG_{i:03d}.png", im)
    return small


def test_llff_prefers_images_n_for_downscale(tmp_path):
    small = _llff_with_copy(tmp_path, 2, 12, 16, 14.0)
    scene = load_scene(tmp_path, downscale=2)
    assert scene.extra["images_dir"] == "images_2"
    assert np.array_equal(scene.train.images[0], small[1])
    assert float(scene.train.cameras.fx[0]) == 7.0 and int(scene.train.cameras.width[0]) == 8


def test_llff_reads_a_shrunk_copy_that_covers_max_size_instead_of_the_full_photos(tmp_path):
    """Big LLFF photos are not decoded to be shrunk when an images_N/ copy reaches (90% of) max_size."""
    small = _llff_with_copy(tmp_path, 4, 48, 64, 56.0)
    scene = load_scene(tmp_path, max_size=17)  # 16 >= 0.9 * 17: the copy stands in
    assert scene.extra["images_dir"] == "images_4" and np.array_equal(scene.train.images[0], small[1])
    assert float(scene.train.cameras.fx[0]) == 14.0 and int(scene.train.cameras.width[0]) == 16
    full = load_scene(tmp_path, max_size=32)  # 16 < 0.9 * 32: read the photos and fit them to 32
    assert full.extra["images_dir"] == "images" and int(full.train.cameras.width[0]) == 32
    (tmp_path / "images_4" / "IMG_002.png").unlink()  # an incomplete copy is never used
    assert load_scene(tmp_path, max_size=17).extra["images_dir"] == "images"


# ---------------------------------------------------------------- COLMAP


def _colmap_truth(n=9):
    poses = ring_poses(n, radius=3.0, seed=2)
    rng = np.random.default_rng(0)
    points = rng.uniform(-0.8, 0.8, (200, 3))
    colors = rng.integers(0, 256, (200, 3)).astype(np.uint8)
    return poses, points, colors


@pytest.mark.parametrize("text", [False, True])
def test_colmap_pinhole_round_trip(tmp_path, text):
    poses, points, colors = _colmap_truth()
    write_colmap(tmp_path, poses, "PINHOLE", [20.0, 21.0, 12.0, 8.5], 24, 16, points, colors, text=text)
    scene = load_scene(tmp_path)
    assert scene.format == "colmap" and detect_format(tmp_path)[0] == "colmap"
    assert np.allclose(_c2w(scene.train), poses[[1, 2, 3, 4, 5, 6, 7]], atol=ATOL_POSE)
    assert np.allclose(_c2w(scene.splits["test"]), poses[[0, 8]], atol=ATOL_POSE)
    c = scene.train.cameras
    assert (float(c.fx[0]), float(c.fy[0]), float(c.cx[0]), float(c.cy[0])) == (20.0, 21.0, 12.0, 8.5)
    assert np.allclose(np.sort(scene.points, axis=0), np.sort(points, axis=0))
    order = np.lexsort(scene.points.T)
    assert np.array_equal(scene.point_colors[order], colors[np.lexsort(points.T)])
    # sparse points project into the loaded cameras where the COLMAP (OpenCV) model says they do
    import pycolmap

    rec = pycolmap.Reconstruction(str(tmp_path / "sparse" / "0"))
    im = next(i for i in rec.images.values() if i.name == "img_01.png")
    ref = np.asarray([rec.cameras[1].img_from_cam(im.cam_from_world() * p) for p in points[:10]])
    uv, z = c.project(torch.tensor(points[:10], dtype=torch.float32), 0)
    assert np.allclose(uv.numpy(), ref, atol=1e-3) and torch.all(z > 0)
    assert scene.extra["normalization"]["rule"] == "points"
    assert np.all(np.abs(scene.norm.to_field(np.percentile(points, [5, 95], axis=0))) < 1.0)


def test_colmap_opencv_distortion(tmp_path):
    import pycolmap

    poses, points, colors = _colmap_truth(n=2)
    w, h = 40, 30
    params = [30.0, 31.0, 20.5, 14.5, 0.4, 0.05, 0.002, 0.001]
    cam = pycolmap.Camera.create_from_model_name(1, "OPENCV", 1.0, w, h)
    cam.params = params
    # a distorted image with a bright dot where a 3D point off the image centre projects (through the distortion)
    w2c = np.linalg.inv(poses[0] @ np.diag([1.0, -1, -1, 1]))  # OpenCV world-to-camera
    p_cam = 2.5 * np.array([0.42, 0.3, 1.0])
    p = np.linalg.inv(w2c[:3, :3]) @ (p_cam - w2c[:3, 3])
    uv_dist = cam.img_from_cam(p_cam)
    vv, uu = np.mgrid[0:h, 0:w] + 0.5
    dot = np.exp(-((uu - uv_dist[0]) ** 2 + (vv - uv_dist[1]) ** 2) / (2 * 1.5 ** 2))
    img = np.clip(np.repeat(dot[..., None] * 255, 3, -1) + 0.5, 0, 255).astype(np.uint8)
    write_colmap(tmp_path, poses, "OPENCV", params, w, h, points, colors, images=[img, img])
    scene = load_scene(tmp_path)
    assert scene.extra["camera_models"] == ["OPENCV"]
    c = scene.splits["test"].cameras  # image 0
    assert np.allclose(_c2w(scene.splits["test"]), poses[[0]], atol=ATOL_POSE)
    # the undistorted (pinhole) projection of the point is where the dot now is
    uv, _ = c.project(torch.tensor(p[None], dtype=torch.float32), 0)
    out = scene.splits["test"].images[0][..., 0].astype(np.float64)
    H, W = out.shape
    vv, uu = np.mgrid[0:H, 0:W] + 0.5
    centroid = np.array([(uu * out).sum(), (vv * out).sum()]) / out.sum()
    pinhole = np.array([params[0] * 0.42 + params[2], params[1] * 0.3 + params[3]])
    assert np.linalg.norm(uv_dist - pinhole) > 1.5  # the distortion moves the dot visibly
    assert np.linalg.norm(centroid - uv[0].numpy()) < 0.25


# ---------------------------------------------------------------- images


def test_image_reading_conversions(tmp_path):
    g16 = (np.arange(12 * 10).reshape(12, 10) * 500).astype(np.uint16)
    cv2.imwrite(str(tmp_path / "g16.png"), g16)
    img = read_image(tmp_path / "g16.png")
    assert img.shape == (12, 10, 3) and img.dtype == np.uint8
    assert np.array_equal(img[..., 0], np.round(g16 / 257.0).astype(np.uint8))
    assert np.array_equal(img[..., 0], img[..., 2])
    rgb = pattern(8, 6, 1)
    write_image(tmp_path / "c.png", rgb)
    assert np.array_equal(read_image(tmp_path / "c.png"), rgb)


@pytest.mark.parametrize("orientation", [3, 6, 8])
def test_exif_orientation_matches_opencv(tmp_path, orientation):
    from PIL import Image

    raw = pattern(20, 30, 2)
    exif = Image.Exif()
    exif[0x0112] = orientation
    path = tmp_path / "o.jpg"
    Image.fromarray(raw).save(path, "JPEG", exif=exif.tobytes(), quality=95)
    ours = read_image(path)
    ref = cv2.cvtColor(cv2.imread(str(path), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)  # OpenCV applies EXIF here
    assert ours.shape == ref.shape and np.array_equal(ours, ref)
    assert read_image(path, orient=False).shape == (20, 30, 3)
    assert apply_orientation(raw, 1) is not None


# ---------------------------------------------------------------- normalisation


def test_object_centric_normalisation_finds_the_centre(tmp_path):
    target = np.array([0.5, -0.3, 0.2])
    poses = np.stack([look_at(target + 4 * np.array([math.cos(a), math.sin(a), 0.4]), target)
                      for a in np.linspace(0, 2 * np.pi, 12, endpoint=False)])
    from repaint_nerf.core.scene.scene import Scene, SceneSplit

    cams = Cameras.create(poses, 30.0, 30.0, 12.0, 12.0, 24, 24)
    scene = Scene(root=tmp_path, format="blender",
                  splits={"train": SceneSplit(cams, [np.zeros((24, 24, 3), np.uint8)] * 12,
                                              [str(i) for i in range(12)])})
    norm = normalize_scene(scene)
    assert scene.extra["normalization"]["rule"] == "cameras"
    assert np.allclose(norm.center, target, atol=1e-6)
    radius = 4 * math.sqrt(1 + 0.16) * math.sin(math.atan(12 / 30))
    assert math.isclose(1 / norm.scale, radius * 1.05, rel_tol=1e-6)
    d = np.linalg.norm(norm.to_field(poses[:, :3, 3]), axis=1)
    assert np.all(d > math.sqrt(3))  # cameras outside the field cube
    assert 0 < scene.near < scene.far < 1e9


# ---------------------------------------------------------------- synthetic scenes (ground truth)


def test_synthetic_scene_loads_with_its_cameras_and_depth(scene_factory):
    root = scene_factory("demo", size=32, views=6, seed=0, test_views=2)
    scene = load_scene(root)
    for split in ("train", "test"):
        meta = json.loads((root / f"transforms_{split}.json").read_text())
        sp = scene.splits[split]
        assert np.allclose(_c2w(sp), [f["transform_matrix"] for f in meta["frames"]], atol=ATOL_POSE)
        for key, t in (("fl_x", sp.cameras.fx), ("fl_y", sp.cameras.fy), ("cx", sp.cameras.cx), ("cy", sp.cameras.cy)):
            assert torch.allclose(t, torch.tensor(float(meta[key])), atol=1e-4)
    # A pixel's ray, taken to its ground-truth z-depth, lands on the surface another view sees there:
    # the depth it projects to in view j matches view j's ground-truth depth to a small fraction of a pixel.
    cams = scene.train.cameras

    def depth(i):
        return np.load(root / "gt" / "train" / f"r_{i}_depth.npy")

    def reprojection_error(shift: float) -> float:
        errs = []
        for i in range(len(cams)):
            zi = torch.tensor(depth(i))
            vv, uu = torch.nonzero(zi > 0, as_tuple=True)
            o, d, dz = cams.rays(torch.full_like(uu, i), uu.float() + shift, vv.float() + shift)
            x = o + (zi[vv, uu] / dz)[:, None] * d
            for j in range(len(cams)):
                if j == i:
                    continue
                zj = depth(j)
                uv, z = cams.project(x, j)
                q, z = uv.double().numpy() - 0.5, z.double().numpy()
                x0, y0 = np.floor(q[:, 0]).astype(int), np.floor(q[:, 1]).astype(int)
                ok = (x0 >= 0) & (y0 >= 0) & (x0 < zj.shape[1] - 1) & (y0 < zj.shape[0] - 1) & (z > 0)
                x0, y0, q, z = x0[ok], y0[ok], q[ok], z[ok]
                c = np.stack([zj[y0, x0], zj[y0, x0 + 1], zj[y0 + 1, x0], zj[y0 + 1, x0 + 1]], 1)
                smooth = (c.min(1) > 0) & (np.ptp(c, axis=1) < 0.03 * c.mean(1)) & (np.abs(z - c.mean(1)) < 0.05 * z)
                fx, fy = q[:, 0] - x0, q[:, 1] - y0
                zint = (c[:, 0] * (1 - fx) * (1 - fy) + c[:, 1] * fx * (1 - fy) + c[:, 2] * (1 - fx) * fy
                        + c[:, 3] * fx * fy)
                errs.append((np.abs(z - zint) / (z / float(cams.fx[j])))[smooth])  # in pixel footprints
        e = np.concatenate(errs)
        assert e.size > 500
        return float(np.median(e))

    assert reprojection_error(0.0) < 0.05
    assert reprojection_error(0.5) > 0.2  # a half-pixel convention error would be caught


# ---------------------------------------------------------------- repaint-nerf info


def test_info_command_reports_the_scene(scene_factory, capsys, tmp_path):
    from repaint_nerf.app.cli import main

    root = scene_factory("demo", size=32, views=6, seed=0, test_views=2)
    assert main(["info", str(root), "--json", "--downscale", "2"]) == 0
    info = json.loads(capsys.readouterr().out)
    meta = json.loads((root / "transforms_train.json").read_text())
    assert info["format"] == "blender" and info["kind"] == meta.get("scene_kind", "bounded")
    assert info["splits"] == {"train": {"images": 6, "size": [16, 16]}, "test": {"images": 2, "size": [16, 16]}}
    assert math.isclose(info["intrinsics"]["fx"], meta["fl_x"] / 2, rel_tol=1e-6)
    assert info["intrinsics"]["vary"] is False
    assert info["depth_gt"]["present"] and info["depth_gt"]["files"] == 8
    assert info["bounds_world"]["rule"] == "aabb" and np.allclose(info["bounds_world"]["region"], meta["aabb"])
    assert info["points"] == 0
    assert main(["info", str(root)]) == 0
    text = capsys.readouterr().out
    for line in ("format          blender", "split train     6 images, 32x32", "depth gt        yes", "normalisation"):
        assert line in text
    # per-frame intrinsics are reported as varying
    write_blender(tmp_path, counts={"train": 2}, angle=False)
    _meta = json.loads((tmp_path / "transforms_train.json").read_text())
    _meta["frames"][1]["fl_x"] = 40.0
    (tmp_path / "transforms_train.json").write_text(json.dumps(_meta))
    assert main(["info", str(tmp_path), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["intrinsics"]["vary"] is True
