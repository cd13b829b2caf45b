"""Structure-from-motion on rendered photos: poses against the truth, cache, report, CLI and bad input."""
from __future__ import annotations

import json
import shutil
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from repaint_nerf.core.errors import SceneError
from repaint_nerf.core.sfm.evaluate import align_similarity, pose_errors
from repaint_nerf.core.sfm.images import prepare_photos

VIEWS, W, H = 20, 240, 180


def _write(path: Path, img: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_RGBA2BGRA if img.shape[2] == 4 else cv2.COLOR_RGB2BGR)
    cv2.imwrite(str(path), img)


def _noise(h: int, w: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    small = rng.integers(0, 255, (h // 8 + 1, w // 8 + 1, 3), dtype=np.uint8)
    return cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC)


@pytest.fixture(scope="module")
def sfm_run(tmp_path_factory):
    """20 views of the room360 preset plus an unrelated photo and a text file, through SfM once."""
    from repaint_nerf.core.sfm.run import sfm_scene
    from repaint_nerf.core.sfm.synthetic import render_photos

    root = tmp_path_factory.mktemp("sfm")
    photos = root / "photos"
    truth = render_photos("room360", photos, VIEWS, W, H, seed=1)
    _write(photos / "zz_unrelated.png", _noise(H, W, 7))
    (photos / "notes.txt").write_text("not a photo")
    phases = []
    t0 = time.perf_counter()
    scene = sfm_scene(photos, root / "ws", progress=lambda p, f, m: phases.append((p, f)))
    return {"root": root, "photos": photos, "truth": truth, "scene": scene, "phases": phases,
            "seconds": time.perf_counter() - t0}


def test_recovered_poses_match_the_truth(sfm_run):
    scene, truth = sfm_run["scene"], sfm_run["truth"]
    names = [n for s in scene.splits.values() for n in s.names]
    assert sorted(names) == sorted(truth["names"])  # every rendered view registered
    c2w = np.concatenate([s.cameras.c2w.double().numpy() for s in scene.splits.values()])
    gt = truth["c2w"][[truth["names"].index(n) for n in names]]
    err = pose_errors(c2w, gt)
    assert err["rotation_deg_max"] < 1.0, err
    assert err["position_rel_max"] < 0.01, err
    assert abs(float(scene.train.cameras.fx[0]) / truth["fx"] - 1.0) < 0.02  # focal length recovered too


def test_report_lists_dropped_and_skipped_files(sfm_run):
    rep = sfm_run["scene"].extra["sfm"]
    assert rep["total"] == VIEWS + 1 and rep["registered"] == VIEWS
    assert rep["unregistered"] == ["zz_unrelated.png"]
    assert rep["skipped"] == ["notes.txt"]
    assert any("could not be registered" in n and "zz_unrelated.png" in n for n in rep["notes"])
    assert set(rep["seconds"]) == {"intake", "features", "matching", "mapping", "undistortion"}
    seen = {p for p, f in sfm_run["phases"] if f >= 1.0}
    assert set(rep["seconds"]) <= seen


def test_scene_kind_points_and_sparse_depth(sfm_run):
    from repaint_nerf.core.teachers.depth_sparse import depth_for_scene

    scene = sfm_run["scene"]
    assert scene.format == "photos" and scene.kind == "unbounded"
    assert scene.points is not None and len(scene.points) > 100
    assert len(scene.extra["visibility"]) == len(scene.train)
    priors = depth_for_scene(scene)
    cams = scene.train.cameras
    assert priors.source == "sfm-points" and len(priors) == len(cams)
    for i in range(len(cams)):
        sd = priors.for_image(i)
        assert len(sd.z) > 20 and np.all(sd.z > 0)
    vis = scene.extra["visibility"][0]  # points the first image observes project inside it, in front
    uv, z = cams.project(torch.as_tensor(scene.points[vis], dtype=torch.float32), 0)
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < cams.width[0]) & (uv[:, 1] >= 0) & (uv[:, 1] < cams.height[0])
    assert bool((z > 0).all()) and float(inside.float().mean()) > 0.98


def test_second_open_is_cached_and_load_scene_uses_it(sfm_run):
    from repaint_nerf.core.scene.loaders.detect import load_scene

    t0 = time.perf_counter()
    scene = load_scene(sfm_run["photos"], workspace=sfm_run["root"] / "ws")
    took = time.perf_counter() - t0
    assert scene.extra["sfm"]["cached"] and took < max(0.5 * sfm_run["seconds"], 2.0)
    first = sfm_run["scene"]
    assert scene.train.names == first.train.names
    assert np.allclose(scene.train.cameras.c2w.numpy(), first.train.cameras.c2w.numpy())
    assert scene.norm.scale > 0 and scene.kind == "unbounded"


def test_a_new_workspace_adopts_the_result_beside_the_photos(sfm_run, tmp_path):
    """`sfm PHOTOS` caches beside the photos; `train PHOTOS --workspace WS` then brings that result into WS instead
    of running every phase again, and WS keeps its own copy once the one beside the photos is gone."""
    from repaint_nerf.core.sfm.run import default_workspace, sfm_scene

    photos = tmp_path / "photos"
    shutil.copytree(sfm_run["photos"], photos)  # copy2: names, sizes and times kept, so the fingerprint matches
    beside = default_workspace(photos)
    shutil.copytree(sfm_run["root"] / "ws" / "sfm", beside / "sfm")
    phases = []
    t0 = time.perf_counter()
    scene = sfm_scene(photos, tmp_path / "ws", progress=lambda p, f, m: phases.append((p, m)))
    took = time.perf_counter() - t0
    assert [p for p, _ in phases] == ["cached"] and str(beside) in phases[0][1]
    assert scene.extra["sfm"]["cached"] and took < max(0.5 * sfm_run["seconds"], 2.0)
    assert np.allclose(scene.train.cameras.c2w.numpy(), sfm_run["scene"].train.cameras.c2w.numpy())
    shutil.rmtree(beside)
    again = sfm_scene(photos, tmp_path / "ws", progress=lambda p, f, m: phases.append((p, m)))
    assert again.extra["sfm"]["cached"] and str(tmp_path / "ws") in phases[-1][1]
    assert again.train.names == scene.train.names


def test_a_second_sfm_into_the_workspace_waits_for_the_first_and_reuses_it(sfm_run):
    """Two structure-from-motion runs into one workspace (the editor and `train` on the same photos) deleted each
    other's databases. The second now waits on the workspace's lock, says so, and then reuses the first's result."""
    import threading

    from filelock import FileLock

    from repaint_nerf.core.sfm.run import run_sfm

    ws = sfm_run["root"] / "ws"
    said, out = [], {}
    first = FileLock(str(ws / "sfm.lock"))  # the first run, still going
    first.acquire()
    try:
        second = threading.Thread(target=lambda: out.update(report=run_sfm(
            sfm_run["photos"], ws, progress=lambda p, f, m: said.append((p, m)))))
        second.start()
        second.join(1.5)
        assert second.is_alive() and said and said[0][0] == "waiting" and str(ws) in said[0][1], said
    finally:
        first.release()
    second.join(30)
    assert not second.is_alive() and out["report"]["cached"] and said[-1][0] == "cached"


def test_cli_writes_the_json_report(sfm_run, capsys):
    from repaint_nerf.app.cli import main

    out = sfm_run["root"] / "report.json"
    assert main(["sfm", str(sfm_run["photos"]), "--workspace", str(sfm_run["root"] / "ws"),
                 "--json", str(out)]) == 0
    rep = json.loads(out.read_text())
    assert rep["total"] == VIEWS + 1 and rep["registered"] == VIEWS
    assert rep["unregistered"] == ["zz_unrelated.png"] and set(rep["seconds"]) >= {"features", "mapping"}
    assert "zz_unrelated.png" in capsys.readouterr().out


def test_similarity_alignment_is_exact_on_transformed_points():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(10, 3))
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    rot = q * np.sign(np.linalg.det(q))
    dst = 2.5 * src @ rot.T + np.array([1.0, -2.0, 0.5])
    s, r, t = align_similarity(src, dst)
    assert abs(s - 2.5) < 1e-9 and np.allclose(r, rot) and np.allclose(t, [1.0, -2.0, 0.5])


