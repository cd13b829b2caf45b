"""Repaint panel: prompts, guidance backend and model paths, settings, Repaint, progress, undo/redo."""
from __future__ import annotations

import dataclasses
from typing import Any

from imgui_bundle import imgui

from repaint_nerf.app.panels.common import remember_item, unavailable
from repaint_nerf.app.state import EditorState
from repaint_nerf.core.repaint import registry
from repaint_nerf.core.repaint.estimate import format_duration


def repaint_request(s: EditorState) -> dict[str, Any]:
    """Engine.repaint's arguments from the panel's fields: prompts, guidance, a copy of the RepaintConfig the
    fields edit (its defaults are the CLI's), the selection threshold and the model folders."""
    return {"prompt": s.prompt, "bg_prompt": s.bg_prompt, "guidance": s.backend,
            "config": dataclasses.replace(s.repaint_config), "threshold": float(s.threshold),
            "sd_path": s.sd_path or None, "clip_path": s.clip_path or None}


def _model_status(app, kind: str, flag: str) -> str | None:
    """None when the model is found, else the resolver's message (cached per input)."""
    key = (kind, flag)
    cache = app.cache.setdefault("model_status", {})
    if key not in cache:
        try:
            from repaint_nerf.core.models.paths import resolve_model_path

            resolve_model_path(kind, flag or None, settings=app.state.scene_info.get("settings"))
            cache[key] = None
        except Exception as exc:  # ModelNotFoundError, or the resolver not built
            cache[key] = str(exc)
    return cache[key]


def _estimate(app) -> str:
    """The expected repaint time for the chosen guidance, steps and scene on the engine's device (cached)."""
    s = app.state
    cams = s.scene_info.get("cameras")
    cfg = s.repaint_config
    key = (s.backend, int(cfg.steps), cfg.resolution, cfg.sd_unet_precision, cfg.sd_tiny_autoencoder,
           cfg.sds_resolution, cfg.sd_token_merging, s.scene_info.get("device"), cams is not None)
    cache = app.cache.setdefault("repaint_estimate", {})
    if key not in cache:
        try:
            from repaint_nerf.core.device import get_device
            from repaint_nerf.core.repaint.estimate import estimate_before_start

            w, h = (int(cams.width[0]), int(cams.height[0])) if cams is not None else (128, 128)
            cache[key] = estimate_before_start(s.backend, max(1, int(cfg.steps)), w, h,
                                               s.scene_info.get("device") or get_device(), cfg.resolution,
                                               unet_precision=cfg.sd_unet_precision,
                                               tiny_autoencoder=bool(cfg.sd_tiny_autoencoder),
                                               sds_resolution=cfg.sds_resolution,
                                               token_merging=cfg.sd_token_merging).describe()
        except Exception as exc:  # a bad field value must not break the panel
            cache[key] = f"estimated time: unknown ({exc})"
    return cache[key]


def draw(app) -> None:
    s = app.state
    opened = imgui.collapsing_header("Repaint", imgui.TreeNodeFlags_.default_open.value)
    imgui.set_item_tooltip("regenerate the selection from a prompt; the rest of the scene is held to the photos")
    if not opened:
        return
    _, s.prompt = imgui.input_text("Prompt", s.prompt)
    remember_item(app, "prompt")
    imgui.set_item_tooltip("what the selection should become, e.g. 'a blue rose' (offline guidance reads a "
                           "colour, or 'remove')")
    _, s.bg_prompt = imgui.input_text("Background prompt", s.bg_prompt)
    remember_item(app, "bg_prompt")
    imgui.set_item_tooltip("what surrounds it, e.g. 'leaves' (Stable Diffusion's CLIP background loss)")
    if not imgui.begin_combo("Guidance", s.backend):
        spec = registry.GUIDANCES.get(s.backend)
        imgui.set_item_tooltip(f"what edits the selection: {spec.help}" if spec else "what edits the selection")
    else:
        for spec in registry.GUIDANCES.values():
            if spec.needs_edited and not s.scene_info.get("has_edited"):
                continue
            if imgui.selectable(spec.name, s.backend == spec.name)[0]:
                s.backend = spec.name
            if imgui.is_item_hovered():
                imgui.set_tooltip(spec.help)
        imgui.end_combo()
    cfg = s.repaint_config
    changed, weight = imgui.input_float("CLIP weight", registry.clip_weight(s.backend, cfg), format="%.4g")
    if changed:  # until edited, the guidance's default (paper Eq. clip; 0.01 with Stable Diffusion)
        cfg.lambda_clip = max(0.0, weight)
    imgui.set_item_tooltip("weight of the CLIP loss that pulls the rest toward the background prompt (0: no CLIP)")
    for kind in registry.models_needed(s.backend, cfg):
        attr = f"{kind}_path"
        _, val = imgui.input_text(f"{kind.upper()} model folder", getattr(s, attr))
        imgui.set_item_tooltip(f"a local {kind.upper()} model (folder, file or cached model id); README: "
                               "Where models go")
        setattr(s, attr, val)
        msg = _model_status(app, kind, val)
        if msg is None:
            imgui.text_colored(imgui.ImVec4(0.4, 1.0, 0.4, 1.0), f"{kind}: found")
        else:
            imgui.text_colored(imgui.ImVec4(1.0, 0.5, 0.4, 1.0), f"{kind}: missing")
            if imgui.is_item_hovered():
                imgui.set_tooltip(msg)
    _, cfg.lambda_unmask = imgui.input_float("lambda_unmask", cfg.lambda_unmask)
    imgui.set_item_tooltip("how hard the unselected pixels are held to the original photos (paper Eq. unmask)")
    _, cfg.steps = imgui.input_int("Steps", cfg.steps)
    imgui.set_item_tooltip("edit steps; more is slower and closer to the prompt (the estimate below follows)")
    if unavailable(app, "repaint"):
        return
    if not s.repaint_running:
        imgui.text_wrapped(_estimate(app))
        if imgui.button("Repaint##start"):  # the header is also "Repaint": a distinct id
            app.start_repaint()
        remember_item(app, "repaint")
        imgui.set_item_tooltip("edit the selection toward the prompt; the view previews it, and the result is "
                               "a new version (Undo returns to the one before)")
    else:
        st = s.last_status
        done = float(st.get("step", 0)) / max(1, st.get("steps", cfg.steps)) if st.get("phase") == "repaint" else 0.0
        imgui.progress_bar(min(done, 1.0), imgui.ImVec2(-1, 0))
        imgui.text(f"step {st.get('step', 0)}/{st.get('steps', cfg.steps)}, {format_duration(st.get('eta_s'))} left")
        if imgui.button("Resume" if not s.training else "Pause"):
            app.set_training(not s.training)
        imgui.set_item_tooltip("pause the edit (the view stays live) or resume it")
        imgui.same_line()
        if imgui.button("Cancel"):
            app.call(app.engine.cancel)
            s.repaint_running = False
        imgui.set_item_tooltip("stop the edit and keep the version from before it")
    if imgui.button("Undo"):
        app.call(app.engine.undo)
    remember_item(app, "undo")
    imgui.set_item_tooltip("back to the previous version of the scene (compare before and after)")
    imgui.same_line()
    if imgui.button("Redo"):
        app.call(app.engine.redo)
    remember_item(app, "redo")
    imgui.set_item_tooltip("forward to the next version again")
