"""The viewport's mask overlay (app.viewport) in a headless OpenGL context: it tints the selection's region map
(the similarity where the region grown from the selection reaches) when the engine sends one, else the raw
similarity."""
from __future__ import annotations

import numpy as np
import pytest

moderngl = pytest.importorskip("moderngl")


@pytest.fixture(scope="module")
def ctx():
    from repaint_nerf.core.synth.raster import standalone_context

    try:  # through the one helper: a window a later test opens must then use EGL too (Mesa refuses GLX after it)
        c = standalone_context()
    except Exception as exc:  # noqa: BLE001  no EGL: the GUI tests say so too
        pytest.fail(f"no headless OpenGL context ({exc}); install Mesa's EGL (install.sh does)")
    yield c
    c.release()


def _tinted(viewport, size, threshold) -> np.ndarray:
    tex = viewport.draw(size, "mask", threshold)
    img = np.frombuffer(tex.read(), np.uint8).reshape(size[1], size[0], 4)[..., :3].astype(int)
    return img[..., 0] > 100  # the tint is yellow over a black picture


def test_the_mask_overlay_tints_the_region_map_not_every_similar_pixel(ctx):
    from repaint_nerf.app.viewport import Viewport

    h, w = 32, 48
    sim = np.full((h, w), 0.1, np.float32)
    sim[8:24, 4:20] = 0.8  # the selected object
    sim[8:24, 28:44] = 0.8  # a look-alike of its colour, walled off
    region = np.where(np.arange(w)[None, :] < 24, sim, -1.0).astype(np.float32)
    vp = Viewport(ctx)
    vp.upload_frame({"rgb": np.zeros((h, w, 3), np.uint8), "similarity": sim, "region": region})
    tinted = _tinted(vp, (w, h), 0.5)
    assert tinted[12:20, 8:16].all() and not tinted[12:20, 32:40].any()
    assert not tinted[:4].any()
    vp.upload_frame({"rgb": np.zeros((h, w, 3), np.uint8), "similarity": sim})  # a view that sees no anchor
    tinted = _tinted(vp, (w, h), 0.5)
    assert tinted[12:20, 8:16].all() and tinted[12:20, 32:40].all()
    vp.upload_similarity(sim, region)
    vp.upload_similarity(None, region)  # a cleared selection clears both
    assert "region" not in vp.textures and "mask" not in vp.available_modes()
    vp.release()


def test_a_frame_is_made_ready_to_show_on_the_render_thread():
    """display_frame: colour as uint8 (rounded), the depth and feature maps' display ranges read from a strided
    sample that matches the full percentiles."""
    from repaint_nerf.app.viewport import display_frame

    rng = np.random.default_rng(0)
    h, w = 400, 500  # 200k pixels: the ranges come from a sample
    rgb = rng.random((h, w, 3), dtype=np.float32) * 1.2 - 0.1
    depth = rng.gamma(2.0, 1.0, (h, w)).astype(np.float32)
    depth[:50] = 0.0  # no surface: not in the range
    pca = rng.normal(size=(h, w, 3)).astype(np.float32) * np.array([1.0, 2.0, 3.0], np.float32)
    out = display_frame({"rgb": rgb, "depth": depth, "feature_pca": pca})
    assert out["rgb"].dtype == np.uint8
    assert np.abs(out["rgb"].astype(int) - np.clip(rgb, 0, 1) * 255).max() <= 0.5 + 1e-3, "rounded, clipped"
    full = np.percentile(depth[depth > 0], (1, 99))
    assert out["depth_range"][0] == pytest.approx(full[0], rel=0.05)
    assert out["depth_range"][1] == pytest.approx(full[1], rel=0.05)
    lo, hi = np.percentile(pca.reshape(-1, 3), (1, 99), axis=0)
    np.testing.assert_allclose(out["feature_range"][0], lo, rtol=0.05)
    np.testing.assert_allclose(out["feature_range"][1], hi, rtol=0.05)
    assert display_frame({"rgb": out["rgb"]})["rgb"] is out["rgb"], "a uint8 picture is kept as it is"


def test_maps_go_to_the_gpu_when_a_view_mode_first_draws_them(ctx):
    """A frame's depth and feature maps are uploaded only when their view mode draws; each mode draws the newest
    frame's map, and a mode offered before its upload draws it."""
    from repaint_nerf.app.viewport import Viewport

    h, w = 16, 24
    vp = Viewport(ctx)
    frame = {"rgb": np.full((h, w, 3), 200, np.uint8), "depth": np.full((h, w), 2.0, np.float32),
             "feature_pca": np.zeros((h, w, 3), np.float32)}
    vp.upload_frame(frame)
    assert "rgb" not in vp.textures and "depth" not in vp.textures, "nothing is uploaded before a draw"
    assert {"rgb", "depth", "feature"} <= set(vp.available_modes())
    img = np.frombuffer(vp.draw((w, h), "rgb").read(), np.uint8).reshape(h, w, 4)
    assert np.abs(img[..., :3].astype(int) - 200).max() <= 1, "uint8 colour shows as it was sent"
    assert "rgb" in vp.textures and "depth" not in vp.textures and "feature" not in vp.textures
    vp.draw((w, h), "depth")
    assert "depth" in vp.textures and "feature" not in vp.textures
    vp.upload_frame({**frame, "rgb": np.full((h, w, 3), 20, np.uint8)})
    img = np.frombuffer(vp.draw((w, h), "rgb").read(), np.uint8).reshape(h, w, 4)
    assert np.abs(img[..., :3].astype(int) - 20).max() <= 1, "the newest frame is drawn"
    vp.release()
