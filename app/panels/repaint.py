"""Repaint panel: prompts, guidance backend and model paths, settings, Repaint, progress, undo/redo."""
from __future__ import annotations

from imgui_bundle import imgui

from app.panels.common import remember_item, unavailable

BACKENDS = ("offline", "recolor", "remove", "analytic", "sd")
BACKEND_HELP = {"offline": "recolor or remove, read from the prompt (no model)", "recolor": "recolour to a colour named "
                "in the prompt", "remove": "remove the object and fill in behind it",
                "analytic": "the synthetic scene's edited/ variant (measurement)",
                "sd": "Stable Diffusion score distillation (local model folder)"}


def _model_status(app, kind: str, flag: str) -> str | None:
    """None when the model is found, else the resolver's message (cached per input)."""
    key = (kind, flag)
    cache = app.cache.setdefault("model_status", {})
    if key not in cache:
        try:
            from core.models.paths import resolve_model_path

            resolve_model_path(kind, flag or None, settings=app.state.scene_info.get("settings"))
            cache[key] = None
        except Exception as exc:  # ModelNotFoundError, or the resolver not built
            cache[key] = str(exc)
    return cache[key]


def draw(app) -> None:
    s = app.state
    if not imgui.collapsing_header("Repaint", imgui.TreeNodeFlags_.default_open.value):
        return
    _, s.prompt = imgui.input_text("Prompt", s.prompt)
    remember_item(app, "prompt")
    _, s.bg_prompt = imgui.input_text("Background prompt", s.bg_prompt)
    if imgui.begin_combo("Guidance", s.backend):
        for b in BACKENDS:
            if b == "analytic" and not s.scene_info.get("has_edited"):
                continue
            if imgui.selectable(b, s.backend == b)[0]:
                s.backend = b
            if imgui.is_item_hovered():
                imgui.set_tooltip(BACKEND_HELP[b])
        imgui.end_combo()
    if s.backend == "sd":
        for kind, attr in (("sd", "sd_path"), ("clip", "clip_path")):
            _, val = imgui.input_text(f"{kind.upper()} model folder", getattr(s, attr))
            setattr(s, attr, val)
            msg = _model_status(app, kind, val)
            if msg is None:
                imgui.text_colored(imgui.ImVec4(0.4, 1.0, 0.4, 1.0), f"{kind}: found")
            else:
                imgui.text_colored(imgui.ImVec4(1.0, 0.5, 0.4, 1.0), f"{kind}: missing")
                if imgui.is_item_hovered():
                    imgui.set_tooltip(msg)
    _, s.lambda_unmask = imgui.input_float("lambda_unmask", s.lambda_unmask)
    _, s.steps = imgui.input_int("Steps", s.steps)
    if unavailable(app, "repaint"):
        return
    if not s.repaint_running:
        if imgui.button("Repaint##start"):  # the header is also "Repaint": a distinct id
            app.start_repaint()
        remember_item(app, "repaint")
    else:
        st = s.last_status
        done = float(st.get("step", 0)) / max(1, st.get("steps", s.steps)) if st.get("phase") == "repaint" else 0.0
        imgui.progress_bar(min(done, 1.0), imgui.ImVec2(-1, 0))
        if imgui.button("Resume" if not s.training else "Pause"):
            app.set_training(not s.training)
        imgui.same_line()
        if imgui.button("Cancel"):
            app.call(app.engine.cancel)
            s.repaint_running = False
    if imgui.button("Undo"):
        app.call(app.engine.undo)
    remember_item(app, "undo")
    imgui.same_line()
    if imgui.button("Redo"):
        app.call(app.engine.redo)