# ---- bad input -------------------------------------------------------------------------------------

def test_fewer_than_three_photos(tmp_path):
    from repaint_nerf.core.sfm.run import sfm_scene

    for i in range(2):
        _write(tmp_path / "p" / f"a{i}.png", _noise(64, 64, i))
    with pytest.raises(SceneError, match="at least 3 photos") as info:
        sfm_scene(tmp_path / "p", tmp_path / "ws")
    assert str(tmp_path / "p") in str(info.value)


def test_cli_bad_input_is_a_message_not_a_traceback(tmp_path, capsys):
    from repaint_nerf.app.cli import main

    (tmp_path / "p").mkdir()
    (tmp_path / "p" / "readme.md").write_text("x")
    assert main(["sfm", str(tmp_path / "p"), "--workspace", str(tmp_path / "ws")]) == 2
    err = capsys.readouterr().err
    assert "error: " in err and "Traceback" not in err and "readme.md" in err and "at least 3 photos" in err


def test_nothing_registers(tmp_path):
    from repaint_nerf.core.sfm.run import sfm_scene

    for i in range(3):
        _write(tmp_path / "p" / f"n{i}.png", _noise(96, 128, 10 + i))
    with pytest.raises(SceneError, match="could not register any") as info:
        sfm_scene(tmp_path / "p", tmp_path / "ws")
    assert str(tmp_path / "p") in str(info.value)


