"""A first edit as a new user meets it: the real engine on a tiny demo scene in a real window under Xvfb, driven
only through the hint line's steps with injected mouse and keys (orbit, the patch tool, a patch, the threshold
slider, a typed prompt, Repaint with the offline guidance, Undo, Export mesh). Each step's hint must give way
to the next once it is done, and the hints stay gone for the same user. Screenshots: tests/artifacts/first_*.png.
"""
from __future__ import annotations

import os

import cv2
import pytest

from real_editor import pretrain, real_editor
from test_gui_editor import click, drag, frames, full_frame, run_until

pytestmark = [pytest.mark.gui, pytest.mark.timeout(600)]
os.environ.setdefault("REPAINT_NERF_COMPILE", "0")  # eager hash grid: no compile wait on a small CPU
PRETRAIN_STEPS = 100


@pytest.fixture()
def editor(xvfb_display, scene_factory, tmp_path, monkeypatch):
    from repaint_nerf.app.user_settings import ENV

    monkeypatch.setenv(ENV, str(tmp_path / "config"))  # a user who has never opened the editor
    path, ws = str(scene_factory("demo", size=32, views=8, test_views=2)), str(tmp_path / "ws")
    pretrain(path, ws, PRETRAIN_STEPS)  # so that a patch selects an object, not fog
    with real_editor(path, ws, 900, 900, train_budget_s=0.2) as app:
        yield app


def _shot(app, artifacts_dir, name: str) -> None:
    cv2.imwrite(str(artifacts_dir / f"first_{name}.png"), frames(app, 2)[..., ::-1])


def _expect_step(app, key: str) -> None:
    from repaint_nerf.app.guide import STEPS

    step = app.guide.next_step()
    assert step is not None and step.key == key, (key, step, app.state.messages)
    assert app.guide.hint().endswith(step.hint)


def _type(app, text: str) -> None:
    from imgui_bundle import imgui

    frames(app, 1, lambda io: io.add_input_characters_utf8(text))
    frames(app, 1, lambda io: io.add_key_event(imgui.Key.enter, True))
    frames(app, 2, lambda io: io.add_key_event(imgui.Key.enter, False))


@pytest.mark.slow  # a short headless reconstruction first
def test_the_first_edit_follows_the_hints(editor, artifacts_dir, tmp_path):
    app, s = editor, editor.state
    run_until(app, lambda: s.scene_info.get("loaded") and full_frame(app), timeout=180)
    ox, oy = app.image_origin
    w, h = app.view_size
    cx, cy = ox + w / 2, oy + h / 2

    _expect_step(app, "orbit")
    _shot(app, artifacts_dir, "1_orbit_hint")
    drag(app, (cx, cy), (cx + 60, cy))

    _expect_step(app, "select")
    click(app, "select_tool")
    assert s.tool == "select"
    run_until(app, lambda: full_frame(app), timeout=60)  # the view's features, for the patch
    drag(app, (cx - 5, cy - 5), (cx + 5, cy + 5))
    run_until(app, lambda: s.has_selection, timeout=120)
    _shot(app, artifacts_dir, "2_selected")

    _expect_step(app, "threshold")
    x0, y0, x1, y1 = app.cache["items"]["threshold"]
    before = s.threshold
    drag(app, ((x0 + x1) / 2, (y0 + y1) / 2), (x0 + 0.3 * (x1 - x0), (y0 + y1) / 2))  # lower: more
    assert s.threshold != before, "the slider moved"

    _expect_step(app, "repaint")
    click(app, "prompt")
    _type(app, "make it blue")
    assert s.prompt == "make it blue" and s.backend == "offline"
    s.repaint_config.steps = 8
    click(app, "repaint")
    run_until(app, lambda: s.repaint_running, timeout=120)

    _expect_step(app, "compare")
    run_until(app, lambda: not s.repaint_running, timeout=300)
    run_until(app, lambda: full_frame(app), timeout=60)
    _shot(app, artifacts_dir, "3_repainted")
    app.set_training(False)
    n = len(app.events)
    click(app, "undo")
    run_until(app, lambda: any(e[1] == "reply:undo" for e in app.events[n:]), timeout=60)
    click(app, "redo")

    _expect_step(app, "export")
    s.mesh_path, s.mesh_resolution = str(tmp_path / "mesh.glb"), 64
    click(app, "export_section")
    click(app, "export_mesh")
    run_until(app, lambda: s.export_job is None and (tmp_path / "mesh.glb").is_file(), timeout=300)
    frames(app, 2)
    assert app.guide.hint() is None, "every step is done: no hint line"
    _shot(app, artifacts_dir, "4_done")

    from repaint_nerf.app.guide import Guide
    from repaint_nerf.app.user_settings import UserSettings

    assert Guide(UserSettings()).hint() is None, "the next session of the same user shows no hint"


@pytest.fixture()
def analytic_editor(xvfb_display, tmp_path, monkeypatch):
    """The editor on test_gui_editor's analytic engine (no training wait): for what needs no real field."""
    from test_gui_editor import AnalyticEngine

    from repaint_nerf.app.editor import EditorApp
    from repaint_nerf.app.user_settings import ENV
    from repaint_nerf.app.window import Window

    monkeypatch.setenv(ENV, str(tmp_path / "config"))
    window = Window(width=900, height=700)
    app = EditorApp(window, AnalyticEngine(), None, worker_kwargs={"train_budget_s": 0.02, "rest_s": 0.05})
    yield app
    app.close()
    window.close()


def test_the_help_menu_lists_the_bindings_and_brings_the_hints_back(analytic_editor, artifacts_dir):
    app = analytic_editor
    run_until(app, lambda: full_frame(app))
    for key in ("orbit", "select"):
        app.guide.done(key)
    frames(app, 2)
    click(app, "help_menu")
    _shot(app, artifacts_dir, "5_help_menu")
    assert app.cache["items"].get("help_reset"), "the menu is open"
    click(app, "help_reset")
    frames(app, 2)
    assert app.guide.next_step().key == "orbit"
