"""The viewport's mask overlay (app.viewport) in a headless OpenGL context: it tints the selection's region map
(the similarity where the region grown from the selection reaches) when the engine sends one, else the raw
similarity."""
from __future__ import annotations

import numpy as np
import pytest

moderngl = pytest.importorskip("moderngl")


@pytest.fixture(scope="module")
def ctx():
    try:
        c = moderngl.create_standalone_context(backend="egl")
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
