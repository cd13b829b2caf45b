"""View panel: display mode, field of view, snap to a training view, reset, render resolution."""
from __future__ import annotations

from imgui_bundle import imgui

from app.viewport import MODE_LABELS


def draw(app) -> None:
    s = app.state
    if not imgui.collapsing_header("View", imgui.TreeNodeFlags_.default_open.value):
        return
    modes = app.viewport.available_modes() if app.viewport is not None else ["rgb"]
    for m in modes:
        if imgui.radio_button(MODE_LABELS[m], s.view_mode == m):
            s.view_mode = m
        imgui.same_line()
    imgui.new_line()
    cam = app.camera
    if cam is None:
        return
    changed, fov = imgui.slider_float("Field of view", cam.fov_y, 10.0, 120.0, "%.0f deg")
    if changed:
        cam.set_fov(fov)
    n = int(s.scene_info.get("views", 0))
    if n:
        _, s.snap_index = imgui.slider_int("Training view", s.snap_index, 0, n - 1)
        imgui.same_line()
        if imgui.button("Snap"):
            app.snap_to_view(s.snap_index)
    if imgui.button("Reset view"):
        cam.reset()
    imgui.same_line()
    imgui.text(f"render {s.render_scale * 100:.0f}%  {s.render_ms:.0f} ms")
    imgui.text_disabled("drag: orbit  right/middle drag: pan  wheel: zoom  arrows, +/-, R")
