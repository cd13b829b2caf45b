"""The engine facade on a tiny generated scene: load, train, render (progressive scale, cancel), save, export,
and clear messages for missing input, a field without a feature head, and a missing optional package."""
from __future__ import annotations

import time

import numpy as np
import pytest

from repaint_nerf.core.engine import Engine, FeatureUnavailable
from repaint_nerf.core.errors import UserError


@pytest.fixture(scope="module")
def engine(scene_factory, tmp_path_factory):
    path = scene_factory("demo", size=24, views=6, test_views=2)
    eng = Engine("cpu")
    info = eng.load(path, workspace=tmp_path_factory.mktemp("ws"))
    assert info["loaded"] and info["views"] == 6
    return eng


def test_train_then_render_at_scale(engine):
    first = engine.train_for(0.2)
    assert first["phase"] == "reconstruct" and first["step"] >= 1
    cams = engine.info()["cameras"][0]
    full = engine.render(cams, scale=1.0, outputs=("rgb", "depth"))
    assert full["rgb"].shape == (24, 24, 3) and full["depth"].shape == (24, 24)
    assert np.isfinite(full["rgb"]).all()
    half = engine.render(cams, scale=0.5, outputs=("rgb",))
    assert half["rgb"].shape == (12, 12, 3)


def test_drawn_views_stop_rays_within_half_an_8_bit_level(engine, monkeypatch):
    """Engine.render (the viewport and the PNG and video exports) stops a ray once its transmittance falls below
    DISPLAY_T_THRESHOLD, under half an 8-bit level: its colour moves by at most that much from a ray marched to
    its end."""
    import torch

    from repaint_nerf.core import engine as engine_mod
    from repaint_nerf.core.render.renderer import RenderOptions, render_camera

    assert engine_mod.DISPLAY_T_THRESHOLD < 0.5 / 255
    seen = []

    def spy(field, grid, cameras, i, opts, **kw):
        seen.append(opts.t_threshold)
        return render_camera(field, grid, cameras, i, opts, **kw)

    monkeypatch.setattr(engine_mod, "render_camera", spy)
    engine.train_for(0.5)
    cams = engine.info()["cameras"][0]
    drawn = engine.render(cams, outputs=("rgb",))["rgb"]
    assert seen == [engine_mod.DISPLAY_T_THRESHOLD]
    opts = RenderOptions(outputs=("rgb",), background=engine.trainer.eval_background(),
                         max_samples=int(engine.trainer.cfg.max_samples), t_threshold=0.0)
    with torch.no_grad():
        full = render_camera(engine.field.eval(), engine.grid, cams.to(engine.device), 0, opts)["rgb"].numpy()
    engine.field.train()
    assert np.abs(drawn - full).max() <= engine_mod.DISPLAY_T_THRESHOLD + 1e-5


def test_cancel_returns_none(engine):
    cams = engine.info()["cameras"][0]
    assert engine.render(cams, cancel=lambda: True) is None


def test_pause_stops_training(engine):
    engine.pause()
    assert engine.train_for(0.05) is None
    engine.resume()
    assert engine.train_for(0.05) is not None


def test_training_yields_between_steps_when_asked(engine):
    start = engine.trainer.step_count
    info = engine.train_for(60.0, stop=lambda: engine.trainer.step_count >= start + 3)
    assert engine.trainer.step_count == start + 3 and info["phase"] == "reconstruct"  # not 60 s of steps
    assert engine.train_for(60.0, stop=lambda: True)["step"] == start + 4  # at least one step
    calls = []
    engine.train_for(60.0, stop=lambda: len(set(calls)) >= 2,
                     interlude=lambda: calls.append(engine.trainer.step_count))
    assert set(calls) == {start + 4, start + 5} and calls == sorted(calls)  # within each step, before it counts


def test_worker_yields_training_to_views_commands_and_gestures(engine):
    from repaint_nerf.app.worker import Worker

    worker = Worker(engine, nav_hold_s=0.3)
    stop = worker._interrupted()
    assert not stop()
    worker.request_render(engine.info()["cameras"][0], key=("moved",))
    assert stop()
    stop = worker._interrupted()
    assert not stop()
    worker.call(engine.info)
    assert stop()
    worker.commands.get_nowait()
    assert not worker._interrupted()()
    worker.hold(True)  # a patch drag: no training step starts, a running one yields
    assert worker._interrupted()() and worker._train() is False
    worker.hold(False)
    time.sleep(worker.rest_s)  # the requested view has come to rest, but the user may move again: no step yet
    assert worker._train() is False
    time.sleep(worker.nav_hold_s - worker.rest_s)  # no move for nav_hold_s: the user stopped navigating
    assert worker._train() is True


