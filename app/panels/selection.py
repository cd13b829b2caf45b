"""Selection panel: the patch tool, the live threshold slider, clear, and apply-to-all-views."""
from __future__ import annotations

from imgui_bundle import imgui

from app.panels.common import remember_item, unavailable


def draw(app) -> None:
    s = app.state
    if not imgui.collapsing_header("Selection", imgui.TreeNodeFlags_.default_open.value):
        return
    if unavailable(app, "select"):
        return
    if s.scene_info.get("loaded") and not s.scene_info.get("feature_head", True):
        imgui.text_wrapped("this field has no feature head: open the scene's dataset with a new workspace to select")
        return
    if imgui.radio_button("Navigate", s.tool == "navigate"):
        s.tool = "navigate"
    imgui.same_line()
    if imgui.radio_button("Select patch", s.tool == "select"):
        s.tool = "select"
    remember_item(app, "select_tool")
    imgui.text_disabled("drag a rectangle; shift adds, ctrl subtracts")
    # The threshold is a shader uniform: moving it redraws the mask in this frame, it does not re-render.
    _, s.threshold = imgui.slider_float("Threshold", s.threshold, 0.0, 1.0, "%.3f")
    remember_item(app, "threshold")
    if not s.has_selection:
        imgui.text("nothing selected")
        return
    if imgui.button("Clear selection"):
        app.clear_selection()
    imgui.same_line()
    if imgui.button("Apply to all views"):
        app.call("masks_for_all_views", float(s.threshold))
    if s.masks_done is not None:
        imgui.text(f"masks for {s.masks_done} views saved")
