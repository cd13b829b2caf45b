"""View panel: display mode, field of view, snap to a training view, reset, render resolution."""
from __future__ import annotations

from imgui_bundle import imgui

from repaint_nerf.app.viewport import MODE_LABELS


def draw(app) -> None:
    s = app.state
    if not imgui.collapsing_header("View", imgui.TreeNodeFlags_.default_open.value):
        return
    modes = app.viewport.available_modes() if app.viewport is not None else ["rgb"]
    style = imgui.get_style()
    right = imgui.get_cursor_screen_pos().x + imgui.get_content_region_avail().x
    for i, m in enumerate(modes):
        if i and imgui.get_item_rect_max().x + _radio_width(m, style) <= right:
            imgui.same_line()  # the modes wrap onto a new row where the panel is narrow
        if imgui.radio_button(MODE_LABELS[m], s.view_mode == m):
            s.view_mode = m
    cam = app.camera
    if cam is None:
        return
    changed, fov = imgui.slider_float("Field of view", cam.fov_y, 10.0, 120.0, "%.0f deg")
    if changed:
        cam.set_fov(fov)
    n = int(s.scene_info.get("views", 0))
    if n:
        _, s.snap_index = imgui.slider_int("Training view", s.snap_index, 0, n - 1)
        if imgui.button("Snap to training view"):
            app.snap_to_view(s.snap_index)
    if imgui.button("Reset view"):
        cam.reset()
    imgui.same_line()
    imgui.text(f"render {s.render_scale * 100:.0f}%  {s.render_ms:.0f} ms")
    imgui.push_style_color(imgui.Col_.text, style.color_(imgui.Col_.text_disabled))
    imgui.text_wrapped("drag: orbit  right/middle drag: pan  wheel: zoom  arrows, +/-, R")
    imgui.pop_style_color()


def _radio_width(mode: str, style) -> float:
    """Width of a radio button with its label, plus the spacing before it on a shared row."""
    return (imgui.get_frame_height() + style.item_inner_spacing.x + imgui.calc_text_size(MODE_LABELS[mode]).x
            + style.item_spacing.x)