def test_intake_handles_exif_gray_alpha_large_mixed_and_junk(tmp_path):
    from PIL import Image

    src = tmp_path / "p"
    src.mkdir()
    base = _noise(60, 80, 0)
    Image.fromarray(base).save(src / "a_plain.jpg", quality=95)
    exif = Image.Exif()
    exif[0x0112] = 6  # rotate 90 degrees clockwise to display
    Image.fromarray(base).save(src / "b_rotated.jpg", exif=exif, quality=95)
    _write(src / "c_gray.png", cv2.cvtColor(base, cv2.COLOR_RGB2GRAY))
    rgba = np.dstack([base, np.full(base.shape[:2], 255, np.uint8)])
    rgba[:10, :10, 3] = 0
    _write(src / "d_alpha.png", rgba)
    _write(src / "e_large.png", cv2.resize(base, (400, 300)))
    (src / "f_broken.png").write_bytes(b"not a png")
    (src / "g.txt").write_text("x")
    out = tmp_path / "out"
    intake = prepare_photos(src, out, max_side=200)
    assert intake.names == ["a_plain.jpg", "b_rotated.jpg", "c_gray.png", "d_alpha.png", "e_large.png"]
    assert intake.skipped == ["g.txt", "f_broken.png"]
    assert intake.sizes["b_rotated.jpg"] == (60, 80) and intake.sizes["e_large.png"] == (200, 150)
    assert (out / intake.prepared["a_plain.jpg"]).read_bytes() == (src / "a_plain.jpg").read_bytes()
    rot = cv2.imread(str(out / intake.prepared["b_rotated.jpg"]))
    assert rot.shape == (80, 60, 3)
    gray = cv2.imread(str(out / intake.prepared["c_gray.png"]), cv2.IMREAD_UNCHANGED)
    assert gray.ndim == 3 and gray.shape[2] == 3
    alpha = cv2.imread(str(out / intake.prepared["d_alpha.png"]), cv2.IMREAD_UNCHANGED)
    assert alpha.shape[2] == 3 and (alpha[:10, :10] == 255).all()  # transparent -> white
    text = " ".join(intake.notes)
    for word in ("non-image", "f_broken.png", "rotated", "grayscale", "alpha", "downscaled", "mixed sizes"):
        assert word in text, (word, text)


@pytest.mark.slow
def test_field_trained_on_recovered_poses(sfm_run):
    """A field fitted for 150 steps on the SfM poses (normalised into the field cube) reaches a stated PSNR on
    the held-out views: measured 14.9 dB at 99 steps and 16.7 dB at 171; unnormalised poses gave 5 dB."""
    from repaint_nerf.core.train.stage1 import Stage1Trainer, TrainConfig
    from repaint_nerf.core.workspace.workspace import Workspace

    scene = sfm_run["scene"]
    assert scene.extra["normalization"]["rule"] == "points"
    ws = Workspace.open_or_create(sfm_run["root"] / "ws")
    trainer = Stage1Trainer(scene, ws, TrainConfig(seed=0, rays_per_batch=1024, max_samples=192, grid_resolution=64))
    trainer.train(steps=150)
    ev = trainer.evaluate()
    assert ev["psnr"] > 14.5, ev


# ---- the model check (core.sfm.judge) --------------------------------------------------------------

def _facts(focal=533.0, radial=(0.01,), exif=None, spread=4.0, err=0.6, registered=50, total=50, w=384, h=288):
    from repaint_nerf.core.sfm.judge import CameraFacts, ModelFacts

    rng = np.random.default_rng(0)
    ang = np.linspace(0, 2 * np.pi, registered, endpoint=False)
    centres = np.stack([spread * np.cos(ang), spread * np.sin(ang), np.ones_like(ang)], 1)
    points = rng.uniform(-5, 5, (500, 3))
    return ModelFacts([CameraFacts(w, h, focal, radial, exif, registered)], centres, points, err, registered, total)


