"""View panel: display mode, field of view, snap to a training view, reset, render resolution."""
from __future__ import annotations

from imgui_bundle import imgui

from repaint_nerf.app.viewport import MODE_LABELS

MODE_TIPS = {"rgb": "the rendered colours", "depth": "the rendered depth (near is bright)",
             "feature": "the semantic feature field, its first three principal components as colours",
             "similarity": "each pixel's similarity to the selected patch (bright: alike)",
             "mask": "the colours with the selection (similarity above the threshold) in yellow"}


def draw(app) -> None:
    s = app.state
    opened = imgui.collapsing_header("View", imgui.TreeNodeFlags_.default_open.value)
    imgui.set_item_tooltip("what the view shows and from where")
    if not opened:
        return
    modes = app.viewport.available_modes() if app.viewport is not None else ["rgb"]
    style = imgui.get_style()
    right = imgui.get_cursor_screen_pos().x + imgui.get_content_region_avail().x
    for i, m in enumerate(modes):
        if i and imgui.get_item_rect_max().x + _radio_width(m, style) <= right:
            imgui.same_line()  # the modes wrap onto a new row where the panel is narrow
        if imgui.radio_button(MODE_LABELS[m], s.view_mode == m):
            s.view_mode = m
        imgui.set_item_tooltip(MODE_TIPS.get(m, MODE_LABELS[m]))
    cam = app.camera
    if cam is None:
        return
    _, s.photo_frame = imgui.checkbox("Photo frame", s.photo_frame)
    imgui.set_item_tooltip("show the view in the training photos' aspect (a portrait capture shows portrait); "
                           "off: fill the whole view area")
    changed, fov = imgui.slider_float("Field of view", cam.fov_y, 10.0, 120.0, "%.0f deg")
    imgui.set_item_tooltip("the view's vertical field of view")
    if changed:
        cam.set_fov(fov)
    n = int(s.scene_info.get("views", 0))
    if n:
        _, s.snap_index = imgui.slider_int("Training view", s.snap_index, 0, n - 1)
        imgui.set_item_tooltip("which training camera Snap to training view jumps to")
        if imgui.button("Snap to training view"):
            app.snap_to_view(s.snap_index)
        imgui.set_item_tooltip("look through that training camera (its photo's viewpoint and field of view)")
    if imgui.button("Reset view"):
        cam.reset()
    imgui.set_item_tooltip("back to the view the editor opened with (key R)")
    imgui.same_line()
    imgui.text(f"render {s.render_scale * 100:.0f}%  {s.render_ms:.0f} ms")
    imgui.push_style_color(imgui.Col_.text, style.color_(imgui.Col_.text_disabled))
    imgui.text_wrapped("drag: orbit  right/middle drag: pan  wheel: zoom  arrows, +/-, R")
    imgui.pop_style_color()


def _radio_width(mode: str, style) -> float:
    """Width of a radio button with its label, plus the spacing before it on a shared row."""
    return (imgui.get_frame_height() + style.item_inner_spacing.x + imgui.calc_text_size(MODE_LABELS[mode]).x
            + style.item_spacing.x)
