"""Bad scene input: each case is one `SceneError` naming the file and what is wrong, and exit 2 from the CLI."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from repaint_nerf.app.cli import main
from repaint_nerf.core.errors import SceneError, UserError
from repaint_nerf.core.scene.loaders import detect
from repaint_nerf.core.scene.loaders.detect import load_scene
from scene_writers import pattern, ring_poses, write_blender, write_colmap, write_image, write_llff


def _blender(root: Path, **kw) -> Path:
    write_blender(root, counts={"train": 3}, rgba=False, **kw)
    return root


def _edit_json(root: Path, fn, name: str = "transforms_train.json") -> Path:
    path = root / name
    meta = json.loads(path.read_text())
    fn(meta)
    path.write_text(json.dumps(meta))
    return path


def case_missing_folder(root):
    return root / "nope", root / "nope", "no such file or folder"


def case_empty_folder(root):
    return root, root, "empty"


def case_unknown_folder(root):
    (root / "notes.txt").write_text("hello")
    return root, root, "no scene found"


def case_missing_image(root):
    """One missing image is skipped with a warning, as instant-ngp skips it (test_real_capture_input); a split
    with none is the error."""
    _blender(root)
    for p in (root / "train").glob("r_*.png"):
        p.unlink()
    return root, root / "transforms_train.json", "none of the 3 frames has its image"


def case_truncated_image(root):
    _blender(root)
    p = root / "train" / "r_2.png"
    p.write_bytes(p.read_bytes()[: p.stat().st_size // 2])
    return root, p, "truncated"


def case_not_an_image(root):
    _blender(root)
    p = root / "train" / "r_0.png"
    p.write_text("this is text, not a PNG")
    return root, p, "not a readable image"


def case_sizes_differ(root):
    _blender(root)
    write_image(root / "train" / "r_1.png", pattern(20, 24, 0))
    return root, root / "transforms_train.json", "differ in size"


def case_nan_pose(root):
    _blender(root)
    return root, _edit_json(root, lambda m: m["frames"][1]["transform_matrix"][0].__setitem__(3, float("nan"))), \
        "frame 1 ('./train/r_1'): the pose contains NaN"


def case_singular_pose(root):
    _blender(root)

    def zero_rotation(m):
        m["frames"][2]["transform_matrix"] = [[0, 0, 0, 1], [0, 0, 0, 2], [0, 0, 0, 3], [0, 0, 0, 1]]
    return root, _edit_json(root, zero_rotation), "frame 2 ('./train/r_2'): the pose is singular"


def case_mirrored_pose(root):
    _blender(root)

    def mirror(m):
        m["frames"][0]["transform_matrix"] = np.diag([-1.0, 1, 1, 1]).tolist()
    return root, _edit_json(root, mirror), "reflection"


def case_bad_matrix_shape(root):
    _blender(root)
    return root, _edit_json(root, lambda m: m["frames"][0].__setitem__("transform_matrix", [[1, 0], [0, 1]])), \
        "4x4"


def case_not_json(root):
    _blender(root)
    (root / "transforms_train.json").write_text("{ frames: oops")
    return root, root / "transforms_train.json", "not valid JSON"


def case_json_not_object(root):
    _blender(root)
    (root / "transforms_train.json").write_text("[1, 2, 3]")
    return root, root / "transforms_train.json", "expected a JSON object"


def case_json_missing_frames(root):
    _blender(root)
    return root, _edit_json(root, lambda m: m.pop("frames")), "missing key 'frames'"


def case_json_empty_frames(root):
    _blender(root)
    return root, _edit_json(root, lambda m: m.__setitem__("frames", [])), "'frames' is empty"


def case_json_missing_intrinsics(root):
    _blender(root)
    return root, _edit_json(root, lambda m: m.pop("camera_angle_x")), "camera_angle_x"


def case_json_frame_missing_key(root):
    _blender(root)
    return root, _edit_json(root, lambda m: m["frames"][1].pop("transform_matrix")), \
        "frame 1 misses key 'transform_matrix'"


def case_json_bad_number(root):
    _blender(root)
    return root, _edit_json(root, lambda m: m.__setitem__("camera_angle_x", "wide")), "'camera_angle_x' is not a finite"


def case_blender_without_train(root):
    _blender(root)
    (root / "transforms_train.json").rename(root / "transforms_test.json")
    return root, root, "transforms_train.json not found"


def case_nerfstudio_unknown_split_file(root):
    poses = ring_poses(2)
    write_image(root / "images" / "a.png", pattern(8, 8, 0))
    write_image(root / "images" / "b.png", pattern(8, 8, 1))
    meta = {"fl_x": 8.0, "fl_y": 8.0, "frames": [{"file_path": f"images/{n}.png", "transform_matrix": m.tolist()}
                                                 for n, m in zip("ab", poses)],
            "train_filenames": ["images/a.png", "images/zzz.png"]}
    (root / "transforms.json").write_text(json.dumps(meta))
    return root, root / "transforms.json", "'images/zzz.png'"


def case_nerfstudio_wrong_aspect(root):
    write_image(root / "images" / "a.png", pattern(8, 16, 0))
    meta = {"fl_x": 8.0, "fl_y": 8.0, "w": 10, "h": 10,
            "frames": [{"file_path": "images/a.png", "transform_matrix": np.eye(4).tolist()}]}
    (root / "transforms.json").write_text(json.dumps(meta))
    return root, root / "transforms.json", "the image is 16x8 but the file says w=10, h=10"


def case_llff_wrong_shape(root):
    np.save(root / "poses_bounds.npy", np.zeros((3, 15)))
    write_image(root / "images" / "a.png", pattern(8, 8, 0))
    return root, root / "poses_bounds.npy", "shape (N, 17)"


def case_llff_not_npy(root):
    (root / "poses_bounds.npy").write_text("garbage")
    return root, root / "poses_bounds.npy", "not a readable .npy"


def case_llff_image_count(root):
    poses = np.stack([np.eye(4)] * 3)
    poses[:, 0, 3] = [0, 1, 2]
    write_llff(root, poses, 8, 8, 8.0, np.tile([1.0, 5.0], (3, 1)))
    (root / "images" / "IMG_002.png").unlink()
    return root, root / "poses_bounds.npy", "holds 2 images but poses_bounds.npy has 3 poses"


def case_llff_bad_values(root):
    np.save(root / "poses_bounds.npy", np.zeros((2, 17)))
    return root, root / "poses_bounds.npy", "near/far bounds must be finite and positive"


def case_llff_no_images(root):
    write_llff(root, np.stack([np.eye(4)] * 2), 8, 8, 8.0, np.tile([1.0, 5.0], (2, 1)))
    for p in (root / "images").iterdir():
        p.unlink()
    return root, root, "no images found"


def case_colmap_without_model(root):
    (root / "sparse" / "0").mkdir(parents=True)
    write_image(root / "images" / "a.png", pattern(8, 8, 0))
    return root, root / "sparse", "COLMAP folder without a model"


def case_colmap_incomplete_model(root):
    rng = np.random.default_rng(0)
    write_colmap(root, ring_poses(2), "PINHOLE", [8, 8, 4, 4], 8, 8, rng.uniform(-1, 1, (3, 3)), np.zeros((3, 3)))
    (root / "sparse" / "0" / "images.bin").unlink()
    return root, root / "sparse" / "0", "images.bin / images.txt is missing"


def case_colmap_corrupt_model(root):
    rng = np.random.default_rng(0)
    write_colmap(root, ring_poses(2), "PINHOLE", [8, 8, 4, 4], 8, 8, rng.uniform(-1, 1, (3, 3)), np.zeros((3, 3)))
    p = root / "sparse" / "0" / "cameras.bin"
    p.write_bytes(p.read_bytes()[:10])
    return root, root / "sparse" / "0", "the model is corrupt"


def case_colmap_missing_image(root):
    rng = np.random.default_rng(0)
    write_colmap(root, ring_poses(2), "PINHOLE", [8, 8, 4, 4], 8, 8, rng.uniform(-1, 1, (3, 3)), np.zeros((3, 3)))
    (root / "images" / "img_01.png").unlink()
    return root, root / "images" / "img_01.png", "image 'img_01.png' of the COLMAP model not found"


def case_bad_file(root):
    p = root / "scene.zip"
    p.write_bytes(b"PK")
    return p, p, "not a scene description"


CASES = [v for k, v in sorted(globals().items()) if k.startswith("case_")]


@pytest.mark.parametrize("case", CASES, ids=[c.__name__[5:] for c in CASES])
def test_bad_input_is_one_clear_scene_error(tmp_path, case, capsys):
    root = tmp_path / "scene"
    root.mkdir()
    target, named, phrase = case(root)
    with pytest.raises(SceneError) as info:
        load_scene(target)
    msg = str(info.value)
    assert str(named) in msg, msg
    assert phrase in msg, msg
    # through the command line: the message, no traceback, exit status 2
    capsys.readouterr()
    assert main(["info", str(target)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and phrase in err and "Traceback" not in err


def test_bare_photos_need_structure_from_motion(tmp_path, monkeypatch):
    for i in range(3):
        write_image(tmp_path / f"IMG_{i}.jpg", pattern(8, 8, i))
    monkeypatch.setattr(detect, "_sfm_hook", lambda: None)
    with pytest.raises(SceneError, match="structure-from-motion is needed") as info:
        load_scene(tmp_path)
    assert str(tmp_path) in str(info.value) and "repaint-nerf sfm" in str(info.value)


def test_bare_photos_use_the_sfm_hook_when_present(tmp_path, monkeypatch):
    write_image(tmp_path / "images" / "IMG_0.jpg", pattern(8, 8, 0))
    other = tmp_path / "other"
    write_blender(other, counts={"train": 2})
    calls = []

    def fake_sfm(root, downscale=1.0, max_size=0):
        calls.append((root, downscale, max_size))
        return detect.load_blender(other, downscale=downscale, max_size=max_size)

    monkeypatch.setattr(detect, "_sfm_hook", lambda: fake_sfm)
    scene = load_scene(tmp_path, downscale=2, max_size=300)
    assert calls == [(tmp_path, 2.0, 300)] and len(scene.train) == 2 and scene.norm.scale > 0


@pytest.mark.parametrize("value", [0, -1, float("nan"), "x"])
def test_bad_downscale(tmp_path, value):
    write_blender(tmp_path, counts={"train": 1})
    with pytest.raises(UserError, match="--downscale"):
        load_scene(tmp_path, downscale=value)


def test_bad_kind(tmp_path):
    write_blender(tmp_path, counts={"train": 1})
    with pytest.raises(UserError, match="unknown scene kind"):
        load_scene(tmp_path, kind="spherical")


@pytest.mark.parametrize("photos", ["images", "input", None])
def test_an_incomplete_model_points_to_the_photos_beside_it(tmp_path, photos):
    """A model without images.bin (a copy that left out its large files) beside photos names the photo folder to open
    instead: `images/`, or `input/` where 3D Gaussian Splatting's convert.py keeps the photos as taken."""
    root = tmp_path / "scene"
    rng = np.random.default_rng(0)
    write_colmap(root, ring_poses(2), "PINHOLE", [8, 8, 4, 4], 8, 8, rng.uniform(-1, 1, (3, 3)), np.zeros((3, 3)))
    (root / "sparse" / "0" / "images.bin").unlink()
    for p in (root / "images").iterdir():
        p.unlink()
    if photos is not None:
        write_image(root / photos / "a.png", pattern(8, 8, 0))
    with pytest.raises(SceneError) as info:
        load_scene(root)
    msg = str(info.value)
    if photos is None:
        assert "run structure-from-motion again" in msg and "open " not in msg, msg
    else:
        assert f"open {root / photos}" in msg, msg
