"""Feature teachers: the default teacher's contract and separation, the ONNX backend against torch,
the PCA codec and the on-disk cache."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from repaint_nerf.core.errors import ModelNotFoundError, UserError
from repaint_nerf.core.teachers.base import FeatureTeacher, l2_normalize
from repaint_nerf.core.teachers.cache import build_feature_store
from repaint_nerf.core.teachers.codec import PCACodec, sample_codes, upsample_codes
from repaint_nerf.core.teachers.feature_default import DEFAULT_THRESHOLD, DefaultFeatureTeacher


def toy_image(size: int = 64, seed: int = 0, shift: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Grey noisy background, a shaded red disc and a green striped square: (rgb uint8, labels)."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float32)
    img = np.full((size, size, 3), 0.6, np.float32) + rng.normal(0, 0.01, (size, size, 3))
    lab = np.zeros((size, size), np.int32)
    c = size * 0.3 + shift
    disc = (yy - c) ** 2 + (xx - c) ** 2 < (size * 0.2) ** 2
    shade = np.clip(1.0 - (xx - c + yy - c) / (size * 0.5), 0.35, 1.0)
    img[disc] = (np.array([0.85, 0.15, 0.1]) * shade[..., None])[disc]
    lab[disc] = 1
    sq = (yy > size * 0.55) & (yy < size * 0.9) & (xx > size * 0.5 + shift) & (xx < size * 0.88 + shift)
    stripes = np.where((xx // 3) % 2 == 0, 1.0, 0.45)
    img[sq] = (np.array([0.15, 0.7, 0.2]) * stripes[..., None])[sq]
    lab[sq] = 2
    return (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8), lab


def iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / max(1, (a | b).sum()))


def test_default_teacher_contract():
    img, _ = toy_image()
    t = DefaultFeatureTeacher()
    assert isinstance(t, FeatureTeacher)
    f = t(img)
    assert f.shape == (64, 64, t.dim) and f.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(f, axis=-1), 1.0, atol=1e-5)
    np.testing.assert_array_equal(f, DefaultFeatureTeacher()(img))  # deterministic
    assert t.config() != DefaultFeatureTeacher(bandwidth=2.0).config()
    rgba = np.concatenate([img, np.full((64, 64, 1), 255, np.uint8)], 2)
    np.testing.assert_allclose(t(rgba), f, atol=1e-6)


def test_default_teacher_rejects_bad_input():
    with pytest.raises(UserError):
        DefaultFeatureTeacher()(np.zeros((4, 4, 5), np.uint8))


def test_cosine_is_a_gaussian_kernel_of_the_descriptor():
    t = DefaultFeatureTeacher(dim=512)
    rng = np.random.default_rng(1)
    x = rng.normal(size=(200, 14)).astype(np.float32) * 0.5
    y = x + rng.normal(size=x.shape).astype(np.float32) * 0.6
    cos = np.sum(t.embed(x) * t.embed(y), -1)
    ref = np.exp(-np.sum((x - y) ** 2, -1) / (2 * t.cfg.bandwidth ** 2))
    assert np.abs(cos - ref).mean() < 0.05


def test_patch_query_separates_objects_across_views():
    t = DefaultFeatureTeacher()
    views = [toy_image(seed=s, shift=3 * s) for s in range(3)]
    feats = [t(im) for im, _ in views]
    _, lab0 = views[0]
    for obj in (1, 2):
        ys, xs = np.nonzero(lab0 == obj)
        cy, cx = int(np.median(ys)), int(np.median(xs))
        q = l2_normalize(feats[0][cy - 2:cy + 3, cx - 2:cx + 3].reshape(-1, t.dim).mean(0))
        for f, (_, lab) in zip(feats, views):
            assert iou(f @ q > DEFAULT_THRESHOLD, lab == obj) > 0.8, obj


def test_l2_normalize_zero_vector_is_zero_not_nan():
    out = l2_normalize(np.zeros((3, 4)))
    assert np.all(out == 0) and not np.isnan(out).any()


def test_pca_codec_preserves_dot_products_and_round_trips():
    rng = np.random.default_rng(0)
    low = rng.normal(size=(5000, 6)) @ rng.normal(size=(6, 40))
    f = l2_normalize(low + 0.001 * rng.normal(size=low.shape))
    codec = PCACodec.fit(f, k=8)
    assert codec.dims == 8 and codec.explained > 0.999
    np.testing.assert_allclose(codec.basis.T @ codec.basis, np.eye(8), atol=1e-5)
    c = codec.encode(f.reshape(100, 50, 40)).reshape(-1, 8).astype(np.float32)
    gram_ref = f[:200] @ f[:200].T
    np.testing.assert_allclose(c[:200] @ c[:200].T, gram_ref, atol=5e-3)
    np.testing.assert_allclose(codec.decode(c), f, atol=5e-3)
    assert PCACodec.fit(f, k=200).dims == 40  # never more than D (and never above 64)


def test_sample_codes_matches_full_resolution_upsampling():
    rng = np.random.default_rng(0)
    codes = rng.normal(size=(6, 8, 3)).astype(np.float32)
    full = upsample_codes(codes, (12, 16))
    vv, uu = torch.meshgrid(torch.arange(12), torch.arange(16), indexing="ij")
    got = sample_codes(torch.from_numpy(codes), (12, 16), uu.reshape(-1), vv.reshape(-1)).reshape(12, 16, 3)
    np.testing.assert_allclose(got.numpy(), full, atol=1e-5)


def test_fitted_images_wait_for_their_codes_at_half_the_memory(tmp_path):
    """The fitted images' features are kept, as float16, until the basis exists to encode them (one teacher pass
    each): wide features (a blended teacher's 216 channels) of 16 fitted 288x512 images held 2 GB as float32. Their
    codes match encoding the float32 features to within one float16 step of the stored codes."""
    import tracemalloc

    rng = np.random.default_rng(0)
    n = 16
    feats = [rng.normal(0, 1, (128, 128, 160)).astype(np.float32) for _ in range(n)]

    class Wide(DefaultFeatureTeacher):
        dim = 160

        def __call__(self, image):
            return feats[int(image[0, 0, 0])].copy()

    imgs = [np.full((128, 128, 3), i, np.uint8) for i in range(n)]
    tracemalloc.start()  # few samples for the fit, so that the held features are what the peak is made of
    store = build_feature_store(imgs, Wide(), tmp_path, dims=8, fit_images=n, samples_per_image=256)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    held = sum(f.nbytes for f in feats)  # what keeping them as float32 takes
    assert peak < 0.75 * held, (peak, held)
    for i, f in enumerate(feats):
        want = torch.from_numpy(np.asarray(store.codec.encode(f), np.float32))
        torch.testing.assert_close(store.codes[i].float(), want, atol=2e-3, rtol=1e-3)


def test_feature_cache_computes_once_and_serves_targets(tmp_path):
    imgs = [toy_image(seed=s, shift=s)[0] for s in range(3)]
    calls = []

    class Counting(DefaultFeatureTeacher):
        def __call__(self, image):
            calls.append(1)
            return super().__call__(image)

    t = Counting()
    store = build_feature_store(imgs, t, tmp_path, dims=16, scale=0.5, fit_images=2)
    first = len(calls)
    assert first == 3  # fit images are encoded from the same pass
    again = build_feature_store(imgs, t, tmp_path, dims=16, scale=0.5, fit_images=2)
    assert len(calls) == first
    for a, b in zip(store.codes, again.codes):
        assert torch.equal(a, b)
    assert store.codes[0].dtype == torch.float16 and store.codes[0].shape == (32, 32, 16)
    img = torch.tensor([0, 2, 1, 2])
    u, v = torch.tensor([0, 5, 63, 30]), torch.tensor([0, 7, 63, 40])
    tg = store.gather(img, u, v)
    assert tg.shape == (4, 16)
    np.testing.assert_allclose(tg[1].numpy(), store.full(2)[7, 5].numpy(), atol=1e-6)
    # the compressed code keeps the teacher's similarity structure
    f = t(imgs[0])
    proj = f @ store.codec.basis
    assert np.abs(store.full(0).numpy() - proj).mean() < 0.02
    other = build_feature_store(imgs, DefaultFeatureTeacher(bandwidth=2.0), tmp_path, dims=16)
    assert other.files[0].parent.parent != store.files[0].parent.parent  # config keys the cache


@pytest.fixture(scope="module")
def tiny_onnx(tmp_path_factory):
    from tiny_onnx import export_feature_net

    return export_feature_net(tmp_path_factory.mktemp("onnx") / "tiny.onnx", dim=6)


@pytest.mark.parametrize("input_size", [None, (24, 40)])
def test_onnx_teacher_matches_torch(tiny_onnx, input_size):
    from repaint_nerf.core.teachers.feature_onnx import OnnxFeatureTeacher

    net, path = tiny_onnx
    mean, std = (0.4, 0.5, 0.6), (0.2, 0.25, 0.3)
    teacher = OnnxFeatureTeacher(path, input_size=input_size, mean=mean, std=std)
    img, _ = toy_image(48)
    img = img[:, :44].copy()
    got = teacher(img)
    x = torch.from_numpy(img).float().permute(2, 0, 1)[None] / 255.0
    if input_size is not None:
        x = torch.nn.functional.interpolate(x, size=input_size, mode="bilinear", align_corners=False)
    x = (x - torch.tensor(mean)[:, None, None]) / torch.tensor(std)[:, None, None]
    with torch.no_grad():
        y = net(x)
    y = torch.nn.functional.interpolate(y, size=img.shape[:2], mode="bilinear", align_corners=False)
    ref = torch.nn.functional.normalize(y[0].permute(1, 2, 0), dim=-1, eps=1e-8).numpy()
    assert got.shape == (48, 44, 6)
    np.testing.assert_allclose(got, ref, atol=1e-5)


def test_onnx_teacher_missing_or_invalid_model(tmp_path, monkeypatch):
    from repaint_nerf.core.teachers.feature_onnx import ENV_FEATURE_MODEL, OnnxFeatureTeacher

    monkeypatch.delenv(ENV_FEATURE_MODEL, raising=False)
    with pytest.raises(ModelNotFoundError, match="--feature-model"):
        OnnxFeatureTeacher(None)
    with pytest.raises(ModelNotFoundError, match="missing.onnx"):
        OnnxFeatureTeacher(tmp_path / "missing.onnx")
    bad = tmp_path / "bad.onnx"
    bad.write_bytes(b"not a model")
    with pytest.raises(ModelNotFoundError, match="bad.onnx") as exc:
        OnnxFeatureTeacher(bad)
    assert ENV_FEATURE_MODEL in str(exc.value)
    monkeypatch.setenv(ENV_FEATURE_MODEL, str(tmp_path / "env.onnx"))
    with pytest.raises(ModelNotFoundError, match="env.onnx"):
        OnnxFeatureTeacher()


def _patch_query(preset: str, tmp_path):
    """(similarity maps, per-view object-id masks, edited object id) of the default teacher's patch query on the
    edited object of a generated preset (64 px, 6 views), as `bench teacher` places it."""
    import json
    from pathlib import Path

    import cv2

    from repaint_nerf.core.bench.teacher import place_patch
    from repaint_nerf.core.scene.loaders.detect import load_scene
    from repaint_nerf.core.synth.generate import make_scene

    root = make_scene(preset, tmp_path / preset, size=64, views=6, seed=0, test_views=1)
    scene = load_scene(root, splits=("train",))
    obj = int(json.loads((root / "gt" / "objects.json").read_text())["edited_object_id"])
    ids = []
    for n in scene.train.names:
        m = cv2.imread(str(root / "gt" / "train" / f"{Path(n).stem}_mask.png"), cv2.IMREAD_UNCHANGED)
        ids.append(m if m.ndim == 2 else m[..., 0])
    t = DefaultFeatureTeacher()
    feats = [t(im) for im in scene.train.images]
    view, (y0, y1, x0, x1) = place_patch([m == obj for m in ids])
    q = l2_normalize(feats[view][y0:y1, x0:x1].reshape(-1, t.dim).mean(0))
    return [f @ q for f in feats], ids, obj


def test_distinct_colours_patch_query_reaches_the_target_iou(tmp_path):
    """On the demo preset (objects of distinct colours) the patch query on the edited object reaches the
    issue's 0.90 IoU at the default threshold (measured 0.944)."""
    from repaint_nerf.core.bench.teacher import mask_iou

    sims, ids, obj = _patch_query("demo", tmp_path)
    got = mask_iou(sims, [m == obj for m in ids], DEFAULT_THRESHOLD)
    print(f"demo IoU at {DEFAULT_THRESHOLD}: {got:.3f}")
    assert got > 0.90


def test_similar_preset_patch_query_keeps_the_object_and_ranks_it_first(tmp_path):
    """Four same-red objects told apart only by texture. The weight-free teacher does NOT reach the 0.90 IoU
    target here (measured 0.256: its mask holds every red object), so this test asserts what it does do: the
    mask keeps the edited object (recall measured 0.967) and the object's mean similarity is the highest of
    all objects (measured 0.937 against 0.913, 0.896 and 0.782 for the other reds); telling textures apart
    is left to a learned teacher (--feature-model)."""
    sims, ids, obj = _patch_query("similar", tmp_path)
    inside = sum(int(np.sum((s > DEFAULT_THRESHOLD) & (m == obj))) for s, m in zip(sims, ids))
    recall = inside / sum(int(np.sum(m == obj)) for m in ids)
    mean_sim = {int(i): float(np.mean(np.concatenate([s[m == i] for s, m in zip(sims, ids)])))
                for i in np.unique(np.concatenate([m.ravel() for m in ids]))}
    print(f"similar: recall {recall:.3f}, mean similarity per object {mean_sim}")
    assert recall > 0.9
    assert max(mean_sim, key=mean_sim.get) == obj


def test_feature_stream_hands_over_the_stores_codes_fitted_images_first(tmp_path):
    """Codes arrive one image at a time on a background thread (the PCA's fitted images first), equal to the
    synchronous store's; a stopped stream ends without finishing, and a teacher's error reaches the poller."""
    import threading

    from repaint_nerf.core.teachers.feature_stream import FeatureStream

    imgs = [toy_image(seed=s, shift=s)[0] for s in range(5)]
    gate = threading.Semaphore(0)

    class Gated(DefaultFeatureTeacher):  # one teacher pass per release of the gate
        def __call__(self, image):
            gate.acquire()
            return super().__call__(image)

    gate.release()  # the stream reads the teacher's channel count off one pass before it starts
    stream = FeatureStream(imgs, Gated(), tmp_path / "a", dims=8)
    assert len(stream) == 5 and stream.sizes == [(64, 64)] * 5 and stream.poll() == []
    got = {}
    for _ in range(5):
        gate.release()
    store = stream.wait(timeout=60)
    for i, codes in stream.poll():
        got[i] = codes
    assert stream.complete and list(got)[0] == 0 and sorted(got) == list(range(5))
    reference = build_feature_store(imgs, DefaultFeatureTeacher(), tmp_path / "b", dims=8)
    for i in range(5):
        assert torch.equal(got[i], store.codes[i]) and torch.equal(got[i], reference.codes[i])

    gate.release()
    stopped = FeatureStream(imgs, Gated(), tmp_path / "c", dims=8)
    for _ in range(2):  # the fit uses every image of so few, so no code exists before the fifth pass
        gate.release()
    stopped.stop()
    for _ in range(5):
        gate.release()  # lets a pass in progress end; the stream stops at the next image
    assert stopped.wait(timeout=60) is None and not stopped.complete

    class Broken(DefaultFeatureTeacher):  # breaks after its first pass
        calls = 0

        def __call__(self, image):
            Broken.calls += 1
            if Broken.calls > 1:
                raise UserError("the teacher broke")
            return super().__call__(image)

    broken = FeatureStream(imgs, Broken(), tmp_path / "d", dims=8)
    with pytest.raises(UserError, match="the teacher broke"):
        broken.wait(timeout=60)
    with pytest.raises(UserError, match="the teacher broke"):
        broken.poll()


def test_feature_stream_knows_the_code_size_before_its_pca(tmp_path):
    """A teacher with fewer channels than the asked dims gets codes of its channel count (what the PCA keeps), known
    before any code exists: the trainer sizes the field's feature head from it (a tiny CLIP gave 8 of 12)."""
    from repaint_nerf.core.teachers.feature_stream import FeatureStream

    class Five(DefaultFeatureTeacher):
        def __call__(self, image):
            return super().__call__(image)[..., :5]

    imgs = [toy_image(seed=s)[0] for s in range(3)]
    stream = FeatureStream(imgs, Five(), tmp_path, dims=8)
    assert stream.dims == 5 and stream.wait(timeout=60).dims == 5
    assert FeatureStream(imgs, Five(), tmp_path, dims=8).dims == 5  # read off the cached basis the second time
