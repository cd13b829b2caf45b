"""Real captures as instant-ngp and nerfstudio users bring them (issue 32), offline: synthetic scenes written as an
instant-ngp `transforms.json` with frames whose image is missing, per-frame `sharpness`, `aabb_scale`, OpenCV lens
distortion, a far textured background without sparse points, and per-image exposure / white balance changes."""
from __future__ import annotations

import json
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from scene_writers import write_ngp_capture

LENS = {"k1": -0.12, "k2": 0.02, "p1": 0.001, "p2": -0.0015}  # a phone's mild barrel distortion


def _load(path, **kw):
    from repaint_nerf.core.scene.loaders.detect import load_scene

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        scene = load_scene(path, **kw)
    from repaint_nerf.core.errors import SceneWarning

    return scene, [str(w.message) for w in caught if issubclass(w.category, SceneWarning)]


def test_frames_without_an_image_are_skipped_with_one_counting_warning(scene_factory, tmp_path, capsys):
    from repaint_nerf.app.cli import main
    from repaint_nerf.core.errors import SceneError
    from repaint_nerf.core.scene.loaders.summary import scene_summary

    src = scene_factory("demo", size=16, views=12, test_views=4)
    write_ngp_capture(src, tmp_path / "cap", missing=(1, 4, 6), lens=LENS)
    scene, said = _load(tmp_path / "cap")
    assert len(said) == 1 and "skipped 3 of 16 frames whose image is missing" in said[0], said
    assert sum(len(s) for s in scene.splits.values()) == 13
    names = [n for s in scene.splits.values() for n in s.names]
    assert not {"images/0001.png", "images/0004.png", "images/0006.png"} & set(names)
    assert scene_summary(scene)["skipped"]["missing"] == 3 and scene.extra["camera_models"] == ["OPENCV"]
    assert main(["info", str(tmp_path / "cap")]) == 0
    out, err = capsys.readouterr()
    assert "skipped         3 frame(s) whose image is missing" in out
    assert err.count("warning:") == 1 and "skipped 3 of 16" in err  # one plain line, not a traceback
    write_ngp_capture(src, tmp_path / "none", missing=range(16))
    with pytest.raises(SceneError, match="none of the 16 frames has its image"):
        _load(tmp_path / "none")


def test_sharpness_discards_frames_blurrier_than_their_neighbours(scene_factory, tmp_path):
    from repaint_nerf.core.errors import UserError

    src = scene_factory("demo", size=16, views=12, test_views=4)
    sharp = np.full(16, 100.0)
    sharp[[5, 11]] = 30.0  # two blurry frames
    write_ngp_capture(src, tmp_path / "cap", sharpness=sharp)
    kept, said = _load(tmp_path / "cap")  # by default every frame is kept, as instant-ngp does
    assert sum(len(s) for s in kept.splits.values()) == 16 and not said
    scene, said = _load(tmp_path / "cap", sharpness_discard=0.8)
    names = {n for s in scene.splits.values() for n in s.names}
    assert len(names) == 14 and not {"images/0005.png", "images/0011.png"} & names
    assert len(said) == 1 and "discarded 2 of 16 frames as blurry" in said[0]
    assert scene.extra["skipped"]["blurry"] == 2
    meta = json.loads((tmp_path / "cap" / "transforms.json").read_text())
    meta["sharpness_discard_threshold"] = 0.8  # instant-ngp's key in the file works the same
    (tmp_path / "cap" / "transforms.json").write_text(json.dumps(meta))
    assert sum(len(s) for s in _load(tmp_path / "cap")[0].splits.values()) == 14
    with pytest.raises(UserError, match="--sharpness-discard"):
        _load(tmp_path / "cap", sharpness_discard=-1)


