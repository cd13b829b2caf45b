"""The feature cache's fast path (core.teachers.projected): a teacher's features sampled at pixels and projected
onto the PCA basis without their full-resolution map are the plain path's values (the teacher's own dense map,
then `PCACodec.encode`), for the ImageNet teacher (real and tiny networks, with and without region pooling, odd
sizes), the blend, a teacher without `prepare`, and the cache built from them."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from repaint_nerf.core.teachers.codec import PCACodec
from repaint_nerf.core.teachers.feature_blend import BlendFeatureTeacher
from repaint_nerf.core.teachers.feature_default import DefaultFeatureTeacher
from repaint_nerf.core.teachers.feature_lite import LiteFeatureTeacher, build_network, load_network
from repaint_nerf.core.teachers.projected import Dense, encode, prepared


def _photo_like(h: int, w: int, seed: int) -> np.ndarray:
    """Smooth colour blobs, an edge and grain: regions of several sizes for the superpixels."""
    rng = np.random.default_rng(seed)
    small = rng.uniform(0, 255, (max(2, h // 16), max(2, w // 16), 3)).astype(np.float32)
    import cv2

    img = cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC)
    img[:, w // 3:w // 3 + 3] = (20, 200, 40)
    img += rng.normal(0, 10, img.shape)
    return np.clip(img, 0, 255).astype(np.uint8)


@pytest.fixture(scope="module")
def tiny():
    torch.manual_seed(0)
    return build_network(width_coefficient=0.25, num_classes=10).eval()


@pytest.fixture(scope="module")
def real():
    return load_network()


def _check(teacher, image: np.ndarray, dims: int = 8) -> None:
    dense = teacher(image)
    flat = dense.reshape(-1, dense.shape[-1])
    codec = PCACodec.fit(flat[::7], k=dims)
    prep = prepared(teacher, image)
    assert prep.size == dense.shape[:2] and prep.dim == dense.shape[2]
    idx = np.random.default_rng(1).choice(flat.shape[0], 500, replace=False)
    np.testing.assert_allclose(prep.at(idx), flat[idx], atol=2e-4)
    for scale in (1.0, 0.5):
        want = codec.encode(dense, scale=scale).astype(np.float32)
        got = encode(codec, prep, scale=scale).astype(np.float32)
        assert got.shape == want.shape
        np.testing.assert_allclose(got, want, atol=2e-3)  # float16 codes: a unit in the last place or two
    proj, length = prep.project(codec.basis)
    np.testing.assert_allclose(length.numpy(), np.linalg.norm(flat, axis=1), atol=3e-4)  # Dense holds float16


@pytest.mark.parametrize("size", [(61, 90), (128, 72), (33, 40)])
def test_lite_prepared_matches_its_dense_map(tiny, size):
    _check(LiteFeatureTeacher(network=tiny), _photo_like(*size, seed=size[0]))


def test_lite_without_pooling_matches(tiny):
    _check(LiteFeatureTeacher(network=tiny, pooled_weight=0.0), _photo_like(70, 52, seed=3))


def test_real_network_and_blend_match(real):
    image = _photo_like(160, 96, seed=5)
    _check(LiteFeatureTeacher(network=real), image, dims=12)
    blend = BlendFeatureTeacher([(LiteFeatureTeacher(network=real), 0.5), (DefaultFeatureTeacher(), 0.5)])
    _check(blend, image, dims=12)


def test_a_teacher_without_prepare_takes_its_dense_map():
    teacher = DefaultFeatureTeacher()
    image = _photo_like(40, 56, seed=2)
    assert isinstance(prepared(teacher, image), Dense)
    _check(teacher, image)


def test_the_cache_holds_the_dense_paths_codes(tiny, tmp_path):
    from repaint_nerf.core.teachers.cache import build_feature_store

    teacher = BlendFeatureTeacher([(LiteFeatureTeacher(network=tiny), 0.5), (DefaultFeatureTeacher(), 0.5)])
    images = [_photo_like(48, 64, seed=s) for s in range(4)]
    store = build_feature_store(images, teacher, tmp_path, dims=6, fit_images=2)
    for i, image in enumerate(images):
        want = store.codec.encode(teacher(image)).astype(np.float32)
        np.testing.assert_allclose(store.codes[i].float().numpy(), want, atol=2e-3)
