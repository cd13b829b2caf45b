"""The model flags reach the teachers: `train --feature-model/--depth-model` distil the ONNX teachers and
save the choice, so re-opening a workspace uses the same teacher and cache; a missing model names its
flag; a CLIP-aligned teacher selects by text (`select --text`, Engine.select_text). Tiny random-weight
models are built here (tests/tiny_onnx.py, tests/tiny_diffusion.py), never downloaded."""
from __future__ import annotations

import json

import numpy as np
import pytest

from repaint_nerf.core.errors import ModelNotFoundError, UserError
from repaint_nerf.core.workspace.workspace import Workspace

D = 16  # feature dim of the tiny ONNX teacher and projection dim of the tiny CLIP (over the 12 cached dims)
TRAIN = ["--steps", "8", "--rays", "256", "--max-samples", "96"]


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    """Paths of the tiny models: feature ONNX (D dims), depth ONNX, CLIP with D and with 8 dims."""
    from tiny_diffusion import make_tiny_clip
    from tiny_onnx import export_depth_net, export_feature_net

    root = tmp_path_factory.mktemp("models")
    return {"feature": export_feature_net(root / "feat.onnx", dim=D)[1],
            "depth": export_depth_net(root / "depth.onnx"),
            "clip": make_tiny_clip(root / "clip16", projection_dim=D),
            "clip8": make_tiny_clip(root / "clip8", projection_dim=8)}


@pytest.fixture(scope="module")
def scene(scene_factory):
    from repaint_nerf.core.scene.loaders.detect import load_scene

    root = scene_factory("demo", size=32, views=12)
    return root, load_scene(root)


@pytest.fixture(autouse=True)
def no_model_env(monkeypatch):
    for var in ("REPAINT_NERF_FEATURE_MODEL", "REPAINT_NERF_DEPTH_MODEL", "REPAINT_NERF_CLIP_PATH",
                "REPAINT_NERF_MODELS"):
        monkeypatch.delenv(var, raising=False)


@pytest.fixture(scope="module")
def onnx_ws(scene, models, tmp_path_factory):
    """A workspace trained by the CLI with the ONNX feature and depth teachers."""
    from repaint_nerf.app.cli import main

    ws = tmp_path_factory.mktemp("onnx_ws") / "ws"
    assert main(["train", str(scene[0]), "--workspace", str(ws), *TRAIN, "--feature-model", str(models["feature"]),
                 "--feature-size", "24x16", "--feature-norm", "clip", "--depth-model", str(models["depth"])]) == 0
    return Workspace.open(ws)


def _onnx_teacher(models):
    from repaint_nerf.core.models.clip import CLIP_MEAN, CLIP_STD
    from repaint_nerf.core.teachers.feature_onnx import OnnxFeatureTeacher

    return OnnxFeatureTeacher(models["feature"], input_size=(16, 24), mean=CLIP_MEAN, std=CLIP_STD)


# -- feature teacher ---------------------------------------------------------------------------------------
def test_train_feature_model_saves_the_choice_and_caches_its_features(onnx_ws, scene, models):
    from repaint_nerf.core.teachers.cache import stored_codec, teacher_key

    s = onnx_ws.settings
    assert s["feature_model"] == {"path": str(models["feature"].resolve()), "input_size": [16, 24], "norm": "clip"}
    assert s["teacher"] == "onnx-feat" and s["depth_model"] == str(models["depth"].resolve())
    teacher = _onnx_teacher(models)
    assert [p.name for p in onnx_ws.teachers_dir.iterdir() if p.is_dir()] == [teacher_key(teacher)]
    codec = stored_codec(scene[1].train.images, teacher, onnx_ws.teachers_dir)
    assert codec is not None and codec.basis.shape == (D, 12)
    code_file = next((onnx_ws.teachers_dir / teacher_key(teacher)).glob("*/*.safetensors"))
    from safetensors.numpy import load_file

    from repaint_nerf.core.teachers.base import check_image
    from repaint_nerf.core.teachers.cache import image_hash

    images = [check_image(im) for im in scene[1].train.images]
    i = [image_hash(im) for im in images].index(code_file.stem)
    np.testing.assert_allclose(load_file(str(code_file))["codes"].astype(np.float32),
                               codec.encode(teacher(images[i])).astype(np.float32), atol=2e-3)


