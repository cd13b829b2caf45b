"""The window's cheap drawing in a real window: the viewport's picture blitted opaque under imgui's windows, only the
bars beside it cleared, and a panel whose draw list did not change blitted from its last rasterization instead of
drawn again; each frame must look as the plain full draw does."""
from __future__ import annotations

import numpy as np
import pytest

WIDTH, HEIGHT = 640, 400
PANEL = (440.0, 0.0, 200.0, 400.0)  # x, y, w, h of the panel window
PICTURE = (60.0, 20.0, 320.0, 360.0)  # the picture's rect, bars left and right of it and above and below


def _picture(ctx):
    """A 32x36 texture stored top row first, as the viewport's: red at the top-left texel, blue at the bottom-right,
    a grey ramp elsewhere."""
    img = np.zeros((36, 32, 4), np.uint8)
    img[..., :3] = np.linspace(40, 200, 32, dtype=np.uint8)[None, :, None]
    img[..., 3] = 255
    img[:4, :4, :3] = (255, 0, 0)
    img[-4:, -4:, :3] = (0, 0, 255)
    return ctx.texture((32, 36), 4, img.tobytes())


def _frame(window, text: str, cached: bool, picture, capture: bool = True):
    """One UI frame: a panel window with `text`, the picture under the rest; returns the screen."""
    from imgui_bundle import imgui

    from repaint_nerf.app.editor import _bars

    window.begin_frame()
    imgui.set_next_window_pos(imgui.ImVec2(*PANEL[:2]))
    imgui.set_next_window_size(imgui.ImVec2(*PANEL[2:]))
    imgui.begin("Panel", None, imgui.WindowFlags_.no_move | imgui.WindowFlags_.no_resize)
    panel = imgui.get_window_draw_list()
    imgui.text(text)
    imgui.button("a button")
    imgui.end()
    area = (0.0, 0.0, PANEL[0], float(HEIGHT))
    return window.end_frame(capture=capture, bare=_bars(area, PICTURE), underlay=(picture, PICTURE),
                            cached=(panel, PANEL) if cached else None)


@pytest.fixture
def window(xvfb_display):
    from repaint_nerf.app.window import Window

    w = Window(width=WIDTH, height=HEIGHT)
    try:
        yield w
    finally:
        w.close()