def test_aabb_scale_sets_the_field_cube_the_kind_and_the_warp(scene_factory, tmp_path):
    """instant-ngp's unit cube (scale 0.33, offset 0.5) becomes the field cube; aabb_scale 1 keeps everything in it
    (bounded, no warp), 4 contracts beyond it out to 4x its size; --kind still wins."""
    from repaint_nerf.core.errors import SceneError
    from repaint_nerf.core.field.contraction import warp_spec
    from repaint_nerf.core.scene.loaders.summary import format_summary, scene_summary

    src = scene_factory("demo", size=16, views=12, test_views=4)
    half = 0.5 / 0.33 * 1.05  # the unit cube's half-size in world units, with normalize.MARGIN
    for k, kind in ((1, "bounded"), (4, "unbounded"), (16, "unbounded")):
        write_ngp_capture(src, tmp_path / f"k{k}", extra={"aabb_scale": k})
        scene, _ = _load(tmp_path / f"k{k}")
        assert scene.kind == kind and f"aabb_scale {k}" in scene.extra["kind_reason"]
        spec = warp_spec(scene)
        text = format_summary(scene_summary(scene))
        assert "instant-ngp's unit cube" in text
        if k == 1:  # bounded: the unit cube is the field cube, cameras outside it or not
            assert np.allclose(scene.norm.center, 0.0) and abs(1.0 / scene.norm.scale - half) < 1e-6
            assert spec is None
            continue
        # contracted: the field cube holds the unit cube and every camera (the demo's ring lies outside the unit
        # cube), and rays reach k unit cubes (in field units of the grown cube), never less than 2
        cams = scene.field_cameras("train").c2w[:, :3, 3]
        assert float(cams.abs().max()) <= 1.0 and scene.extra["normalization"]["grown_for_cameras"] > 1.0
        corner = scene.norm.to_field(np.full(3, 0.5 / 0.33))
        assert np.all(np.abs(corner) <= 1.0)
        reach = (k * 0.5 / 0.33 + float(np.max(np.abs(scene.norm.center)))) * scene.norm.scale
        assert spec["kind"] == "contract" and spec["extent"] == pytest.approx(max(2.0, reach))
        assert f"marched to {spec['extent']:.4g}x" in text and "to hold the cameras" in text
    forced, _ = _load(tmp_path / "k4", kind="bounded")
    assert warp_spec(forced) is None
    meta = json.loads((tmp_path / "k4" / "transforms.json").read_text())  # an aabb sets the unit cube instead
    meta["aabb"] = [[-1.0, -1.0, 0.0], [1.0, 1.0, 1.0]]
    (tmp_path / "k4" / "transforms.json").write_text(json.dumps(meta))
    boxed, _ = _load(tmp_path / "k4")
    lo, hi = np.asarray(boxed.extra["normalization"]["box"])
    assert np.all(lo <= [-1.0, -1.0, 0.0]) and np.all(hi >= [1.0, 1.0, 1.0])  # the aabb, grown for the cameras
    assert warp_spec(boxed)["extent"] >= 2.0
    meta["aabb_scale"] = 0.5
    (tmp_path / "k4" / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(SceneError, match="aabb_scale"):
        _load(tmp_path / "k4")


def test_nerfstudio_scene_box_bounds_the_field_and_contracts_beyond(scene_factory, tmp_path):
    from repaint_nerf.core.field.contraction import warp_spec

    src = scene_factory("demo", size=16, views=12, test_views=4)
    write_ngp_capture(src, tmp_path / "ns")
    rot = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # what ns-train writes: x_ns = s (R x + t)
    t = np.array([0.1, -0.2, 0.3])
    (tmp_path / "ns" / "dataparser_transforms.json").write_text(json.dumps(
        {"transform": np.c_[rot, t].tolist(), "scale": 0.25}))
    scene, _ = _load(tmp_path / "ns")
    lo, hi = np.asarray(scene.extra["unit_box"])
    assert np.allclose(lo, rot.T @ -t - 4.0)  # R^T (x_ns / s - t) of the cube [-1, 1]^3 (R a signed permutation)
    assert np.allclose(hi - lo, 8.0) and scene.kind == "unbounded" and "nerfstudio" in scene.extra["kind_reason"]
    assert warp_spec(scene)["kind"] == "contract"


@pytest.fixture()
def textured_room(monkeypatch, tmp_path_factory):
    """The room360 preset with noise-textured walls and ceiling: a far background with texture a probe can see."""
    from repaint_nerf.core.synth import presets
    from repaint_nerf.core.synth.generate import make_scene

    def room():
        spec = presets.build_spec("room360")
        spec.objects = [replace(o, texture="noise", texture_scale=3.0) if o.name in ("walls", "ceiling") else o
                        for o in spec.objects]
        return spec

    monkeypatch.setitem(presets.PRESETS, "room_textured", ("room360 with textured walls", room))
    return make_scene("room_textured", tmp_path_factory.mktemp("room"), size=64, views=12, test_views=2, seed=0)


def test_unbounded_content_is_told_from_poses_and_images_alone(textured_room, scene_factory, tmp_path):
    """No sparse points, no depth range, no aabb_scale: a quick probe triangulates a few image pairs with the known
    poses; the room behind the objects lies beyond the cameras (unbounded, contracted), an object on a plain
    background does not (bounded)."""
    from repaint_nerf.core.field.contraction import warp_spec
    from repaint_nerf.core.scene.loaders.summary import format_summary, scene_summary

    write_ngp_capture(textured_room, tmp_path / "room", lens=LENS, extra={"camera_model": "OPENCV"})
    room, _ = _load(tmp_path / "room")  # undistorted at load, then probed
    assert room.points is None and room.kind == "unbounded", room.extra["kind_reason"]
    assert "quick probe" in room.extra["kind_reason"] and warp_spec(room)["kind"] == "contract"
    assert "quick probe" in format_summary(scene_summary(room))
    write_ngp_capture(scene_factory("demo", size=64, views=12, test_views=2), tmp_path / "obj", alpha=False)
    obj, _ = _load(tmp_path / "obj")
    assert obj.kind == "bounded", obj.extra["kind_reason"]


def _exposure_capture(scene_factory, root: Path):
    """The demo at 32 px as a capture whose training photos differ in exposure and white balance (a gain per
    channel in [0.35, 1.65]); the held-out photos (every 8th) have the neutral one."""
    src = scene_factory("demo", size=32, views=16, test_views=4)
    n = 20
    gains = np.random.default_rng(0).uniform(0.35, 1.65, (n, 3))
    gains[::8] = 1.0  # frames 0, 8, 16 are the test split (sorted file names, every 8th)
    write_ngp_capture(src, root, gains=gains)
    scene, _ = _load(root)
    assert [n for n in scene.split("test").names] == ["images/0000.png", "images/0008.png", "images/0016.png"]
    return scene


def test_appearance_codes_beat_training_without_them_on_exposure_changes(scene_factory, tmp_path):
    """Held-out PSNR, the test views rendered with the mean code (nerfstudio's protocol), is higher with a code per
    training image than without: without, the field bends geometry and view dependence to explain the gains."""
    from repaint_nerf.core.train.stage1 import Stage1Trainer, TrainConfig

    scene = _exposure_capture(scene_factory, tmp_path / "cap")
    psnr = {}
    for setting in ("off", "on"):
        tr = Stage1Trainer(scene, None, TrainConfig(seed=0, rays_per_batch=256, grid_resolution=32,
                                                    appearance=setting))
        assert tr.field_cfg.appearance_dim == (16 if setting == "on" else 0)
        tr.train(steps=240)
        psnr[setting] = tr.evaluate(full=True)["psnr"]
    print(f"held-out PSNR without codes {psnr['off']:.2f} dB, with codes {psnr['on']:.2f} dB")
    assert psnr["on"] > psnr["off"] + 1.0, psnr


def test_appearance_codes_by_scene_and_flag_saved_and_old_checkpoints_load(scene_factory, tmp_path):
    from repaint_nerf.app.cli import build_parser
    from repaint_nerf.core.field.appearance import appearance_default
    from repaint_nerf.core.field.field import FieldConfig, NGPField
    from repaint_nerf.core.render.renderer import RenderOptions, render_camera
    from repaint_nerf.core.scene.loaders.detect import load_scene
    from repaint_nerf.core.train.checkpoint import Checkpoint
    from repaint_nerf.core.train.stage1 import Stage1Trainer, TrainConfig, restore_field

    synthetic = load_scene(scene_factory("demo", size=16, views=6, test_views=2))
    assert appearance_default(synthetic) == (False, "a rendered (blender) scene has one exposure")
    assert appearance_default(synthetic, "on")[0] and not appearance_default(synthetic, "off")[0]
    assert Stage1Trainer(synthetic, None, TrainConfig(grid_resolution=16)).field_cfg.appearance_dim == 0
    args = build_parser().parse_args(["train", "x", "--workspace", "w", "--no-appearance", "--sharpness-discard", "0.5"])
    assert args.appearance is False and args.sharpness_discard == 0.5

    scene = _exposure_capture(scene_factory, tmp_path / "cap")
    tr = Stage1Trainer(scene, None, TrainConfig(seed=0, rays_per_batch=256, grid_resolution=16))
    assert tr.field_cfg.appearance_dim == 16 and tr.field_cfg.appearance_count == len(scene.train)
    tr.train(steps=4)
    codes = tr.field.appearance.embedding.weight.detach()
    assert float(codes.abs().sum()) > 0  # the codes learn
    path = tmp_path / "ck.safetensors"
    tr.checkpoint().save(path)
    field, grid, _ = restore_field(Checkpoint.load(path, "cpu"), "cpu")
    assert torch.equal(field.appearance.embedding.weight, codes)
    cams, opts = scene.field_cameras("test"), RenderOptions(outputs=("rgb",), max_samples=64)
    tr.field.eval()
    assert torch.equal(render_camera(tr.field, tr.grid, cams, 0, opts)["rgb"],
                       render_camera(field, grid, cams, 0, opts)["rgb"])
    old = {k: v for k, v in tr.field_cfg.to_dict().items() if not k.startswith("appearance")}
    assert NGPField(FieldConfig.from_dict(old)).appearance is None  # a checkpoint from before the codes


def test_a_nerf_synthetic_test_split_without_images_is_left_out_with_a_warning(scene_factory, tmp_path):
    import shutil

    from repaint_nerf.core.errors import SceneError

    root = tmp_path / "s"
    shutil.copytree(scene_factory("demo", size=16, views=6, test_views=2), root)
    shutil.rmtree(root / "test")
    scene, said = _load(root)
    assert "test" not in scene.splits and len(scene.train) == 6
    assert len(said) == 1 and "left out the test split" in said[0] and "none of the 2 frames" in said[0]
    shutil.rmtree(root / "train")
    with pytest.raises(SceneError, match="none of the 6 frames has its image"):
        _load(root)


def test_resume_keeps_the_frame_selection_its_appearance_codes_index(scene_factory, tmp_path, capsys):
    """A resumed training must see the training images its appearance codes (one per image, in order) were made
    for: leaving --sharpness-discard out keeps the workspace's; another value that picks other frames is refused
    with a message saying which value to use, and the refused run leaves the workspace's settings as they were."""
    from repaint_nerf.app.cli import main
    from repaint_nerf.core.workspace.workspace import Workspace

    src = scene_factory("demo", size=16, views=12, test_views=4)
    sharp = np.full(16, 100.0)
    sharp[[5, 11]] = 30.0  # two blurry training frames (0 and 8 are held out)
    write_ngp_capture(src, tmp_path / "cap", sharpness=sharp)
    ws = tmp_path / "ws"
    base = ["train", str(tmp_path / "cap"), "--workspace", str(ws), "--rays", "256", "--max-samples", "64",
            "--no-features", "--no-depth"]
    assert main(base + ["--steps", "2", "--sharpness-discard", "0"]) == 0
    frames = Workspace.open(ws).settings["train_frames"]
    assert len(frames) == 14 and "images/0005.png" in frames
    capsys.readouterr()
    assert main(base + ["--steps", "3", "--sharpness-discard", "0.8", "--resume"]) == 2
    err = capsys.readouterr().err
    assert "cannot resume" in err and "left out 3 (e.g. images/0005.png)" in err and "--sharpness-discard 0" in err, err
    settings = Workspace.open(ws).settings
    assert settings["sharpness_discard"] == 0 and settings["train_frames"] == frames
    assert main(base + ["--steps", "3", "--resume"]) == 0  # no value given: the workspace's
    assert "resumed at step 2" in capsys.readouterr().out
    assert Workspace.open(ws).settings["train_frames"] == frames
    # a workspace from before the frames were saved: its codes' count decides
    Workspace.open(ws).update_settings(train_frames=None)
    assert main(base + ["--steps", "4", "--sharpness-discard", "0.8", "--resume"]) == 2
    assert "appearance codes for 14 training images, this load gives 12" in capsys.readouterr().err
    # a new training (no --resume) may choose other frames
    assert main(base + ["--steps", "2", "--sharpness-discard", "0.8"]) == 0
    assert len(Workspace.open(ws).settings["train_frames"]) == 12