def test_reopening_uses_the_saved_teacher_and_cache(onnx_ws, models, tmp_path, monkeypatch):
    import repaint_nerf.core.teachers.cache as cache
    from repaint_nerf.core.engine import Engine

    monkeypatch.setenv("REPAINT_NERF_FEATURE_MODEL", str(tmp_path / "other.onnx"))  # the saved choice wins
    built, real = [], cache.build_feature_store
    monkeypatch.setattr(cache, "build_feature_store", lambda images, teacher, *a, **k: (
        built.append(teacher), real(images, teacher, *a, **k))[1])
    before = sorted(p.relative_to(onnx_ws.teachers_dir) for p in onnx_ws.teachers_dir.rglob("*"))
    eng = Engine("cpu")
    eng.load(onnx_ws.root)
    eng.trainer.feature_stream.wait()  # the codes are read on the teacher's thread
    assert len(built) == 1 and built[0].config() == _onnx_teacher(models).config()
    assert sorted(p.relative_to(onnx_ws.teachers_dir) for p in onnx_ws.teachers_dir.rglob("*")) == before
    assert onnx_ws.settings["feature_model"]["path"] == str(models["feature"].resolve())


def test_missing_feature_model_names_the_flag_and_loses_nothing(onnx_ws, scene, tmp_path, capsys):
    from repaint_nerf.app.cli import main

    fresh = tmp_path / "fresh"
    assert main(["train", str(scene[0]), "--workspace", str(fresh), *TRAIN,
                 "--feature-model", str(tmp_path / "missing.onnx")]) == 2
    err = capsys.readouterr().err
    assert "--feature-model" in err and "missing.onnx" in err and "Traceback" not in err
    assert not fresh.exists()  # checked before any workspace is made
    bad = tmp_path / "bad.onnx"
    bad.write_bytes(b"not a model")
    settings, versions = onnx_ws.settings, [v.id for v in onnx_ws.versions]
    assert main(["train", str(scene[0]), "--workspace", str(onnx_ws.root), *TRAIN, "--resume",
                 "--feature-model", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "bad.onnx" in err and "--feature-model" in err
    assert onnx_ws.settings == settings and [v.id for v in onnx_ws.versions] == versions


def test_saved_model_that_moved_is_a_clear_error(tmp_path, models):
    from repaint_nerf.core.teachers.stage1_targets import workspace_feature_teacher

    ws = Workspace.create(tmp_path / "ws", {"feature_model": {"path": str(tmp_path / "gone.onnx"),
                                                              "input_size": None, "norm": "imagenet"}})
    with pytest.raises(ModelNotFoundError, match="settings.json 'feature_model'") as exc:
        workspace_feature_teacher(ws)
    assert "gone.onnx" in str(exc.value) and "--feature-model" in str(exc.value)


@pytest.mark.parametrize("text", ["24", "0x5", "axb", "24x", "-3x4"])
def test_feature_size_parsing(text, capsys, tmp_path, scene):
    from repaint_nerf.app.cli import main
    from repaint_nerf.app.commands.train import parse_size

    assert parse_size("24x16") == (16, 24) and parse_size(" 8 X 9 ") == (9, 8) and parse_size(None) is None
    with pytest.raises(UserError, match="--feature-size"):
        parse_size(text)
    assert main(["train", str(scene[0]), "--workspace", str(tmp_path / "ws"), f"--feature-size={text}"]) == 2
    assert "WIDTHxHEIGHT" in capsys.readouterr().err and not (tmp_path / "ws").exists()


def test_choice_order_flag_setting_env_default(tmp_path, models, monkeypatch):
    import repaint_nerf.core.teachers.feature_lite as lite
    from repaint_nerf.core.teachers.stage1_targets import LITE_BLEND, FeatureModel, choose_feature_model

    ws = Workspace.create(tmp_path / "ws")
    assert choose_feature_model(ws) == (FeatureModel(LITE_BLEND), "default")  # CI installs the lite extra
    with monkeypatch.context() as m:
        m.setattr(lite, "available", lambda: False)
        assert choose_feature_model(ws) == (FeatureModel(), "default")  # without it, the built-in teacher
    with pytest.raises(UserError, match="--feature-model"):
        choose_feature_model(ws, input_size=(8, 8))
    monkeypatch.setenv("REPAINT_NERF_MODELS", str(models["feature"].parent))
    (models["feature"].parent / "features.onnx").write_bytes(models["feature"].read_bytes())
    assert choose_feature_model(ws)[0].path.endswith("features.onnx")
    monkeypatch.setenv("REPAINT_NERF_FEATURE_MODEL", str(models["feature"]))
    assert choose_feature_model(ws, norm="clip") == (FeatureModel(str(models["feature"]), None, "clip"), "env")
    ws.update_settings(feature_model=None)
    assert choose_feature_model(ws) == (FeatureModel(), "setting")
    assert choose_feature_model(ws, str(models["feature"]), (4, 6))[0].input_size == (4, 6)
    assert choose_feature_model(ws, "default")[0] == FeatureModel()
    (models["feature"].parent / "features.onnx").unlink()


def test_engine_load_with_a_chosen_teacher_trains_with_it_and_notes_a_change(scene, tmp_path):
    """The editor's "Feature teacher" reaches Engine.load as `train --feature-model` does: a new workspace trains with
    the chosen built-in teacher and saves it; another choice on reopening is noted (the editor shows the notes); no
    choice keeps the saved one."""
    from repaint_nerf.core.engine import Engine
    from repaint_nerf.core.teachers.stage1_targets import LITE_BLEND

    eng = Engine("cpu")
    info = eng.load(scene[0], tmp_path / "ws", feature_model=LITE_BLEND)
    assert eng.train_for(0.2)["step"] >= 1
    saved = json.loads((tmp_path / "ws" / "settings.json").read_text())
    assert saved["feature_model"]["path"] == LITE_BLEND and saved["teacher"] == LITE_BLEND
    assert info["settings"]["feature_model"]["path"] == LITE_BLEND and not any("changed" in n for n in info["notes"])
    eng.save()
    info = eng.load(tmp_path / "ws", feature_model="default")
    assert any(n.startswith("feature teacher changed to default") for n in info["notes"]), info["notes"]
    info = eng.load(tmp_path / "ws")
    assert info["settings"]["feature_model"] is None and not any("changed" in n for n in info["notes"])


# -- depth teacher -------------------------------------------------------------------------------------------
def _sparse_points(scene) -> "DepthPriors":
    """20 sparse depth points per training image (the 32 px demo triangulates too few to align to)."""
    from repaint_nerf.core.teachers.depth import DepthPriors, SparseDepth

    rng = np.random.default_rng(0)
    sizes = [im.shape[:2] for im in scene.train.images]
    pts = [SparseDepth(*(rng.uniform(0, s, 20).astype(np.float32) for s in (w, h)),
                       rng.uniform(2, 4, 20).astype(np.float32)) for h, w in sizes]
    return DepthPriors(pts, sizes, "points")


def test_depth_model_gives_aligned_monocular_depth(scene, models, tmp_path, monkeypatch):
    import repaint_nerf.core.teachers.depth_sparse as depth_sparse
    from repaint_nerf.core.teachers.depth import DenseDepth, SparseDepth
    from repaint_nerf.core.teachers.depth_onnx import OnnxDepthTeacher, aligned_monocular_depth
    from repaint_nerf.core.teachers.stage1_targets import depth_priors

    sc = scene[1]
    monkeypatch.setattr(depth_sparse, "depth_for_scene", _sparse_points)
    ws = Workspace.create(tmp_path / "ws")
    notes: list = []
    got = depth_priors(sc, ws, notes, model=str(models["depth"]))
    want = aligned_monocular_depth(OnnxDepthTeacher(models["depth"]), sc.train.images, _sparse_points(sc))
    assert got.source == "onnx-depth-depth+points" and not notes
    assert all(isinstance(p, DenseDepth) for p in got.priors)
    for a, b in zip(got.priors, want.priors):
        assert type(a) is type(b)
        if isinstance(a, DenseDepth):
            np.testing.assert_allclose(a.depth, b.depth, rtol=1e-5)
            assert np.array_equal(a.valid, b.valid)
    assert ws.settings["depth_model"] == str(models["depth"].resolve())
    files = sorted(p.name for p in ws.teachers_dir.glob("depth_priors*.safetensors"))
    assert len(files) == 2 and "depth_priors.safetensors" in files  # sparse + this model's aligned depth
    assert depth_priors(sc, ws).source == got.source  # the saved choice, from its cache
    other = tmp_path / "other_depth.onnx"
    other.write_bytes(models["depth"].read_bytes())
    assert depth_priors(sc, ws, model=str(other)).source.startswith("onnx-depth-other_depth+")
    assert len(list(ws.teachers_dir.glob("depth_priors*.safetensors"))) == 3  # never the first model's file
    sparse = depth_priors(sc, ws, model="none")
    assert all(isinstance(p, SparseDepth) for p in sparse.priors) and ws.settings["depth_model"] is None


def test_depth_model_without_sparse_points_says_so(scene, models, tmp_path, monkeypatch):
    import repaint_nerf.core.teachers.depth_sparse as depth_sparse
    from repaint_nerf.core.teachers.stage1_targets import depth_priors

    def no_matches(scene):
        raise ValueError("too few matches to triangulate")

    monkeypatch.setattr(depth_sparse, "depth_for_scene", no_matches)
    notes: list = []
    assert depth_priors(scene[1], Workspace.create(tmp_path / "ws"), notes, model=str(models["depth"])) is None
    assert any("too few matches" in n for n in notes) and any("depth.onnx not used" in n for n in notes)
    with pytest.raises(ModelNotFoundError, match="--depth-model"):
        depth_priors(scene[1], Workspace.create(tmp_path / "ws2"), model=str(tmp_path / "nope.onnx"))


# -- text queries ----------------------------------------------------------------------------------------------
def test_encode_text_is_a_unit_vector_of_the_teacher_dim(models):
    from repaint_nerf.core.teachers.feature_default import DefaultFeatureTeacher
    from repaint_nerf.core.teachers.text import text_teacher

    t = text_teacher(_onnx_teacher(models), models["clip"])
    e = t.encode_text("a red ball")
    assert e.shape == (D,) and e.dtype == np.float32 and abs(np.linalg.norm(e) - 1) < 1e-5
    assert not np.allclose(e, t.encode_text("leaves"))
    with pytest.raises(UserError, match="CLIP-aligned") as exc:
        text_teacher(_onnx_teacher(models), models["clip8"])
    assert "16-dim" in str(exc.value) and "8 dims" in str(exc.value) and "patch" in str(exc.value)
    with pytest.raises(UserError, match="not CLIP-aligned") as exc:
        text_teacher(DefaultFeatureTeacher(), models["clip"])
    assert "select with a patch" in str(exc.value)
    with pytest.raises(ModelNotFoundError, match="--clip-path"):
        text_teacher(_onnx_teacher(models), None)


def test_select_text_cli_writes_masks_from_the_projected_embedding(onnx_ws, scene, models, tmp_path, capsys):
    from repaint_nerf.app.cli import main
    from repaint_nerf.core.select.masks import load_masks
    from repaint_nerf.core.select.selection import Selection
    from repaint_nerf.core.teachers.cache import stored_codec

    out = tmp_path / "masks"
    assert main(["select", str(onnx_ws.root), "--text", "a red ball", "--clip-path", str(models["clip"]),
                 "--out", str(out)]) == 0
    assert "selected by text 'a red ball'" in capsys.readouterr().out
    n = len(scene[1].train)
    assert len(list(out.glob("mask_*.png"))) == n and len(load_masks(onnx_ws.masks_dir)) == n
    assert json.loads((out / "selection.json").read_text())["texts"] == ["a red ball"]
    sel = Selection.load(onnx_ws)
    # The expected query, computed without the implementation: the CLIP text embedding straight from
    # transformers, L2-normalised, projected on the cache's stored PCA basis: (e - mean) @ basis.
    import torch
    from transformers import CLIPModel, CLIPTokenizer

    model = CLIPModel.from_pretrained(models["clip"], local_files_only=True).eval()
    tok = CLIPTokenizer.from_pretrained(models["clip"], local_files_only=True)(["a red ball"], return_tensors="pt")
    with torch.no_grad():
        out = model.get_text_features(input_ids=tok.input_ids, attention_mask=tok.attention_mask)
    e = (out if isinstance(out, torch.Tensor) else out.pooler_output)[0].double().numpy()
    e /= np.linalg.norm(e)
    codec = stored_codec(scene[1].train.images, _onnx_teacher(models), onnx_ws.teachers_dir)  # the stored basis
    want = (e - codec.mean.astype(np.float64)) @ codec.basis.astype(np.float64)
    np.testing.assert_allclose(sel.positives[0].numpy(), want, rtol=2e-3, atol=2e-3)  # codes are stored as fp16
    assert sel.texts == ["a red ball"] and sel.patches == [] and sel.positives[0].shape == (12,)
    # no --threshold: the text query's automatic threshold (Otsu over every view's similarities) is used
    assert sel.auto_threshold is not None and sel.threshold == sel.auto_threshold


def test_select_text_cli_bad_inputs(onnx_ws, models, tmp_path, capsys):
    from repaint_nerf.app.cli import main

    base = ["select", str(onnx_ws.root), "--out", str(tmp_path / "o")]
    assert main(base + ["--text", "a ball", "--clip-path", str(models["clip8"])]) == 2
    assert "CLIP-aligned" in capsys.readouterr().err
    assert main(base + ["--text", "a ball", "--add", "0,0,4,4"]) == 2
    assert "--add" in capsys.readouterr().err
    assert main(base + ["--patch", "0,0,4,4"]) == 2
    assert "--view" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(base + ["--view", "0"])  # neither --patch nor --text
    with pytest.raises(SystemExit):
        main(base + ["--text", "x", "--patch", "0,0,4,4"])


def test_engine_select_text(onnx_ws, models):
    from repaint_nerf.core.engine import Engine

    eng = Engine("cpu")
    eng.load(onnx_ws.root)
    cams = eng.info()["cameras"][0]
    sim = eng.select_text(cams, "a red ball", clip_path=str(models["clip"]))
    assert sim.shape == (32, 32) and np.isfinite(sim).all()
    assert eng.selection.texts == ["a red ball"] and not eng.selection.cleanup
    eng.select_text(cams, "leaves", "add", clip_path=str(models["clip"]))
    assert eng.selection.texts == ["a red ball", "leaves"]
    with pytest.raises(UserError, match="subtract with a patch"):
        eng.select_text(cams, "x", "sub", clip_path=str(models["clip"]))
    with pytest.raises(UserError, match="CLIP-aligned"):
        eng.select_text(cams, "x", clip_path=str(models["clip8"]))
