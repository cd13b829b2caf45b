"""Scene and training panel: open, training status with a live loss/PSNR plot, pause/resume, save, export."""
from __future__ import annotations

import math

import numpy as np
from imgui_bundle import imgui, implot

from repaint_nerf.app.panels.common import remember_item, unavailable
from repaint_nerf.core.teachers.stage1_targets import (DEFAULT_FEATURE, LITE_BLEND, LITE_FEATURE, feature_choices,
                                                       saved_feature_name)


# What each phase's 'psnr' measures: stage 1 the step's training rays; a repaint the pixels Eq. unmask holds
# to the photos (the selection changes on purpose, so a PSNR over it says nothing).
PSNR_LABELS = {"reconstruct": "PSNR", "repaint": "unmasked PSNR"}
# The "Feature teacher" combo's names and tooltips of the built-in teachers (a model path or id shows as itself).
FEATURE_LABELS = {DEFAULT_FEATURE: "built-in", LITE_BLEND: "efficientnet-lite0 + built-in"}
FEATURE_HELP = {
    DEFAULT_FEATURE: "the built-in teacher: colour and texture pooled over superpixels; no model, nothing to install",
    LITE_FEATURE: "EfficientNet-Lite0, an ImageNet network (the lite extra): tells objects apart by what they are",
    LITE_BLEND: "EfficientNet-Lite0 and the built-in teacher, half and half: what things are and their colour",
}
OTHER_FEATURE_HELP = "the workspace's feature model: a model file, folder or model id"


def status_line(st: dict) -> str:
    """The training status: phase, step, loss and what its PSNR measures; a missing or non-finite value is left out."""
    parts = [f"{st.get('phase', '')} step {st.get('step', 0)}".strip()]
    loss, psnr = st.get("loss"), st.get("psnr")
    if isinstance(loss, (int, float)) and math.isfinite(loss):
        parts.append(f"loss {loss:.4f}")
    if isinstance(psnr, (int, float)) and math.isfinite(psnr):
        parts.append(f"{PSNR_LABELS.get(st.get('phase'), 'PSNR')} {psnr:.2f} dB")
    ready = st.get("features_ready")
    if ready and ready[0] < ready[1]:  # the teacher still runs beside training (core.teachers.feature_stream)
        parts.append(f"teacher features {ready[0]}/{ready[1]} views")
    return "  ".join(parts)


def feature_label(name: str) -> str:
    """How the "Feature teacher" combo names a teacher: 'built-in' for the default one, else its name or path."""
    return FEATURE_LABELS.get(name, name)


def _feature_teacher(app) -> None:
    """The "Feature teacher" combo: what the next Open or Demo scene distils the field's features from (as
    `train --feature-model`); untouched, it shows the loaded workspace's saved teacher and changes nothing."""
    s = app.state
    saved = saved_feature_name(s.scene_info.get("settings") or {})
    shown = s.feature_model or saved
    opened = imgui.begin_combo("Feature teacher", feature_label(shown) if shown else "automatic")
    remember_item(app, "Feature teacher")
    if not opened:
        imgui.set_item_tooltip("what the field's features (selection) are distilled from, used when a scene is "
                               "opened; untouched: the workspace's saved teacher, else $REPAINT_NERF_FEATURE_MODEL, "
                               "else efficientnet-lite0 + built-in where the lite extra is installed, else the "
                               "built-in one")
    else:
        for name in feature_choices(saved, s.feature_model):
            if imgui.selectable(feature_label(name), name == shown)[0]:
                s.feature_model = name
            remember_item(app, f"feature:{name}")
            imgui.set_item_tooltip(f"{FEATURE_HELP.get(name, OTHER_FEATURE_HELP)} (train --feature-model {name})")
        imgui.end_combo()
    if s.feature_model and saved and s.feature_model != saved:
        imgui.text_disabled("(used on the next Open or Demo scene)")


