"""Selection panel: the patch tool, select by text, the live threshold slider, clear, and apply-to-all-views."""
from __future__ import annotations

from imgui_bundle import imgui

from repaint_nerf.app.panels.common import remember_item, unavailable


def draw(app) -> None:
    s = app.state
    opened = imgui.collapsing_header("Selection", imgui.TreeNodeFlags_.default_open.value)
    imgui.set_item_tooltip("select an object through the feature field: a patch (or text) and a threshold")
    if not opened:
        return
    if unavailable(app, "select"):
        return
    if s.scene_info.get("loaded") and not s.scene_info.get("feature_head", True):
        imgui.text_wrapped("this field has no feature head: open the scene's dataset with a new workspace to select")
        return
    if imgui.radio_button("Navigate", s.tool == "navigate"):
        s.tool = "navigate"
    imgui.set_item_tooltip("left drag orbits the camera")
    imgui.same_line()
    if imgui.radio_button("Select patch", s.tool == "select"):
        s.tool = "select"
    remember_item(app, "select_tool")
    imgui.set_item_tooltip("left drag draws a patch: what looks like it, in every view, is selected "
                           "(right drag orbits meanwhile)")
    imgui.text_disabled("drag a rectangle; shift adds, ctrl subtracts")
    _draw_text_query(app)
    # The threshold is a shader uniform: moving it redraws the mask in this frame, it does not re-render.
    moved, s.threshold = imgui.slider_float("Threshold", s.threshold, 0.0, 1.0, "%.3f")
    remember_item(app, "threshold")
    imgui.set_item_tooltip("how alike a pixel must be to the patch to be selected: higher selects less; the "
                           "mask follows at once (ctrl+click to type a value)")
    if moved:
        app.guide.done("threshold")
    if s.auto_threshold is not None:  # on its own line: beside the slider it ran off a 400-px panel
        if imgui.small_button(f"Automatic threshold {s.auto_threshold:.2f}"):
            s.threshold = s.auto_threshold
            app.guide.done("threshold")
        imgui.set_item_tooltip("the threshold chosen from this patch's own similarity (where the region grown "
                               "from the patch stops growing or leaks); click to return to it")
    if not s.has_selection:
        imgui.text("nothing selected")
        return
    _, s.use_geometry = imgui.checkbox("Masks follow the field's depth", s.use_geometry)  # its own line: 400-px panel
    remember_item(app, "use_geometry")
    imgui.set_item_tooltip("shape the masks with the field's geometry: stop at depth edges and at the crease where "
                           "an object rests on its support, let the views outvote each other's leaks and give the "
                           "border pixels to the surface whose depth they share (off: only drop what is not "
                           "connected to the patch in 3D)")
    if imgui.button("Clear selection"):
        app.clear_selection()
    imgui.set_item_tooltip("forget the patches and the mask")
    imgui.same_line()
    if imgui.button("Apply to all views"):
        app.call(app.engine.masks_for_all_views, float(s.threshold), "full" if s.use_geometry else "basic")
    remember_item(app, "apply_all")
    imgui.set_item_tooltip("save a mask per training view at this threshold (Repaint does this itself)")
    if s.masks_done is not None:
        imgui.text(f"masks for {s.masks_done} views saved")


def take_auto_threshold(state, auto: float | None) -> None:
    """After a patch selection: the engine's automatic threshold for it (None for a subtracted patch); the slider
    moves to it for a new selection, and for an added patch unless the user moved the slider."""
    if state.select_rect is None:
        return
    _, mode = state.select_rect
    state.select_rect = None
    if mode == "sub" or auto is None:
        return
    untouched = state.auto_threshold is None or abs(state.threshold - state.auto_threshold) < 1e-6
    if mode == "new" or untouched:
        state.threshold = auto
    state.auto_threshold = auto


def take_refined_threshold(state, auto: float | None) -> None:
    """The patch's automatic threshold once the training views voted on it (Engine.refine_threshold, a moment
    after its mask): the slider follows unless the user moved it meanwhile."""
    if auto is None or state.auto_threshold is None:
        return
    if abs(state.threshold - state.auto_threshold) < 1e-6:
        state.threshold = auto
    state.auto_threshold = auto


def _draw_text_query(app) -> None:
    """A folded "Select by text" section: a prompt and the engine's select_text on the current view (it needs a
    workspace trained with a CLIP-aligned teacher and that teacher's CLIP model)."""
    s = app.state
    opened = imgui.tree_node("Select by text")
    remember_item(app, "text_section")
    imgui.set_item_tooltip("select by a word instead of a patch (needs a CLIP-aligned feature teacher)")
    if not opened:
        return
    _, s.text_query = imgui.input_text("Text", s.text_query)
    remember_item(app, "text_query")
    imgui.set_item_tooltip("what to select, e.g. 'chair'")
    _, s.clip_path = imgui.input_text("CLIP model folder", s.clip_path)
    imgui.set_item_tooltip("the CLIP model of the feature teacher's space (else $REPAINT_NERF_CLIP_PATH); text "
                           "selection needs a workspace trained with a CLIP-aligned --feature-model (LSeg)")
    if imgui.button("Select by text") and s.text_query.strip() and app.camera is not None:
        mode = "add" if imgui.get_io().key_shift and s.has_selection else "new"
        app.call(app.engine.select_text, app.camera.cameras(*app.view_size), s.text_query, mode, s.clip_path or None)
    remember_item(app, "select_text")
    imgui.set_item_tooltip("select what the text names in this view (shift adds to the selection)")
    imgui.tree_pop()
