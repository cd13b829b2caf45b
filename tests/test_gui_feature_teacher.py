"""The editor's "Feature teacher" choice (the Scene panel) in a real window under Xvfb, on the real engine: a new
workspace distils the default blend (the lite extra is installed); picking the built-in teacher and pressing "Demo
scene" trains the workspace with it, saves it in settings.json (as `train --feature-model` does) and says that the
teacher changed. The demo scene is swapped for a
small one of the same preset, so the test takes seconds on one core."""
from __future__ import annotations

import json

import pytest
import torch

from test_gui_editor import click, frames, run_until

pytestmark = pytest.mark.gui


@pytest.mark.timeout(120)
def test_the_chosen_teacher_trains_the_demo_workspace(xvfb_display, scene_factory, tmp_path, monkeypatch,
                                                      artifacts_dir):
    import cv2

    import repaint_nerf.core.engine as engine_module
    from repaint_nerf.app.editor import EditorApp
    from repaint_nerf.app.window import Window
    from repaint_nerf.core.engine import Engine
    from repaint_nerf.core.teachers.stage1_targets import DEFAULT_FEATURE, LITE_BLEND

    torch.set_num_threads(1)
    monkeypatch.delenv("REPAINT_NERF_FEATURE_MODEL", raising=False)
    monkeypatch.delenv("REPAINT_NERF_MODELS", raising=False)
    small = scene_factory("demo", size=24, views=6, test_views=1)
    monkeypatch.setattr(engine_module, "demo_scene_path", lambda: small)
    ws = tmp_path / "ws"
    window = Window(width=1000, height=960)
    app = EditorApp(window, Engine("cpu"), None, str(ws),  # opens the demo scene with the untouched choice
                    worker_kwargs={"train_budget_s": 0.05, "rest_s": 0.05, "preview_interval_s": 0.5})

    def loads() -> int:
        return sum(e[1] == "reply:load" for e in app.events)

    try:
        run_until(app, lambda: app.state.scene_info.get("loaded"), timeout=60)
        # the default teacher where the lite extra is installed (CI installs it)
        assert json.loads((ws / "settings.json").read_text())["feature_model"]["path"] == LITE_BLEND
        click(app, "Feature teacher")
        cv2.imwrite(str(artifacts_dir / "gui_feature_teacher_choices.png"), frames(app, 1)[..., ::-1])
        click(app, f"feature:{DEFAULT_FEATURE}")
        assert app.state.feature_model == DEFAULT_FEATURE
        click(app, "Demo scene")
        run_until(app, lambda: loads() == 2 and not app.state.loading, timeout=60)
        trained = len(app.state.history.steps)
        run_until(app, lambda: len(app.state.history.steps) > trained, timeout=30)  # training has started
        cv2.imwrite(str(artifacts_dir / "gui_feature_teacher.png"), frames(app, 2)[..., ::-1])
        assert not [t for kind, t in app.state.messages if kind == "error"], app.state.messages
        saved = json.loads((ws / "settings.json").read_text())
        assert saved["feature_model"] is None and saved["teacher"] == DEFAULT_FEATURE  # the built-in teacher
        said = [t for _, t in app.state.messages]
        assert any(t.startswith(f"feature teacher changed to {DEFAULT_FEATURE}") for t in said), said
    finally:
        app.close()
        window.close()