def draw(app) -> None:
    s = app.state
    opened = imgui.collapsing_header("Scene and training", imgui.TreeNodeFlags_.default_open.value)
    imgui.set_item_tooltip("open a scene and watch it reconstruct (test PSNR rises as it trains)")
    if not opened:
        return
    _, s.scene_path = imgui.input_text("Path", s.scene_path)
    imgui.set_item_tooltip("a folder of photos, a NeRF dataset (Blender, nerfstudio, LLFF, COLMAP) or a saved "
                           "workspace; then press Open")
    _feature_teacher(app)
    opened = imgui.button("Open")
    imgui.set_item_tooltip("open the scene at Path (a photo folder is posed by structure from motion first)")
    if opened:
        app.open_scene(s.scene_path or None)
    imgui.same_line()
    demo = imgui.button("Demo scene")
    remember_item(app, "Demo scene")
    imgui.set_item_tooltip("the built-in synthetic scene: needs no photos and no downloaded model")
    if demo:
        app.open_scene(None)
    unavailable(app, "load")
    if s.repair_offer:
        _repair_offer(app)
    info = s.scene_info
    if s.loading:
        imgui.text("loading...")
    elif info.get("loaded"):
        imgui.text(f"{info['name']} ({info['format']}), {info['views']} views")
    else:
        imgui.text("no scene loaded")
    if unavailable(app, "train"):
        return
    changed, s.training = imgui.checkbox("Train", s.training)
    imgui.set_item_tooltip("train the field in the background (off: pause it and give the CPU to the view)")
    if changed:
        app.set_training(s.training)
    st = s.last_status
    if st:
        imgui.text(status_line(st))
    h = s.history
    if h.steps and implot.begin_plot("##training", imgui.ImVec2(-1, 140)):
        implot.setup_axes("step", "PSNR (dB) / loss", implot.AxisFlags_.auto_fit.value,
                          implot.AxisFlags_.auto_fit.value)
        xs = np.asarray(h.steps, dtype=np.float64)
        implot.plot_line("PSNR", xs, np.asarray(h.psnr, dtype=np.float64))
        implot.plot_line("loss x100", xs, np.asarray(h.loss, dtype=np.float64) * 100.0)
        implot.end_plot()
    save = imgui.button("Save project")
    imgui.set_item_tooltip("save the workspace (field, selection, versions) so that Open resumes it")
    if save:
        app.call(app.engine.save)
    _, s.export_path = imgui.input_text("PNG", s.export_path)
    imgui.set_item_tooltip("the PNG file Export view writes")
    imgui.same_line()
    png = imgui.button("Export view")
    imgui.set_item_tooltip("save the current view, at the view's size, as the PNG above")
    if png:
        app.export_png(s.export_path)
    _, s.video_path = imgui.input_text("Video", s.video_path)
    imgui.set_item_tooltip("the .mp4 (or .gif) file Turntable writes")
    imgui.same_line()
    turn = imgui.button("Turntable")
    imgui.set_item_tooltip("a video orbiting the scene once around the current target")
    if turn:
        app.export_turntable(s.video_path)


def _repair_offer(app) -> None:
    """The offer shown when a workspace failed to open as damaged: repair it (core.workspace.repair) and reopen."""
    imgui.text_colored(imgui.ImVec4(1.0, 0.55, 0.3, 1.0), "This workspace is damaged.")
    imgui.text_wrapped("Repair sets damaged files aside in its damaged/ folder (nothing is deleted), rebuilds "
                       "its index and settings, and keeps every good version.")
    repair = imgui.button("Repair workspace")
    remember_item(app, "Repair workspace")
    imgui.set_item_tooltip("set damaged files aside, rebuild the index and settings, keep every good version, reopen")
    if repair:
        app.repair_workspace()
    imgui.same_line()
    later = imgui.button("Not now")
    imgui.set_item_tooltip("leave the workspace as it is (repair it later with: repaint-nerf repair WS)")
    if later:
        app.state.repair_offer = None
