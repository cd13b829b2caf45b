"""The editor in a real window under Xvfb, driven by injected imgui input.

The engine here is a test double with an analytic scene (a red sphere in front of a blue background,
with one feature vector each), so the UI, worker protocol, viewport shaders and input are checked
against known answers without the learned backends; the real engine is exercised in test_engine.py.
"""
from __future__ import annotations

import inspect
import time

import numpy as np
import pytest
import torch

from repaint_nerf.core.engine import PatchSelected
from repaint_nerf.core.scene.cameras import Cameras, look_at
from repaint_nerf.core.select.autothreshold import patch_auto_threshold

pytestmark = pytest.mark.gui

SPHERE_R = 0.5
RED, BLUE, GREEN = np.array([0.9, 0.1, 0.1]), np.array([0.1, 0.2, 0.8]), np.array([0.1, 0.9, 0.1])


class AnalyticEngine:
    """Engine double: ray-traces a sphere; features are one-hot (sphere / background); edits recolour the sphere."""

    def __init__(self, fail_render_after: int | None = None):
        self.step = 0
        self.query: np.ndarray | None = None
        self.versions = [RED]
        self.current = 0
        self.edit_steps = 0
        self.edit_target = None
        self.fail_render_after = fail_render_after
        self.renders = 0
        self.render_delay = 0.0
        self.text_calls: list = []
        self.mask_calls: list = []
        self.repaint_calls: list[dict] = []
        self.refine_calls: list = []
        self.refine_to: float | None = None  # what refine_threshold answers (None: the patch's own threshold)
        self.refine_s = 0.0  # how long the vote takes, in 10 ms slices that give way to `cancel`

    def capabilities(self):
        return {"load": None, "train": None, "select": None, "repaint": None}

    def load(self, path, workspace=None, feature_model=None):
        poses = [look_at([3 * np.cos(a), 3 * np.sin(a), 1.0], [0, 0, 0]) for a in np.linspace(0, 6, 8)]
        cams = Cameras.create(np.stack(poses), 60.0, 60.0, 40.0, 40.0, 80, 80)
        from repaint_nerf.core.train.history import TrainingHistory

        self.step = 3  # a reopened workspace: three steps trained before, their curve saved with it
        past = TrainingHistory([1.0, 2.0, 3.0], [1.0, 0.5, 0.33], [10.0, 10.7, 11.1])
        return {"loaded": True, "name": "analytic", "format": "test", "views": 8, "cameras": cams, "history": past}

    def can_train(self):
        return True

    def train_for(self, seconds, stop=None, interlude=None):
        time.sleep(min(seconds, 0.02))
        self.step += 1
        info = {"step": self.step, "loss": 1.0 / self.step, "psnr": 10 + np.log(self.step)}
        if self.edit_target is not None:
            self.edit_steps += 1
            info["phase"] = "repaint"
            if self.edit_steps >= 3:
                self.versions = self.versions[: self.current + 1] + [self.edit_target]
                self.current += 1
                self.edit_target = None
                info["done"] = True
        return info

    def _color(self):
        if self.edit_target is not None:
            return 0.5 * (self.versions[self.current] + self.edit_target)
        return self.versions[self.current]

    def render(self, cameras, scale=1.0, outputs=("rgb",), cancel=None, stride=1.0):
        self.renders += 1
        time.sleep(self.render_delay)
        if self.fail_render_after is not None and self.renders > self.fail_render_after:
            raise RuntimeError("simulated renderer failure")
        cams = cameras.scaled(scale)
        h, w = int(cams.height[0]), int(cams.width[0])
        o, d, dz = cams.image_rays(0)
        b = (o * d).sum(-1)
        c = (o * o).sum(-1) - SPHERE_R ** 2
        disc = b * b - c
        hit = (disc > 0).numpy().reshape(h, w)
        t = (-b - torch.sqrt(disc.clamp_min(0))).numpy().reshape(h, w)
        rgb = np.where(hit[..., None], self._color(), BLUE).astype(np.float32)
        feat = np.where(hit[..., None], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]).astype(np.float32)
        out = {"rgb": rgb, "depth": np.where(hit, t * dz.numpy().reshape(h, w), 0).astype(np.float32),
               "feature": feat}
        if self.query is not None:
            out["similarity"] = self._sim(feat)
        return out

    def _sim(self, feat):
        q = self.query / (np.linalg.norm(self.query) + 1e-8)
        return (feat @ q / (np.linalg.norm(feat, axis=-1) + 1e-8)).astype(np.float32)

    def select(self, cameras, patch, mode="new"):
        feat = self.render(cameras)["feature"]
        h, w = feat.shape[:2]
        x0, y0, x1, y1 = patch
        mean = feat[int(y0 * h):max(int(y1 * h), int(y0 * h) + 1), int(x0 * w):max(int(x1 * w), int(x0 * w) + 1)]
        mean = mean.reshape(-1, feat.shape[-1]).mean(0)
        self.query = mean if mode == "new" or self.query is None else self.query + (mean if mode == "add" else -mean)
        sim = self._sim(feat)
        return PatchSelected(sim, None if mode == "sub" else patch_auto_threshold(sim, patch))

    def refine_threshold(self, own, cancel=None):
        self.refine_calls.append(own)
        end = time.perf_counter() + self.refine_s
        while time.perf_counter() < end:
            if cancel is not None and cancel():
                return None
            time.sleep(0.01)
        return own if self.refine_to is None else self.refine_to

    def select_text(self, cameras, text, mode="new", clip_path=None):
        self.text_calls.append((text, mode, clip_path))
        q = np.array([1.0, 0.0, 0.0] if "sphere" in text else [0.0, 1.0, 0.0])
        self.query = q if mode == "new" or self.query is None else self.query + q
        return self._sim(self.render(cameras)["feature"])

    def clear_selection(self):
        self.query = None

    def masks_for_all_views(self, *args, **kwargs):
        from repaint_nerf.core.engine import Engine

        call = inspect.signature(Engine.masks_for_all_views).bind(self, *args, **kwargs)  # the real signature
        call.apply_defaults()
        self.mask_calls.append((call.arguments["threshold"], call.arguments["geometry"]))
        return 8

    def repaint(self, *args, **kwargs):
        from repaint_nerf.core.engine import Engine

        call = inspect.signature(Engine.repaint).bind(self, *args, **kwargs)  # the real engine's signature
        call.apply_defaults()
        self.repaint_calls.append(call.arguments)
        self.edit_target = GREEN
        self.edit_steps = 0
        return {}

    def cancel(self):
        self.edit_target = None

    def undo(self):
        if self.current == 0:
            return False
        self.current -= 1
        return True

    def redo(self):
        if self.current + 1 >= len(self.versions):
            return False
        self.current += 1
        return True

    def save(self):
        return "/tmp/ws"