def test_a_cancellable_command_gives_way_to_the_users_next_action(engine):
    from repaint_nerf.app.worker import Worker

    worker = Worker(engine)  # not started: the test runs its command loop by hand
    seen = []

    def vote(own, cancel=None):
        seen.append(cancel())
        worker.request_render(engine.info()["cameras"][0], key=("moved",))  # the user orbits meanwhile
        seen.append(cancel())
        return own

    worker.call(vote, 0.4, tag=0.4, cancellable=True)
    worker._run_commands()
    reply = worker.poll()[-1]
    assert seen == [False, True] and reply.cancelled and reply.tag == 0.4
    for interrupt in (lambda: worker.call(engine.info), lambda: worker.hold(True)):  # a command, a patch gesture
        flags = []
        worker.commands.put((lambda cancel=None: flags.append(cancel()) or interrupt() or flags.append(cancel()),
                             (), {}, None, True))
        worker._run_commands()
        assert flags == [False, True]
        worker.hold(False)
    worker.poll()
    worker.call(engine.info)  # a plain command gets no cancel and is never marked
    worker._run_commands()
    assert not worker.poll()[-1].cancelled


def test_save_and_export(engine, tmp_path):
    root = engine.save()
    assert engine.workspace.original_version is not None and root
    png = engine.export_png(engine.info()["cameras"][0], tmp_path / "view.png")
    import cv2

    img = cv2.imread(png)
    assert img.shape == (24, 24, 3)
    with pytest.raises(UserError):
        engine.export_png(engine.info()["cameras"][0], tmp_path / "missing_dir" / "view.png")


def test_user_errors():
    eng = Engine("cpu")
    with pytest.raises(UserError, match="no scene is loaded"):
        eng.render(None)
    with pytest.raises(UserError, match="no such dataset"):
        eng.load("/nonexistent/scene")
    caps = Engine.capabilities()
    assert set(caps) == {"sd"}  # the one optional feature (the diffusion extra); all else is always built
    assert caps["sd"] is None or "pip install" in caps["sd"]


def test_missing_optional_package_is_reported(engine, monkeypatch):
    """Without diffusers, the sd guidance is reported as unavailable (in the panels and on use), not a crash."""
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "diffusers" else real(name, *a))
    reason = Engine.capabilities()["sd"]
    assert "diffusers" in reason and "not available" in reason
    with pytest.raises(FeatureUnavailable, match="diffusers"):
        engine.repaint("a blue ball", guidance="sd")


def test_selection_needs_a_feature_head(scene_factory, tmp_path):
    eng = Engine("cpu", features=False, depth=False)
    eng.load(scene_factory("demo", size=24, views=6, test_views=2), workspace=tmp_path / "ws")
    assert not eng.has_feature_head()
    with pytest.raises(UserError, match="without a feature head"):
        eng.select(eng.info()["cameras"][0], (0.4, 0.4, 0.6, 0.6))


def test_a_patch_selects_from_features_no_coarser_than_its_threshold_reads(engine, monkeypatch):
    """A patch on a view whose newest feature render is coarse (the first frame after switching to the patch tool)
    selects from a finer render, so its threshold does not depend on how soon the user dragged; a fine enough render
    of the view is reused without rendering again, unless it marched a longer step."""
    engine.train_for(0.2)
    cams = engine.info()["cameras"][0]  # 24 px: under EVAL_SIDE, the view's own size is fine enough
    coarse = engine.render(cams, scale=0.25, outputs=("rgb", "feature"))
    assert coarse["feature"].shape[:2] == (6, 6)
    sel = engine.select(cams, (0.4, 0.4, 0.6, 0.6))
    assert sel.similarity.shape == (24, 24)
    engine.render(cams, scale=1.0, outputs=("rgb", "feature"))
    calls = []
    real = engine.render
    monkeypatch.setattr(engine, "render", lambda *a, **k: calls.append(k) or real(*a, **k))
    assert engine.select(cams, (0.4, 0.4, 0.6, 0.6)).similarity.shape == (24, 24)
    assert calls == [], "the view's fine feature render is reused"
    real(cams, scale=1.0, outputs=("rgb", "feature"), stride=2.0)  # full size, but at a longer step
    engine.select(cams, (0.4, 0.4, 0.6, 0.6))
    assert len(calls) == 1 and calls[0].get("stride", 1.0) == 1.0, "a longer step's render is not read"