def test_picture_is_blitted_upright_and_only_the_bars_are_cleared(window):
    picture = _picture(window.ctx)
    for _ in range(3):  # imgui's first frames lay windows out
        shot = _frame(window, "step 1", False, picture)
    x, y, w, h = (int(v) for v in PICTURE)
    assert tuple(shot[y + 2, x + 2]) == (255, 0, 0), "the texture's first row is the picture's top"
    assert tuple(shot[y + h - 3, x + w - 3]) == (0, 0, 255)
    inside = shot[y + h // 2, x + 8:x + w - 8, 0].astype(int)
    assert np.all(np.diff(inside) >= 0) and inside[-1] - inside[0] > 100, "bilinear upsampling of the ramp"
    bars = [shot[y:y + h, 2:x - 2], shot[y:y + h, x + w + 2:int(PANEL[0]) - 2], shot[2:y - 2, 5:int(PANEL[0]) - 5],
            shot[y + h + 2:HEIGHT - 2, 5:int(PANEL[0]) - 5]]
    clear = np.array([0.1, 0.1, 0.12]) * 255
    for bar in bars:
        assert bar.size and np.abs(bar.reshape(-1, 3) - clear).max() <= 1.5, "a bar holds the clear colour"


def test_unchanged_panel_is_blitted_and_looks_as_drawn(window):
    picture = _picture(window.ctx)
    for _ in range(3):
        drawn = _frame(window, "step 1", False, picture)
    cache = window._window_cache
    for _ in range(4):
        cached = _frame(window, "step 1", True, picture)
    assert cache.redraws == 1, "an unchanged panel is rasterized once, then blitted"
    np.testing.assert_array_equal(cached, drawn)
    changed = _frame(window, "step 2", True, picture)
    assert cache.redraws == 2, "a changed panel is drawn again"
    px, pw = int(PANEL[0]), int(PANEL[2])
    assert not np.array_equal(changed[:, px:px + pw], drawn[:, px:px + pw]), "the new text is on screen"
    for _ in range(3):
        redrawn = _frame(window, "step 2", False, picture)
    np.testing.assert_array_equal(changed, redrawn)


def test_bars_are_the_area_outside_the_picture():
    from repaint_nerf.app.editor import _bars

    area, inner = (0.0, 10.0, 100.0, 50.0), (20.0, 15.0, 60.0, 40.0)
    strips = _bars(area, inner)
    mask = np.zeros((60, 100), bool)
    for x, y, w, h in strips + [inner]:
        assert not mask[int(y):int(y + h), int(x):int(x + w)].any(), "no overlaps"
        mask[int(y):int(y + h), int(x):int(x + w)] = True
    assert mask[10:60].all() and not mask[:10].any()
    assert _bars(area, area) == []


def test_new_glyphs_reach_the_gpu_when_the_cached_panel_is_first(window):
    """A window after an unchanged cached panel, first in the draw order, shows text in glyphs never drawn before
    (imgui bakes them on demand, as a texture update that some render call must make): that frame uploads them, and
    it looks as the full draw does."""
    from imgui_bundle import imgui

    picture = _picture(window.ctx)

    def frame(later: str | None, cached: bool):
        window.begin_frame()
        imgui.set_next_window_pos(imgui.ImVec2(*PANEL[:2]))
        imgui.set_next_window_size(imgui.ImVec2(*PANEL[2:]))
        imgui.begin("Panel", None, imgui.WindowFlags_.no_move | imgui.WindowFlags_.no_resize)
        panel = imgui.get_window_draw_list()
        imgui.text("step 1")
        imgui.end()
        if later is not None:
            imgui.set_next_window_pos(imgui.ImVec2(20, 20))
            imgui.set_next_window_size(imgui.ImVec2(300, 120))
            imgui.begin("Later", None, imgui.WindowFlags_.no_move | imgui.WindowFlags_.no_resize)
            imgui.push_font(None, 31.0)  # a size no text had: every glyph of it is new
            imgui.text(later)
            imgui.pop_font()
            imgui.end()
        return window.end_frame(capture=True, underlay=(picture, PICTURE), cached=(panel, PANEL) if cached else None)

    for _ in range(3):
        frame(None, True)
    shown = frame("Wq 7&", True)
    textures = imgui.get_draw_data().textures
    assert all(textures[i].status == imgui.ImTextureStatus.ok for i in range(textures.size())), \
        "the frame that first drew the glyphs uploaded them"
    for _ in range(2):
        shown = frame("Wq 7&", True)
    for _ in range(2):
        drawn = frame("Wq 7&", False)
    np.testing.assert_array_equal(shown, drawn)


def _lines_frame(window, lines: list[str], cached: bool, picture):
    """A frame whose panel holds `lines` of text, then a button and a slider, over the picture."""
    from imgui_bundle import imgui

    window.begin_frame()
    imgui.set_next_window_pos(imgui.ImVec2(*PANEL[:2]))
    imgui.set_next_window_size(imgui.ImVec2(*PANEL[2:]))
    imgui.begin("Panel", None, imgui.WindowFlags_.no_move | imgui.WindowFlags_.no_resize)
    panel = imgui.get_window_draw_list()
    for line in lines:
        imgui.text(line)
    imgui.button("a button")
    imgui.slider_float("value", 0.25, 0.0, 1.0)
    imgui.end()
    return window.end_frame(capture=True, underlay=(picture, PICTURE), cached=(panel, PANEL) if cached else None)


@pytest.mark.parametrize("change", [
    {1: "step 1002"},  # digits changed in place
    {1: "step 10020", 6: "loss 0.0410"},  # two lines apart, one longer: what follows it moves in the buffers
    {0: "Training: paused"},  # the first line, so every triangle after it sits elsewhere in the buffers
])
def test_a_few_changed_lines_are_redrawn_alone_and_look_as_the_full_draw(window, change):
    """A panel whose status lines changed is rasterized again only in the rects the changed text covers (the rest
    of the cached pixels stay), and the screen is the one a full draw of the new panel gives, pixel for pixel."""
    picture = _picture(window.ctx)
    lines = ["Training: running", "step 1001", "PSNR 24.31 dB", "steps/s 5.6", "render 41 ms", "scale 0.50",
             "loss 0.0412", "a line that does not change"]
    new = [change.get(i, line) for i, line in enumerate(lines)]
    for _ in range(3):
        _lines_frame(window, lines, True, picture)
    cache = window._window_cache
    partial, redraws = cache.partial_redraws, cache.redraws
    shown = _lines_frame(window, new, True, picture)
    assert cache.redraws == redraws + 1 and cache.partial_redraws == partial + 1, "the panel was redrawn in part"
    assert 0.0 < cache.damaged < 0.15 * len(change), "only the changed lines' rects were rasterized"
    for _ in range(3):
        drawn = _lines_frame(window, new, False, picture)
    np.testing.assert_array_equal(shown, drawn)
    back = _lines_frame(window, lines, True, picture)  # and back: the old text again, in part
    for _ in range(3):
        full = _lines_frame(window, lines, False, picture)
    np.testing.assert_array_equal(back, full)


def test_changed_triangles_are_found_wherever_they_sit_in_the_buffers():
    """`_changed` finds the triangles that differ between two lists: one changed in place, and a longer middle
    with the rows after it shifted."""
    from repaint_nerf.app.window import _changed

    rng = np.random.default_rng(0)
    old = rng.integers(0, 2 ** 32, (50, 20), dtype=np.uint64).astype(np.uint32)
    new = old.copy()
    new[[7, 30]] += 1
    a, b = _changed(old, new)
    np.testing.assert_array_equal(a, old[[7, 30]])
    np.testing.assert_array_equal(b, new[[7, 30]])
    longer = np.concatenate([old[:10], rng.integers(0, 2 ** 32, (3, 20), dtype=np.uint64).astype(np.uint32),
                             old[10:]])
    a, b = _changed(old, longer)
    assert len(a) == 0 and np.array_equal(b, longer[10:13])
    a, b = _changed(old, old)
    assert len(a) == 0 and len(b) == 0


def _tri_rows(boxes, clip=(0.0, 0.0, 640.0, 400.0)) -> np.ndarray:
    """Triangle rows as `window._triangles` makes them, one triangle per (x0, y0, x1, y1) box (its corners)."""
    rows = []
    for i, (x0, y0, x1, y1) in enumerate(boxes):
        verts = np.zeros((3, 5), np.float32)
        verts[:, :2] = [(x0, y0), (x1, y0), (x1, y1)]
        verts[:, 2] = i  # a texture coordinate that tells the triangles apart
        rows.append(np.concatenate([verts.reshape(-1).view(np.uint32),
                                    np.array(clip, np.float32).view(np.uint32), [np.uint32(1)]]))
    return np.array(rows, np.uint32)


def test_damage_bands_follow_the_changed_triangles():
    """`_damage` groups the changed triangles into bands down the window (with a pixel's margin), one rect over
    them all past MAX_DAMAGE_RECTS, and a full redraw where the clip rects leave the pixel grid or the change covers
    most of the window."""
    from types import SimpleNamespace

    from repaint_nerf.app.window import MAX_DAMAGE_RECTS, _damage

    dd = SimpleNamespace(framebuffer_scale=SimpleNamespace(x=1.0, y=1.0), display_pos=SimpleNamespace(x=0.0, y=0.0))
    rect = (440, 0, 200, 400)  # GL origin, the window's full height
    lines = [(450.0, 10.0 + 20 * k, 600.0, 24.0 + 20 * k) for k in range(12)]
    old = _tri_rows(lines)

    def changed(ks):
        boxes = [(x0 + 5, y0, x1 + 5, y1) if k in ks else (x0, y0, x1, y1) for k, (x0, y0, x1, y1) in enumerate(lines)]
        return _tri_rows(boxes)

    assert _damage(old, old, dd, 400, rect) == []
    one = _damage(old, changed({2}), dd, 400, rect)
    assert one == [((449, 400 - 65, 157, 16), (449.0, 49.0, 606.0, 65.0))]  # the old and the new place, a px around
    two = _damage(old, changed({2, 9}), dd, 400, rect)
    assert [r[1][1] for r in two] == [49.0, 189.0]
    many = _damage(old, changed(set(range(0, 12, 2))), dd, 400, rect)  # 6 lines apart
    assert MAX_DAMAGE_RECTS < 6 and len(many) == 1 and many[0][1][1] == 9.0 and many[0][1][3] == 225.0
    off_grid = _tri_rows(lines, clip=(0.5, 0.0, 640.0, 400.0))
    assert _damage(off_grid, _tri_rows([(x0 + 5, y0, x1, y1) for x0, y0, x1, y1 in lines], (0.5, 0.0, 640.0, 400.0)),
                   dd, 400, rect) is None
    big = [(445.0, 5.0, 635.0, 395.0)]
    assert _damage(_tri_rows(big), _tri_rows([(446.0, 5.0, 635.0, 395.0)]), dd, 400, rect) is None