def test_judge_trusts_a_plain_model():
    from repaint_nerf.core.sfm.judge import judge

    v = judge(_facts())
    assert v.trusted and v.reasons == [] and "trusted" in v.summary()
    assert abs(v.figures["fov_deg"][0] - np.degrees(2 * np.arctan(192 / 533))) < 0.01


def test_judge_rejects_the_shared_camera_failure():
    """The model seen in the field: focal 276 px instead of 533 at 384 px, k = 0.38 (corners moved by ~29%)."""
    from repaint_nerf.core.sfm.judge import corner_distortion, judge

    facts = _facts(focal=276.0, radial=(0.38,))
    r2 = (192 ** 2 + 144 ** 2) / 276.0 ** 2
    assert abs(corner_distortion(facts.cameras[0]) - 0.38 * r2) < 1e-9  # plain reference: k r^2 at the corner
    v = judge(facts)
    assert not v.trusted and any("distortion" in r for r in v.reasons), v.reasons
    assert "implausible" in v.summary()


@pytest.mark.parametrize("kw,word", [({"exif": 533.0, "focal": 276.0, "radial": ()}, "EXIF"),
                                     ({"focal": 60.0, "radial": ()}, "field of view"),
                                     ({"focal": 3000.0, "radial": ()}, "field of view"),
                                     ({"err": 3.5}, "reprojection"),
                                     ({"spread": 0.001}, "barely move"),
                                     ({"registered": 10, "total": 50}, "registered")])
def test_judge_names_each_implausible_figure(kw, word):
    from repaint_nerf.core.sfm.judge import judge

    v = judge(_facts(**kw))
    assert not v.trusted and any(word in r for r in v.reasons), v.reasons


def test_judge_a_real_model_is_trusted(sfm_run):
    rep = sfm_run["scene"].extra["sfm"]
    v = rep["verdict"]
    assert v["trusted"] and v["cameras"] == "shared" and rep["attempts"] == [v]
    assert v["figures"]["reprojection_px"] < 2.0 and v["figures"]["corner_distortion"] < 0.1
    fov = np.degrees(2 * np.arctan(0.5 * W / sfm_run["truth"]["fx"]))
    assert abs(v["figures"]["fov_deg"][0] - fov) < 1.0


def _reject(cameras_rejected):
    from repaint_nerf.core.sfm import judge as judge_mod

    real = judge_mod.judge

    def fake(facts, cameras="shared"):
        v = real(facts, cameras)
        if cameras in cameras_rejected:
            v.trusted, v.reasons = False, v.reasons + ["rejected by the test"]
        return v
    return fake


def test_implausible_shared_model_is_repaired_with_per_image_cameras(sfm_run, monkeypatch, tmp_path):
    from repaint_nerf.core.sfm import judge as judge_mod
    from repaint_nerf.core.sfm.run import sfm_scene

    monkeypatch.setattr(judge_mod, "judge", _reject({"shared"}))
    said = []
    scene = sfm_scene(sfm_run["photos"], tmp_path / "ws", progress=lambda p, f, m: said.append(m))
    rep = scene.extra["sfm"]
    assert rep["verdict"]["trusted"] and rep["verdict"]["cameras"] == "per-image"
    assert [a["cameras"] for a in rep["attempts"]] == ["shared", "per-image"] and "retry" in rep["seconds"]
    assert rep["verdict"]["figures"]["n_cameras"] == VIEWS  # one camera per registered photo
    assert any("implausible" in m for m in said) and scene.kind == "unbounded"


def test_a_model_that_stays_implausible_is_an_error_not_registered(sfm_run, monkeypatch, tmp_path, capsys):
    from repaint_nerf.app.cli import main
    from repaint_nerf.core.sfm import judge as judge_mod

    monkeypatch.setattr(judge_mod, "judge", _reject({"shared", "per-image"}))
    ws = tmp_path / "ws"
    assert main(["sfm", str(sfm_run["photos"]), "--workspace", str(ws)]) == 2
    out = capsys.readouterr()
    assert "rejected by the test" in out.err and "no plausible model" in out.err
    assert "registered" not in out.out and "Traceback" not in out.err
    monkeypatch.undo()  # the cached failure answers again, without mapping, even with an honest judge
    t0 = time.perf_counter()
    assert main(["sfm", str(sfm_run["photos"]), "--workspace", str(ws)]) == 2
    assert "no plausible model" in capsys.readouterr().err and time.perf_counter() - t0 < 5.0