@pytest.fixture(scope="module")
def editor(xvfb_display):
    from repaint_nerf.app.editor import EditorApp
    from repaint_nerf.app.window import Window

    window = Window(width=1000, height=960)  # tall enough that every panel is on screen
    engine = AnalyticEngine()
    app = EditorApp(window, engine, None, worker_kwargs={"train_budget_s": 0.02, "rest_s": 0.05,
                                                          "preview_interval_s": 0.05})
    yield app
    app.close()
    window.close()


def run_until(app, pred, timeout=20.0, inject=None):
    """Run frames until pred() holds; returns the last screenshot."""
    t0 = time.perf_counter()
    while True:
        if inject is not None:
            app.window.inject(inject)
        shot = app.frame(capture=True)
        if pred():
            return shot
        assert time.perf_counter() - t0 < timeout, \
            f"timed out waiting for the editor: {app.state.messages} {app.state.error} {app.worker.alive()} " \
            f"{app.worker.commands.qsize()} {[e[1] for e in app.events[-8:]]}"


def frames(app, n, inject=None):
    shot = None
    for _ in range(n):
        if inject is not None:
            app.window.inject(inject)
        shot = app.frame(capture=True)
    return shot


def view_pixels(app, shot):
    """The viewport region of a screenshot."""
    x, y = (int(round(v)) for v in app.image_origin)
    w, h = app.view_size
    return shot[y:y + h, x:x + w].astype(np.int32)


def mouse(x, y, button=None, down=None, shift=False, ctrl=False):
    from repaint_nerf.app.window import mouse_event

    return mouse_event(x, y, button, down, shift, ctrl)


