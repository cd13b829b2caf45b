"""Teachers from the transformers models users already have (DINOv2 / CLIP / SigLIP features, MaskCLIP text
selection, DPT / Depth Anything depth, SAM mask refinement), each loaded from a folder and from a populated
local Hugging Face cache by model id, never downloaded; tiny random models from tests/tiny_transformers.py."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from repaint_nerf.core.errors import ModelNotFoundError, UserError
from repaint_nerf.core.workspace.workspace import Workspace

TRAIN = ["--steps", "8", "--rays", "256", "--max-samples", "96"]
IDS = {"dinov2": "tiny-org/dinov2", "clip": "tiny-org/clip", "siglip": "tiny-org/siglip", "dpt": "tiny-org/dpt",
       "depth_anything": "tiny-org/depth-anything", "sam": "tiny-org/sam"}


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    """name -> folder of every tiny model, each also installed in one local hub cache (models['hf_home'])."""
    from tiny_transformers import BUILDERS, install_in_hf_cache, make_tiny_dinov2

    root = tmp_path_factory.mktemp("hf_models")
    out = {name: build(root / name) for name, build in BUILDERS.items()}
    out["dinov2_reg"] = make_tiny_dinov2(root / "dinov2_reg", registers=2)
    hf_home = root / "hf_home"
    for name, model_id in IDS.items():
        install_in_hf_cache(out[name], hf_home, model_id)
    out["hf_home"] = hf_home
    return out


@pytest.fixture(autouse=True)
def isolated_env(monkeypatch, models):
    for var in ("REPAINT_NERF_FEATURE_MODEL", "REPAINT_NERF_DEPTH_MODEL", "REPAINT_NERF_CLIP_PATH",
                "REPAINT_NERF_SAM_PATH", "REPAINT_NERF_MODELS", "HF_HUB_CACHE"):
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setenv("HF_HOME", str(models["hf_home"]))
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")


def _image(h: int = 40, w: int = 56, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (h, w, 3), dtype=np.uint8)


# -- where a model comes from ----------------------------------------------------------------------------------
def test_cached_snapshot_follows_refs_main_and_never_guesses(models, tmp_path):
    from repaint_nerf.core.models.paths import cached_snapshot, is_model_id, locate_model

    snap = cached_snapshot(IDS["dinov2"])
    assert snap == models["hf_home"] / "hub" / "models--tiny-org--dinov2" / "snapshots" / "0123abcd"
    assert locate_model("feature", IDS["dinov2"]) == snap
    assert locate_model("feature", models["dinov2"]) == models["dinov2"]
    (snap.parent.parent / "refs" / "main").write_text("gone")
    assert cached_snapshot(IDS["dinov2"]) is None  # refs/main names a snapshot that is not there
    (snap.parent.parent / "refs" / "main").write_text("0123abcd")
    one = tmp_path / "hub" / "models--a--b" / "snapshots" / "r1"
    one.mkdir(parents=True)
    assert cached_snapshot("a/b", {"HF_HUB_CACHE": str(tmp_path / "hub")}) == one  # no refs: the only snapshot
    assert not is_model_id("/abs/path") and not is_model_id("./rel") and not is_model_id("m.onnx")
    assert is_model_id("facebook/dinov2-small") and is_model_id("dinov2")


@pytest.mark.parametrize("kind,flag,var", [("feature", "--feature-model", "REPAINT_NERF_FEATURE_MODEL"),
                                           ("depth", "--depth-model", "REPAINT_NERF_DEPTH_MODEL"),
                                           ("sam", "--sam-path", "REPAINT_NERF_SAM_PATH")])
def test_missing_model_names_flag_env_and_cache(kind, flag, var, models, tmp_path):
    from repaint_nerf.core.models.paths import locate_model, resolve_model_path

    with pytest.raises(ModelNotFoundError) as by_id:
        locate_model(kind, "nobody/absent")
    with pytest.raises(ModelNotFoundError) as by_path:
        locate_model(kind, tmp_path / "absent")
    with pytest.raises(ModelNotFoundError) as nothing:
        resolve_model_path(kind, None, None, environ={})
    assert "Hugging Face cache" in str(by_id.value) and str(models["hf_home"] / "hub") in str(by_id.value)
    assert str(tmp_path / "absent") in str(by_path.value)
    for err in (by_id, by_path, nothing):
        assert flag in str(err.value) and var in str(err.value) and "downloaded" in str(err.value)


# -- dense features ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["dinov2", "dinov2_reg", "clip", "siglip"])
def test_feature_teacher_from_folder_and_cache(name, models):
    from repaint_nerf.core.teachers.feature_hf import HFFeatureTeacher
    from repaint_nerf.core.teachers.stage1_targets import FeatureModel, make_feature_teacher

    t = make_feature_teacher(FeatureModel(str(models[name])))
    assert isinstance(t, HFFeatureTeacher)
    img = _image()
    f = t(img)
    assert f.shape == (40, 56, t.dim) and f.dtype == np.float32 and np.isfinite(f).all()
    np.testing.assert_allclose(np.linalg.norm(f, axis=-1), 1.0, atol=1e-5)
    assert t.dim == (8 if name == "clip" else 16)  # CLIP: MaskCLIP features in the 8-dim joint space
    assert t.model_input(40, 56) == (128, 176)  # short side 16 patches (over the 32 px image size), aspect kept
    assert f.std(axis=(0, 1)).max() > 1e-3  # the features vary over the image
    if name in IDS:
        cached = make_feature_teacher(FeatureModel(IDS[name]))
        np.testing.assert_allclose(cached(img), f, atol=1e-6)
    sized = HFFeatureTeacher(models[name], input_size=(20, 30))
    assert sized.input_size == (16, 32) and sized(img).shape == f.shape  # snapped to patch multiples


def _upsampled_unit(tokens: torch.Tensor, grid: tuple[int, int], size: tuple[int, int]) -> np.ndarray:
    """An independent reference: (N, D) patch tokens -> torch bilinear upsampling -> unit vectors (H, W, D)."""
    g = tokens.reshape(*grid, -1).permute(2, 0, 1)[None]
    up = torch.nn.functional.interpolate(g, size=size, mode="bilinear", align_corners=False)
    return torch.nn.functional.normalize(up[0].permute(1, 2, 0), dim=-1).numpy()


def test_dinov2_features_are_its_patch_tokens_upsampled(models):
    from transformers import Dinov2WithRegistersModel

    from repaint_nerf.core.teachers._onnx import prepare_input
    from repaint_nerf.core.teachers.feature_hf import HFFeatureTeacher

    t = HFFeatureTeacher(models["dinov2_reg"])
    img = _image(24, 32)
    x = torch.from_numpy(prepare_input(img, (128, 168), (0.485, 0.456, 0.406), (0.229, 0.224, 0.225)))
    assert t.model_input(24, 32) == (128, 168)  # 128 x 170.7 -> patch multiples
    ref_model = Dinov2WithRegistersModel.from_pretrained(models["dinov2_reg"], local_files_only=True).eval()
    with torch.no_grad():
        tokens = ref_model(pixel_values=x).last_hidden_state[0, 1 + 2:]  # after the class and 2 register tokens
    np.testing.assert_allclose(t(img), _upsampled_unit(tokens, (16, 21), (24, 32)), atol=1e-5)


def test_maskclip_features_live_in_the_text_space(models):
    """MaskCLIP: the last layer's value path of its own input (no attention mixing), post layer norm, visual
    projection; recomputed here from the hidden states transformers returns."""
    from transformers import CLIPModel

    from repaint_nerf.core.teachers._onnx import prepare_input
    from repaint_nerf.core.teachers.feature_hf import HFFeatureTeacher

    t = HFFeatureTeacher(models["clip"])
    img = _image(32, 32)
    m = CLIPModel.from_pretrained(models["clip"], local_files_only=True).eval()
    assert t.model_input(32, 32) == (128, 128)
    x = torch.from_numpy(prepare_input(img, (128, 128), t.backbone.mean, t.backbone.std))
    with torch.no_grad():
        h = m.vision_model(pixel_values=x, output_hidden_states=True,
                           interpolate_pos_encoding=True).hidden_states[-2]
        last = m.vision_model.encoder.layers[-1]
        v = last.self_attn.out_proj(last.self_attn.v_proj(last.layer_norm1(h)))
        tokens = m.visual_projection(m.vision_model.post_layernorm(v))[0, 1:]
    assert tokens.shape[-1] == m.config.projection_dim == t.dim
    np.testing.assert_allclose(t(img), _upsampled_unit(tokens, (16, 16), (32, 32)), atol=1e-5)
    assert t.clip is not None and t.clip.tokenizer is not None


def test_unsupported_or_broken_feature_model_is_clear(models, tmp_path, capsys, scene_factory):
    from repaint_nerf.app.cli import main
    from repaint_nerf.core.teachers.stage1_targets import FeatureModel, make_feature_teacher

    with pytest.raises(ModelNotFoundError, match="model_type 'sam' is not a supported feature backbone"):
        make_feature_teacher(FeatureModel(str(models["sam"])))
    ws = tmp_path / "ws"
    assert main(["train", str(scene_factory("demo", size=32, views=12)), "--workspace", str(ws),
                 "--feature-model", IDS["sam"]]) == 2
    assert "not a supported feature backbone" in capsys.readouterr().err and not ws.exists()  # checked first
    assert main(["train", str(scene_factory("demo", size=32, views=12)), "--workspace", str(ws),
                 "--depth-model", str(models["dinov2"])]) == 2
    assert "as a depth-estimation model" in capsys.readouterr().err and not ws.exists()
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "config.json").write_text(json.dumps({"model_type": "dinov2"}))
    with pytest.raises(ModelNotFoundError, match="could not load the dinov2 model") as exc:
        make_feature_teacher(FeatureModel(str(broken)))
    assert str(broken) in str(exc.value)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(ModelNotFoundError, match="neither config.json nor an .onnx"):
        make_feature_teacher(FeatureModel(str(empty)))


# -- training with them, selecting by text with one CLIP -----------------------------------------------------------
@pytest.fixture(scope="module")
def scene(scene_factory):
    from repaint_nerf.core.scene.loaders.detect import load_scene

    root = scene_factory("demo", size=32, views=12)
    return root, load_scene(root)


@pytest.fixture(scope="module")
def clip_ws(scene, models, tmp_path_factory):
    """A workspace trained by the CLI with the tiny CLIP, named by its cached model id, as the feature teacher."""
    from repaint_nerf.app.cli import main

    mp = pytest.MonkeyPatch()
    mp.setenv("HF_HOME", str(models["hf_home"]))
    try:
        ws = tmp_path_factory.mktemp("clip_ws") / "ws"
        assert main(["train", str(scene[0]), "--workspace", str(ws), *TRAIN, "--no-depth",
                     "--feature-model", IDS["clip"]]) == 0
    finally:
        mp.undo()
    return Workspace.open(ws)


def test_train_saves_the_cached_id(clip_ws):
    s = clip_ws.settings
    assert s["feature_model"] == {"path": IDS["clip"], "input_size": None, "norm": "imagenet"}
    assert s["teacher"] == "hf-clip-maskclip"


def test_select_text_with_one_clip_alone(clip_ws, scene, models, tmp_path, capsys):
    from repaint_nerf.app.cli import main
    from repaint_nerf.core.select.masks import load_masks
    from repaint_nerf.core.select.selection import Selection
    from repaint_nerf.core.teachers.cache import stored_codec
    from repaint_nerf.core.teachers.stage1_targets import workspace_feature_teacher
    from repaint_nerf.core.teachers.text import text_teacher

    out = tmp_path / "masks"
    assert main(["select", str(clip_ws.root), "--text", "a red ball", "--out", str(out)]) == 0  # no --clip-path
    assert "selected by text 'a red ball'" in capsys.readouterr().out
    assert len(load_masks(clip_ws.masks_dir)) == len(scene[1].train)
    teacher = workspace_feature_teacher(clip_ws)
    emb = text_teacher(teacher).encode_text("a red ball")
    assert emb.shape == (teacher.dim,) and abs(np.linalg.norm(emb) - 1) < 1e-5
    with torch.no_grad():
        tok = teacher.clip.tokenizer(["a red ball"], return_tensors="pt")
        ref = teacher.clip.model.get_text_features(input_ids=tok.input_ids, attention_mask=tok.attention_mask)
    ref = (ref if isinstance(ref, torch.Tensor) else ref.pooler_output)[0].numpy()
    np.testing.assert_allclose(emb, ref / np.linalg.norm(ref), atol=1e-5)
    codec = stored_codec(scene[1].train.images, teacher, clip_ws.teachers_dir)
    np.testing.assert_allclose(Selection.load(clip_ws).positives[0].numpy(),
                               codec.encode(emb[None, None]).reshape(-1).astype(np.float32), rtol=1e-5, atol=1e-6)


def test_text_needs_a_clip_teacher(models):
    from repaint_nerf.core.teachers.stage1_targets import FeatureModel, make_feature_teacher
    from repaint_nerf.core.teachers.text import text_teacher

    with pytest.raises(UserError, match="not CLIP-aligned") as exc:
        text_teacher(make_feature_teacher(FeatureModel(IDS["dinov2"])), models["clip"])
    assert "CLIP model folder or cached id" in str(exc.value)


# -- depth ---------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["dpt", "depth_anything"])
def test_depth_teacher_from_folder_and_cache_aligns_to_sparse_depth(name, models):
    from repaint_nerf.core.teachers.depth import DenseDepth, DepthPriors, SparseDepth
    from repaint_nerf.core.teachers.depth_hf import HFDepthTeacher
    from repaint_nerf.core.teachers.depth_onnx import aligned_monocular_depth
    from repaint_nerf.core.teachers.stage1_targets import make_depth_teacher

    t = make_depth_teacher(str(models[name]))
    assert isinstance(t, HFDepthTeacher) and t.inverse
    img = _image(36, 48)
    rel = t(img)
    assert rel.shape == (36, 48) and rel.dtype == np.float32 and np.isfinite(rel).all() and rel.std() > 1e-3
    np.testing.assert_allclose(make_depth_teacher(IDS[name])(img), rel, atol=1e-6)
    h, w = t.model_input(36, 48)
    assert h % t.net.multiple == 0 and w % t.net.multiple == 0
    z_true = 1.0 / (0.4 * rel + 0.05)  # metric depth whose inverse is affine in the prediction
    rng = np.random.default_rng(1)
    u, v = rng.uniform(0, 48, 50).astype(np.float32), rng.uniform(0, 36, 50).astype(np.float32)
    sparse = DepthPriors([SparseDepth(u, v, z_true[v.astype(int), u.astype(int)].astype(np.float32))], [(36, 48)],
                         "points")
    dense = aligned_monocular_depth(t, [img], sparse).for_image(0)
    assert isinstance(dense, DenseDepth) and dense.valid.all()
    np.testing.assert_allclose(dense.depth, z_true, rtol=1e-3)


def test_depth_priors_with_a_cached_depth_model_save_its_id(scene, models, tmp_path, monkeypatch):
    import repaint_nerf.core.teachers.depth_sparse as depth_sparse
    from repaint_nerf.core.teachers.depth import DenseDepth, DepthPriors, SparseDepth
    from repaint_nerf.core.teachers.stage1_targets import depth_priors

    def points(sc):
        rng = np.random.default_rng(0)
        sizes = [im.shape[:2] for im in sc.train.images]
        return DepthPriors([SparseDepth(*(rng.uniform(0, s, 20).astype(np.float32) for s in (w, h)),
                                        rng.uniform(2, 4, 20).astype(np.float32)) for h, w in sizes], sizes, "points")

    monkeypatch.setattr(depth_sparse, "depth_for_scene", points)
    ws = Workspace.create(tmp_path / "ws")
    got = depth_priors(scene[1], ws, [], model=IDS["depth_anything"])
    assert got.source == "hf-depth-depth_anything+points" and ws.settings["depth_model"] == IDS["depth_anything"]
    assert any(isinstance(p, DenseDepth) for p in got.priors)
    with pytest.raises(ModelNotFoundError, match="--depth-model"):
        depth_priors(scene[1], ws, model="nobody/absent-depth")
    with pytest.raises(ModelNotFoundError, match="not load 'dinov2' as a depth-estimation model"):
        depth_priors(scene[1], ws, model=str(models["dinov2"]))


# -- SAM refinement ------------------------------------------------------------------------------------------------
def test_mask_prompt_is_the_largest_region_box_and_inside_point():
    from repaint_nerf.core.teachers.sam_refine import grown_box, mask_prompt

    m = np.zeros((40, 50), bool)
    m[10:30, 5:25] = True  # the object
    m[2:4, 40:43] = True   # a stray island the prompt ignores
    box, (px, py) = mask_prompt(m)
    assert box == (5, 10, 25, 30) and 12 <= px <= 17 and 17 <= py <= 22 and m[py, px]
    assert mask_prompt(np.zeros((4, 4), bool)) is None
    g = grown_box(box, 40, 50)
    assert g[8:32, 3:27].all() and g.sum() == 24 * 24


def test_sam_refines_masks_inside_the_prompt_box(models):
    from repaint_nerf.core.models.sam import load_sam
    from repaint_nerf.core.teachers.sam_refine import grown_box, mask_prompt, refine_masks

    sam = load_sam(models["sam"])
    img = np.full((48, 60, 3), 40, np.uint8)
    img[10:30, 20:45] = 230  # a bright object
    field = np.zeros((48, 60), bool)
    field[8:34, 16:42] = True  # the field's mask: the object and a rim of the background
    empty = np.zeros_like(field)
    out = refine_masks([img, img], [field, empty], sam, min_agreement=0.0)
    assert [o.shape for o in out] == [field.shape] * 2 and all(o.dtype == bool for o in out)
    assert not out[1].any()  # an empty view stays empty
    assert not (out[0] & ~grown_box(mask_prompt(field)[0], 48, 60)).any()  # never outside the grown box
    assert not np.array_equal(out[0], field)  # SAM's mask replaced the field's
    kept = refine_masks([img], [field], sam, min_agreement=1.01)  # SAM never agrees enough: masks kept
    assert np.array_equal(kept[0], field)
    cached = refine_masks([img], [field], load_sam(IDS["sam"]), min_agreement=0.0)
    assert np.array_equal(cached[0], out[0])
    small = refine_masks([np.ascontiguousarray(img[::2, ::2])], [field], sam, min_agreement=0.0)
    assert small[0].shape == field.shape  # images at another size are resized to the masks


def test_select_with_sam_path_refines_and_saves_the_choice(clip_ws, scene, models, tmp_path, capsys):
    from repaint_nerf.app.cli import main
    from repaint_nerf.core.select.masks import load_masks
    from repaint_nerf.core.teachers.sam_refine import workspace_refiner

    base = ["select", str(clip_ws.root), "--view", "0", "--patch", "10,10,20,20"]
    assert main(base + ["--out", str(tmp_path / "a"), "--sam-path", IDS["sam"]]) == 0
    assert "SAM-refined" in capsys.readouterr().out and clip_ws.settings["sam_path"] == IDS["sam"]
    assert len(load_masks(tmp_path / "a")) == len(scene[1].train)
    assert workspace_refiner(clip_ws, scene[1].train.images) is not None  # the saved choice, next time
    assert workspace_refiner(clip_ws, scene[1].train.images, "none") is None and clip_ws.settings["sam_path"] is None
    assert workspace_refiner(clip_ws, scene[1].train.images) is None
    assert main(base + ["--out", str(tmp_path / "c"), "--sam-path", str(tmp_path / "nosam")]) == 2
    err = capsys.readouterr().err
    assert "--sam-path" in err and "REPAINT_NERF_SAM_PATH" in err and "Traceback" not in err
    with pytest.raises(ModelNotFoundError, match="not 'sam'"):
        workspace_refiner(clip_ws, scene[1].train.images, str(models["dpt"]))


def test_editor_masks_use_the_workspaces_sam(clip_ws, scene, monkeypatch):
    import repaint_nerf.core.teachers.sam_refine as sam_refine
    from repaint_nerf.core.engine import Engine

    calls = []
    real = sam_refine.refine_masks
    monkeypatch.setattr(sam_refine, "refine_masks", lambda images, masks, sam: calls.append(len(masks)) or
                        real(images, masks, sam))
    clip_ws.update_settings(sam_path=IDS["sam"])
    try:
        eng = Engine("cpu")
        eng.load(clip_ws.root)
        eng.select_text(eng.info()["cameras"][0], "a red ball")
        assert eng.masks_for_all_views(0.5) == len(scene[1].train) and calls == [len(scene[1].train)]
    finally:
        clip_ws.update_settings(sam_path=None)