def drag(app, p0, p1, steps=6, **mods):
    frames(app, 2, mouse(*p0, **mods))
    frames(app, 1, mouse(*p0, button=0, down=True, **mods))
    for i in range(1, steps + 1):
        a = i / steps
        frames(app, 1, mouse(p0[0] + a * (p1[0] - p0[0]), p0[1] + a * (p1[1] - p0[1]), **mods))
    frames(app, 1, mouse(*p1, button=0, down=False, **mods))
    frames(app, 1, mouse(*p1, **mods))


def full_frame(app):
    """The newest request is on screen at full resolution (an older frame of an equal view does not count)."""
    f = app.last_frame
    return f is not None and f.final and f.key == app.requested_key and f.serial == app.worker._serial


def redness(px):
    return (px[..., 0] > 150) & (px[..., 2] < 100)


def test_open_renders_the_scene(editor, artifacts_dir):
    shot = run_until(editor, lambda: full_frame(editor))
    shot = frames(editor, 2)
    import cv2

    cv2.imwrite(str(artifacts_dir / "gui_01_open.png"), shot[..., ::-1])
    px = view_pixels(editor, shot)
    # The sphere is red at the centre of the view, the background blue at the corner.
    h, w = px.shape[:2]
    assert redness(px[h // 2 - 2:h // 2 + 2, w // 2 - 2:w // 2 + 2]).all()
    assert px[5, 5, 2] > 150 and px[5, 5, 0] < 60
    assert editor.state.history.steps[:3] == [1.0, 2.0, 3.0], "the reopened workspace's curve is plotted"
    assert len(editor.state.history.steps) > 3, "training status reached the UI"


def test_orbit_changes_the_image(editor, artifacts_dir):
    before = view_pixels(editor, frames(editor, 1))
    yaw0 = editor.camera.yaw
    ox, oy = editor.image_origin
    w, h = editor.view_size
    drag(editor, (ox + w * 0.5, oy + h * 0.5), (ox + w * 0.8, oy + h * 0.5))
    assert editor.camera.yaw != yaw0
    shot = run_until(editor, lambda: full_frame(editor))
    after = view_pixels(editor, frames(editor, 1))
    import cv2

    cv2.imwrite(str(artifacts_dir / "gui_02_orbit.png"), shot[..., ::-1])
    # Rotating around a sphere centred at the target barely changes it; pan off-centre instead to be sure.
    editor.camera.pan(60, 0, h)
    run_until(editor, lambda: full_frame(editor))
    panned = view_pixels(editor, frames(editor, 1))
    assert np.abs(panned - after).mean() > 5
    editor.camera.reset()
    run_until(editor, lambda: full_frame(editor))
    assert np.abs(view_pixels(editor, frames(editor, 1)) - before).mean() < 2


def test_patch_selection_overlays_the_object_and_threshold_is_monotonic(editor, artifacts_dir):
    import cv2

    run_until(editor, lambda: full_frame(editor))  # the viewport has its size (also when run on its own)
    editor.state.tool = "select"
    ox, oy = editor.image_origin
    w, h = editor.view_size
    cx, cy = ox + w / 2, oy + h / 2
    editor.engine.refine_to = 0.37
    drag(editor, (cx - 5, cy - 5), (cx + 5, cy + 5))
    shot = run_until(editor, lambda: editor.state.has_selection)
    # then the training views vote on the patch's threshold, and the untouched slider follows
    run_until(editor, lambda: abs(editor.state.threshold - 0.37) < 1e-6)  # the slider holds a float32
    assert len(editor.engine.refine_calls) == 1 and editor.state.auto_threshold == 0.37
    # A slow vote gives way to a camera move, and votes again once the view rests.
    editor.engine.refine_to, editor.engine.refine_s = 0.41, 1.0
    drag(editor, (cx - 8, cy - 8), (cx + 8, cy + 8))
    run_until(editor, lambda: len(editor.engine.refine_calls) == 2)
    moved = time.perf_counter()
    editor.camera.orbit(5, 0)
    run_until(editor, lambda: any(w == "reply:refine_threshold" and t > moved and m.cancelled
                                  for t, w, m in editor.events))
    assert abs(editor.state.threshold - 0.41) > 1e-6  # the interrupted vote changed nothing
    run_until(editor, lambda: abs(editor.state.threshold - 0.41) < 1e-6)
    assert len(editor.engine.refine_calls) == 3
    editor.camera.orbit(-5, 0)
    editor.engine.refine_to, editor.engine.refine_s = None, 0.0
    shot = frames(editor, 1)
    assert editor.state.view_mode == "mask"
    cv2.imwrite(str(artifacts_dir / "gui_03_mask.png"), shot[..., ::-1])
    px = view_pixels(editor, shot)
    rgb_only = view_pixels(editor, _draw_mode(editor, "rgb"))
    tinted = np.abs(px - rgb_only).sum(-1) > 30
    sphere = redness(rgb_only)
    assert tinted[sphere].mean() > 0.9, "overlay covers the selected object"
    assert tinted[~sphere].mean() < 0.05, "and not the background"
    areas = []
    for thr in (0.99, 0.5, -0.5, -0.999):
        editor.state.threshold = thr
        shot = frames(editor, 1)  # one frame: the threshold is a uniform, no re-render
        areas.append(int((np.abs(view_pixels(editor, shot) - rgb_only).sum(-1) > 30).sum()))
    assert areas == sorted(areas) and areas[0] < areas[-1], areas
    editor.state.threshold = 0.5
    click(editor, "apply_all")  # the field's geometry is on by default; the checkbox turns it off
    click(editor, "use_geometry")
    click(editor, "apply_all")
    run_until(editor, lambda: len(editor.engine.mask_calls) == 2)
    assert editor.engine.mask_calls == [(0.5, "full"), (0.5, "basic")]
    editor.state.use_geometry = True
    editor.state.tool = "navigate"


def test_a_patch_holds_training_until_its_mask_is_drawn(editor):
    """From a patch's release to the frame that shows its mask no training step starts (one used to start on the
    selection's reply and took both cores from that frame); training resumes once the mask is on screen."""
    run_until(editor, lambda: full_frame(editor))
    editor.state.tool = "select"
    steps, real = [], editor.engine.train_for
    editor.engine.train_for = lambda *a, **k: (steps.append(time.perf_counter()), real(*a, **k))[1]
    try:
        ox, oy = editor.image_origin
        w, h = editor.view_size
        cx, cy = ox + w / 2, oy + h / 2
        frames(editor, 1, mouse(cx - 6, cy - 6))
        frames(editor, 1, mouse(cx - 6, cy - 6, button=0, down=True))
        frames(editor, 1, mouse(cx + 6, cy + 6))
        editor.state.has_selection = False
        frames(editor, 1, mouse(cx + 6, cy + 6, button=0, down=False))
        released = time.perf_counter()
        assert editor.worker.held, "the release keeps the worker held while its selection runs"
        presented = editor.frames_presented
        run_until(editor, lambda: editor.state.has_selection)
        shown = time.perf_counter()
        assert editor.frames_presented > presented and not editor.worker.held
        assert not [t for t in steps if released <= t <= shown], "a training step started before the mask was drawn"
        run_until(editor, lambda: any(t > shown for t in steps))  # and training goes on after it
    finally:
        editor.engine.train_for = real
        editor.state.tool = "navigate"


def test_a_refined_threshold_leaves_a_moved_slider_alone():
    from types import SimpleNamespace

    from repaint_nerf.app.panels.selection import take_refined_threshold

    moved = SimpleNamespace(threshold=0.8, auto_threshold=0.5)
    take_refined_threshold(moved, 0.3)
    assert (moved.threshold, moved.auto_threshold) == (0.8, 0.3)
    untouched = SimpleNamespace(threshold=0.5, auto_threshold=0.5)
    take_refined_threshold(untouched, 0.3)
    assert (untouched.threshold, untouched.auto_threshold) == (0.3, 0.3)
    take_refined_threshold(untouched, None)  # nothing selected any more
    assert untouched.threshold == 0.3


def _draw_mode(editor, mode):
    saved = editor.state.view_mode
    editor.state.view_mode = mode
    shot = frames(editor, 1)
    editor.state.view_mode = saved
    return shot


def click(app, name):
    app.cache["reveal"] = name  # scroll the panel to it first (a small window's panel scrolls)
    frames(app, 3)
    x0, y0, x1, y1 = app.cache["items"][name]
    p = ((x0 + x1) / 2, (y0 + y1) / 2)
    frames(app, 3, mouse(*p))
    frames(app, 1, mouse(*p, button=0, down=True))
    frames(app, 1, mouse(*p))
    frames(app, 1, mouse(*p, button=0, down=False))
    frames(app, 2, mouse(*p))


def test_repaint_previews_and_undo_restores(editor, artifacts_dir):
    import cv2

    editor.state.view_mode = "rgb"
    before = view_pixels(editor, frames(editor, 2))
    click(editor, "prompt")
    frames(editor, 1, lambda io: io.add_input_characters_utf8("a green ball"))
    from imgui_bundle import imgui

    frames(editor, 1, lambda io: io.add_key_event(imgui.Key.enter, True))
    frames(editor, 2, lambda io: io.add_key_event(imgui.Key.enter, False))
    assert editor.state.prompt == "a green ball", "typed into the prompt field"
    editor.state.backend, editor.state.clip_path = "sd", "/models/clip"
    click(editor, "bg_prompt")
    frames(editor, 1, lambda io: io.add_input_characters_utf8("green leaves"))
    frames(editor, 1, lambda io: io.add_key_event(imgui.Key.enter, True))
    frames(editor, 2, lambda io: io.add_key_event(imgui.Key.enter, False))
    click(editor, "repaint")
    run_until(editor, lambda: editor.engine.edit_target is not None or editor.engine.current == 1)
    shot = run_until(editor, lambda: editor.engine.current == 1 and full_frame(editor) and _green_center(editor))
    cv2.imwrite(str(artifacts_dir / "gui_04_repaint.png"), shot[..., ::-1])
    from repaint_nerf.core.repaint.config import RepaintConfig
    from repaint_nerf.core.repaint.registry import clip_weight

    call = editor.engine.repaint_calls[-1]  # what the panel sent: the CLI's defaults, the CLIP loss on with SD
    assert (call["prompt"], call["bg_prompt"], call["guidance"], call["clip_path"]) == \
        ("a green ball", "green leaves", "sd", "/models/clip")
    assert call["config"] == RepaintConfig() and clip_weight(call["guidance"], call["config"]) == 0.01
    editor.state.backend = "offline"
    click(editor, "undo")
    run_until(editor, lambda: editor.engine.current == 0 and not _green_center(editor))
    run_until(editor, lambda: full_frame(editor))
    shot = frames(editor, 2)
    cv2.imwrite(str(artifacts_dir / "gui_05_undo.png"), shot[..., ::-1])
    assert np.abs(view_pixels(editor, shot) - before).mean() < 2


def _green_center(editor, shot=None):
    shot = frames(editor, 1) if shot is None else shot
    px = view_pixels(editor, shot)
    h, w = px.shape[:2]
    c = px[h // 2, w // 2]
    return c[1] > 150 and c[0] < 100


def test_worker_crash_is_shown_and_ui_stays_usable(editor):
    editor.engine.fail_render_after = editor.engine.renders
    editor.camera.orbit(40, 0)
    run_until(editor, lambda: editor.state.error is not None)
    assert "simulated renderer failure" in editor.state.error
    assert editor.worker.alive()
    editor.engine.fail_render_after = None
    editor.state.error = None
    editor.camera.orbit(-40, 0)
    run_until(editor, lambda: full_frame(editor))


def test_an_idle_editor_sleeps_and_a_result_wakes_it(editor):
    """At rest, with no input and no result, frames come at idle_fps (the CPU goes to training); a worker
    reply wakes the waiting UI at once instead of after the idle period."""
    editor.worker.set_training(False)  # training publishes previews, which (rightly) wake the UI
    run_until(editor, lambda: full_frame(editor))
    time.sleep(0.3)
    frames(editor, 3)  # settle: no input, nothing new
    assert not editor._active
    editor.idle_fps = 1.0
    t0 = time.perf_counter()
    editor.frame()
    assert time.perf_counter() - t0 > 0.5  # waited for events (1 s budget), nothing came
    editor.frame()
    editor.call(editor.engine.clear_selection)  # a reply is on its way: the worker wakes the waiting UI
    t0 = time.perf_counter()
    editor.frame()
    assert time.perf_counter() - t0 < 0.5
    editor.idle_fps = 4.0
    editor.worker.set_training(True)


def test_a_moved_view_is_not_redrawn_stale_while_it_renders(editor):
    """After a camera move the old picture is not drawn again at every frame while the new one renders (that
    draw competes with the render for the CPU), but at least every STALE_REDRAW_S; its arrival is drawn."""
    from repaint_nerf.app.editor import STALE_REDRAW_S

    run_until(editor, lambda: full_frame(editor))
    editor.engine.render_delay = 0.5
    try:
        editor.camera.orbit(30, 0)
        presented, n, t0 = editor.frames_presented, 0, time.perf_counter()
        x0 = editor.window.framebuffer_size()[0] - 100  # over the panels: input that keeps frames coming
        while n == 0 or editor.shown_key != editor.requested_key:
            editor.window.inject(mouse(x0 + n % 2, 300))
            editor.frame()
            n += 1
            assert time.perf_counter() - t0 < 10
        waited = time.perf_counter() - t0
        drawn = editor.frames_presented - presented
        assert drawn < n / 2  # most frames that would show the old picture were skipped
        assert drawn >= waited / (STALE_REDRAW_S + 1.0 / editor.max_fps) - 1  # but not for longer than the period
        last = editor.frames_presented
        editor.frame(capture=True)  # a screenshot is always drawn
        assert editor.frames_presented == last + 1
    finally:
        editor.engine.render_delay = 0.0
    run_until(editor, lambda: full_frame(editor))


def test_the_first_move_of_a_resting_view_skips_the_frame_pacing(editor):
    """An active UI paces its frames (max_fps), but the first camera move of a view at rest is sent to the
    worker at once; the drag's next move, while that view renders, waits for its frame as before."""
    run_until(editor, lambda: full_frame(editor))
    x0 = editor.window.framebuffer_size()[0] - 100  # over the panels: input that keeps the UI active
    editor.max_fps = 1.0  # a one-second pace, so a skipped wait is plain to see
    try:
        for dx in (0, 1):
            editor.window.inject(mouse(x0 + dx, 300))
            editor.frame()
        assert editor._active and editor.shown_key == editor.requested_key
        editor.engine.render_delay = 2.0
        editor.camera.orbit(20, 0)
        t0 = time.perf_counter()
        editor.frame()
        assert time.perf_counter() - t0 < 0.5
        assert editor.requested_key[0] == editor.camera.state()  # the request went out in that frame
        editor.camera.orbit(20, 0)  # its view renders (2 s): this move keeps the pace
        t0 = time.perf_counter()
        editor.frame()
        assert time.perf_counter() - t0 > 0.6
    finally:
        editor.max_fps = 30.0
        editor.engine.render_delay = 0.0
    run_until(editor, lambda: full_frame(editor))


def test_window_flags_a_drag_as_navigation_but_not_a_hover(editor):
    """The window's own input callbacks: mouse motion with a button held (or the wheel) may move the camera;
    motion with no button held does not."""
    import glfw

    w = editor.window
    w._navigated = False
    w._on_cursor(w.handle, 10.0, 10.0)
    assert not w.navigated()
    w._on_button(w.handle, 1, glfw.PRESS, 0)
    w._on_cursor(w.handle, 12.0, 10.0)
    assert w.navigated() and w.clicked()
    w._on_button(w.handle, 1, glfw.RELEASE, 0)
    w._navigated = False
    w._on_cursor(w.handle, 14.0, 10.0)
    assert not w.navigated()
    w._on_scroll(w.handle, 0.0, 1.0)
    assert w.navigated()
    frames(editor, 1)


def test_select_by_text_calls_the_engine_and_shows_the_mask(editor):
    editor.clear_selection()
    run_until(editor, lambda: editor.engine.query is None)
    click(editor, "text_section")  # the section is folded by default
    editor.state.text_query, editor.state.clip_path = "red sphere", "/models/clip"
    frames(editor, 2)
    click(editor, "select_text")
    run_until(editor, lambda: editor.state.has_selection)
    assert editor.engine.text_calls == [("red sphere", "new", "/models/clip")]
    np.testing.assert_array_equal(editor.engine.query, [1.0, 0.0, 0.0])
    assert editor.state.view_mode in ("mask", "similarity")
    click(editor, "text_section")
    editor.clear_selection()
