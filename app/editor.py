"""The desktop editor: a viewport streamed from the worker thread, camera input, patch selection and panels.

The UI thread only does events, imgui, GL uploads and draws; every model call goes to the worker
(`app.worker.Worker`) and comes back as a message. `run_editor` is the entry point of `repaint-nerf`.
"""
from __future__ import annotations

import math
import os
import signal
import time
import traceback
from pathlib import Path
from typing import Any, Callable

import numpy as np
from imgui_bundle import imgui

from repaint_nerf.app import menu_bar
from repaint_nerf.app.camera_control import CameraControl, fit_aspect
from repaint_nerf.app.guide import Guide
from repaint_nerf.app.panels import repaint as repaint_panel
from repaint_nerf.app.panels import scene as scene_panel
from repaint_nerf.app.panels import selection as selection_panel
from repaint_nerf.app.panels import export as export_panel
from repaint_nerf.app.panels import view as view_panel
from repaint_nerf.app.state import EditorState, ExportJob, TrainingHistory
from repaint_nerf.app.user_settings import UserSettings
from repaint_nerf.app.viewport import Viewport
from repaint_nerf.app.window import Window
from repaint_nerf.app.worker import Crashed, Frame, Reply, Status, Worker

PANEL_WIDTH = 400
MODEL_CHANGING = {"undo", "redo", "cancel", "load"}
EXPORTS = {"export_mesh", "export_points", "export_dataset", "export_turntable", "export_camera_path"}
STALE_REDRAW_S = 0.1  # while a moved camera's view renders, the unchanged screen is redrawn at this period
# The panel's render readout (scale, time) changes at most this often, but always for a sharp frame: each change
# rasterizes the panel again where its digits changed (~2 ms on llvmpipe, the whole panel 8-9 ms; unchanged, it is
# blitted from the last draw: window._WindowCache)
READOUT_S = 0.5


def export_message(value: Any) -> str:
    """'wrote PATH (facts)' for an export's reply (a path, or the dict core.export returns)."""
    if not isinstance(value, dict):
        return f"wrote {value}"
    facts = [f"{value[k]} {k}" for k in ("vertices", "faces", "points", "frames") if k in value]
    if "bytes" in value:
        facts.append(f"{value['bytes'] / 1e6:.2f} MB")
    return f"wrote {value['path']}" + (f" ({', '.join(facts)})" if facts else "")


class EditorApp:
    """One editor session: owns the window's viewport, the camera, the UI state and the worker."""

    def __init__(self, window: Window, engine: Any, path: str | None = None, workspace: str | None = None,
                 worker_kwargs: dict | None = None):
        self.window = window
        self.engine = engine
        self.state = EditorState(scene_path=path or "", workspace=workspace)
        self.state.capabilities = engine.capabilities()
        self.viewport = Viewport(window.ctx)
        self.camera: CameraControl | None = None
        self.worker = Worker(engine, **(worker_kwargs or {})).start()
        self.cache: dict = {}
        self.view_size = (1, 1)
        self.image_origin = (0.0, 0.0)
        self.requested_key: tuple | None = None
        self.max_fps = float(os.environ.get("REPAINT_NERF_MAX_FPS", "30"))
        self.idle_fps = float(os.environ.get("REPAINT_NERF_IDLE_FPS", "4"))
        self._frame_started = 0.0
        self._active = True  # the last frame saw input, a result or a new render request
        self.frame_work_ms = 0.0  # the last frame's own time, without the pacing wait before it
        self.worker.notify = window.wake
        self.shown_key: tuple | None = None
        self.frames_shown = 0
        self.frames_presented = 0  # UI frames drawn to the screen (see `_worth_drawing`)
        self._last_present = 0.0
        self._bare: list | None = None  # the screen rects no picture or window covers (Window.end_frame)
        self._picture: tuple | None = None  # (texture, rect): the viewport's picture, drawn under imgui's windows
        self._panel: tuple | None = None  # (draw list, rect) of the panel window: redrawn only when it changed
        self._readout_at = 0.0  # when the panel's render readout last changed
        self.last_frame: Frame | None = None
        self.drag_start: tuple[float, float] | None = None
        self._refine_after: float | None = None  # a patch's threshold the training views vote on next frame
        self._vote_paused: float | None = None  # ... or once the view rests again, after the user interrupted it
        self._hold_until_shown = False  # a patch's release keeps the worker held until its mask is drawn
        self.drag_rect: tuple[float, float, float, float] | None = None  # normalised x0, y0, x1, y1
        self.events: list = []  # (time, what) log for tests and the viewport benchmark
        self.guide = Guide(UserSettings())  # the first-run hint line (app.menu_bar draws it)
        self.open_scene(path)

    # ---- actions (called by panels and input)
    def call(self, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> None:
        """Run `fn` (a bound method of the engine) on the worker; its Reply arrives in `_handle`."""
        self.worker.call(fn, *args, **kwargs)

    def open_scene(self, path: str | None) -> None:
        self._opened = path  # opened again after a repair
        self.state.repair_offer = None
        self.state.loading = True
        self.state.has_selection = False
        self.viewport.upload_similarity(None)
        self.worker.forget_costs()
        # the Scene panel's teacher; None (untouched): the engine keeps the workspace's choice, as before
        self.worker.call(self.engine.load, path, self.state.workspace, feature_model=self.state.feature_model)

    def repair_workspace(self) -> None:
        """Repair the workspace that failed to open (the Scene panel's offer); it opens again when done."""
        root, self.state.repair_offer = self.state.repair_offer, None
        if root:
            self.state.loading = True
            self.state.say(f"repairing {root} ...")
            self.call(self.engine.repair, root)

    def set_training(self, on: bool) -> None:
        self.state.training = on
        self.worker.set_training(on)

    def snap_to_view(self, i: int) -> None:
        cams = self.state.scene_info.get("cameras")
        if self.camera is not None and cams is not None and 0 <= i < len(cams):
            fov = math.degrees(2 * math.atan(0.5 * float(cams.height[i]) / float(cams.fy[i])))
            self.camera.snap_to(cams.c2w[i].double().numpy(), fov_y=fov)

    def clear_selection(self) -> None:
        self.state.has_selection = False
        self.state.masks_done = None
        self.viewport.upload_similarity(None)
        self.call(self.engine.clear_selection)
        self.worker.refresh()

    def start_repaint(self) -> None:
        self.call(self.engine.repaint, **repaint_panel.repaint_request(self.state))

    def export_png(self, path: str) -> None:
        if self.camera is not None:
            self.call(self.engine.export_png, self.camera.cameras(*self.view_size), path)

    def start_export(self, export: Callable[..., Any], *args: Any, **kwargs: Any) -> None:
        """Run an engine export (e.g. `engine.export_mesh`) on the worker with a progress bar and Cancel (one
        export at a time)."""
        if self.state.export_job is not None:
            self.state.say("an export is running; wait for it or cancel it", "error")
            return
        kind = export.__name__.removeprefix("export_")
        target = str(args[-1] if kind == "turntable" else args[0])
        job = self.state.export_job = ExportJob(kind, target)
        self.call(export, *args, cancel=job.cancelled, progress=job.report, **kwargs)

    def _video_size(self) -> tuple[int, int]:
        """Video frames: the viewport's aspect at most `state.video_height` pixels high, even sizes (H.264 4:2:0)."""
        w, h = self.view_size
        k = min(1.0, self.state.video_height / max(h, 1))
        return max(2, round(w * k) // 2 * 2), max(2, round(h * k) // 2 * 2)  # round: 941 * (64 / 941) is 63.99

    def _orbit_cameras(self, frames: int) -> list:
        cam = CameraControl(**{k: getattr(self.camera, k) for k in ("target", "distance", "yaw", "pitch", "fov_y", "up")})
        w, h = self._video_size()
        cams = []
        for _ in range(frames):
            cams.append(cam.cameras(w, h))
            cam.yaw += 2 * math.pi / frames
        return cams

    def _path_cameras(self) -> list:
        from repaint_nerf.core.export.camera_path import CameraPath, interpolate
        from repaint_nerf.core.scene.scene import Normalization

        c2w, fov = interpolate([k[0] for k in self.state.path_keys], [k[1] for k in self.state.path_keys],
                               int(self.state.path_frames))
        cams = CameraPath(c2w, fov, *self._video_size()).cameras(Normalization())  # field space stays field space
        return [cams[i:i + 1] for i in range(len(cams))]

    def export_turntable(self, path: str, frames: int = 48) -> None:
        if self.camera is not None:
            self.start_export(self.engine.export_turntable, self._orbit_cameras(frames), path)  # the Scene panel's button

    def export_video(self, path: str) -> None:
        """A video along the recorded camera path (two or more key views), else the turntable."""
        if self.camera is None:
            return
        keys = len(self.state.path_keys)
        cams = self._path_cameras() if keys >= 2 else self._orbit_cameras(int(self.state.path_frames))
        self.start_export(self.engine.export_turntable, cams, path)

    def add_path_key(self) -> None:
        """Record the current view as a key view of the camera path."""
        if self.camera is not None:
            c2w = self.camera.cameras(*self.view_size).c2w[0].double().numpy()
            self.state.path_keys.append((c2w, float(self.camera.fov_y)))

    def save_camera_path(self, path: str) -> None:
        if len(self.state.path_keys) < 2:
            self.state.say("add at least two key views (Add key view) before saving a path", "error")
            return
        keys = self.state.path_keys
        self.call(self.engine.export_camera_path, [k[0] for k in keys], [k[1] for k in keys], path,
                  int(self.state.path_frames), *self._video_size())

    # ---- messages from the worker
    def _handle(self, msg: Any) -> None:
        s = self.state
        if isinstance(msg, Frame):
            self.viewport.upload_frame(msg.data)
            self.last_frame = msg
            self.shown_key = msg.key
            self.frames_shown += 1
            now = time.perf_counter()
            if msg.final or now - self._readout_at >= READOUT_S:  # a changed readout redraws the whole panel
                s.render_ms, s.render_scale, self._readout_at = msg.render_ms, msg.scale, now
            self.events.append((time.perf_counter(), "frame", msg))
        elif isinstance(msg, Status):
            s.last_status = msg.info
            s.history.add(msg.info)
            if msg.info.get("phase") == "repaint" and msg.info.get("done"):
                s.repaint_running = False
                self.worker.refresh()  # show the finished edit sharp
        elif isinstance(msg, Reply):
            self.events.append((time.perf_counter(), f"reply:{msg.name}", msg))
            if msg.name in EXPORTS:
                s.export_job = None
            if msg.error is not None:
                s.say(f"{msg.name}: {msg.error}", "error")
                if msg.name == "load":
                    s.loading = False
                    s.repair_offer = msg.repairable
                if msg.name == "repair":
                    s.loading = False
                if msg.name == "repaint":
                    s.repaint_running = False
                if msg.name in ("select", "select_text"):
                    s.selection_busy = False
                return
            if msg.name == "load":
                s.loading = False
                s.scene_info = dict(msg.value)
                s.history = s.scene_info.pop("history", None) or TrainingHistory()  # a reopened workspace's curve
                self.camera = CameraControl.framing(s.scene_info["cameras"])
                self.worker.projector.reset()
                for note in s.scene_info.get("notes", []):
                    s.say(note)
            elif msg.name in ("select", "select_text"):
                s.selection_busy = False
                s.has_selection = True
                self.guide.done("select")
                self._vote_paused = None  # a vote for an older selection is moot
                if msg.name == "select":  # a PatchSelected: the map and its automatic threshold
                    self.viewport.upload_similarity(msg.value.similarity, msg.value.region)
                    selection_panel.take_auto_threshold(s, msg.value.auto_threshold)
                    if msg.value.auto_threshold is not None:  # the training views vote on it, after this mask
                        self._refine_after = msg.value.auto_threshold
                else:
                    self.viewport.upload_similarity(msg.value)
                if s.view_mode not in ("similarity", "mask"):
                    s.view_mode = "mask"
            elif msg.name == "refine_threshold":
                if msg.cancelled:  # the user moved on: vote again once the view rests
                    self._vote_paused = msg.tag
                else:
                    selection_panel.take_refined_threshold(s, msg.value)
            elif msg.name == "masks_for_all_views":
                s.masks_done = int(msg.value)
            elif msg.name == "repaint":
                self.guide.done("repaint")
                s.repaint_running = True
                s.training = True
                self.worker.set_training(True)
            elif msg.name in EXPORTS or msg.name in ("export_png", "save"):
                s.say(export_message(msg.value))
                if msg.name != "save":
                    self.guide.done("export")
            elif msg.name == "repair":
                for line in msg.value or ["nothing was damaged"]:
                    s.say(f"repair: {line}")
                self.open_scene(self._opened)
            elif msg.name in ("undo", "redo"):
                if msg.value:
                    self.guide.done("compare")
                else:
                    s.say(f"nothing to {msg.name}")
            if msg.name in MODEL_CHANGING:
                self.worker.refresh()
        elif isinstance(msg, Crashed):
            s.error = f"worker error in {msg.where}:\n{msg.text}"
            s.training = False

    def photo_aspect(self) -> float | None:
        """Width / height of the scene's first training photo (None before a scene is loaded)."""
        cams = self.state.scene_info.get("cameras")
        if cams is None or len(cams) == 0:
            return None
        return float(cams.width[0]) / max(float(cams.height[0]), 1.0)

    # ---- input over the viewport image
    def _image_pos(self, io) -> tuple[float, float]:
        return ((io.mouse_pos.x - self.image_origin[0]) / max(self.view_size[0], 1),
                (io.mouse_pos.y - self.image_origin[1]) / max(self.view_size[1], 1))

    def _viewport_input(self, hovered: bool) -> None:
        io = imgui.get_io()
        cam = self.camera
        if cam is None:
            return
        select_tool = self.state.tool == "select" and self.state.capabilities.get("select") is None
        if hovered and imgui.is_mouse_clicked(imgui.MouseButton_.left) and select_tool:
            self.drag_start = self._image_pos(io)
            self.worker.hold(True)  # the release's selection then runs at once, not after a training step
        if self.drag_start is not None:
            x, y = self._image_pos(io)
            x0, y0 = self.drag_start
            self.drag_rect = (min(x0, x), min(y0, y), max(x0, x), max(y0, y))
            if imgui.is_mouse_released(imgui.MouseButton_.left) or not imgui.is_mouse_down(imgui.MouseButton_.left):
                rect = tuple(float(np.clip(v, 0.0, 1.0)) for v in self.drag_rect)
                self.drag_start = self.drag_rect = None
                if (rect[2] - rect[0]) * self.view_size[0] >= 2 and (rect[3] - rect[1]) * self.view_size[1] >= 2:
                    mode = "add" if io.key_shift else "sub" if io.key_ctrl else "new"
                    if mode != "new" and not self.state.has_selection:
                        mode = "new"
                    self.state.selection_busy = True
                    self.events.append((time.perf_counter(), "patch_release", rect))
                    self.state.select_rect = (rect, mode)
                    self.call(self.engine.select, cam.cameras(*self.view_size), rect, mode)
                    # The hold stays until the frame that shows the mask is drawn: a training step or a sharper
                    # render started on the reply took both cores from that frame (patch to mask 40-57 ms on
                    # the demo, against 50).
                    self._hold_until_shown = True
                else:
                    self.worker.hold(False)
            return
        if hovered:
            d = io.mouse_delta
            if imgui.is_mouse_dragging(imgui.MouseButton_.left, 0.0) and not select_tool:
                cam.orbit(d.x, d.y)
                if d.x or d.y:
                    self.guide.done("orbit")
            if imgui.is_mouse_dragging(imgui.MouseButton_.right, 0.0):
                cam.orbit(d.x, d.y) if select_tool else cam.pan(d.x, d.y, self.view_size[1])
            if imgui.is_mouse_dragging(imgui.MouseButton_.middle, 0.0):
                cam.pan(d.x, d.y, self.view_size[1])
            if io.mouse_wheel:
                cam.zoom(io.mouse_wheel)
        if not io.want_text_input:
            step = 10.0
            keys = imgui.Key
            if imgui.is_key_down(keys.left_arrow):
                cam.orbit(-step, 0)
            if imgui.is_key_down(keys.right_arrow):
                cam.orbit(step, 0)
            if imgui.is_key_down(keys.up_arrow):
                cam.orbit(0, -step)
            if imgui.is_key_down(keys.down_arrow):
                cam.orbit(0, step)
            if imgui.is_key_pressed(keys.equal) or imgui.is_key_pressed(keys.keypad_add):
                cam.zoom(1)
            if imgui.is_key_pressed(keys.minus) or imgui.is_key_pressed(keys.keypad_subtract):
                cam.zoom(-1)
            if imgui.is_key_pressed(keys.r):
                cam.reset()

    def _draw_viewport(self, top: float, width: float, height: float) -> None:
        imgui.set_next_window_pos(imgui.ImVec2(0, top))
        imgui.set_next_window_size(imgui.ImVec2(width, height))
        flags = (imgui.WindowFlags_.no_title_bar | imgui.WindowFlags_.no_resize | imgui.WindowFlags_.no_move
                 | imgui.WindowFlags_.no_scrollbar | imgui.WindowFlags_.no_bring_to_front_on_focus
                 | imgui.WindowFlags_.no_scroll_with_mouse
                 | imgui.WindowFlags_.no_background)  # the image covers it: one blended full-window pass less
        imgui.push_style_var(imgui.StyleVar_.window_padding, imgui.ImVec2(0, 0))
        imgui.begin("Viewport", None, flags)
        avail = imgui.get_content_region_avail()
        pos = imgui.get_cursor_screen_pos()
        x, y, w, h = fit_aspect(avail.x, avail.y, self.photo_aspect() if self.state.photo_frame else None)
        self.view_size = (max(w, 8), max(h, 8))
        self.image_origin = (pos.x + x, pos.y + y)
        imgui.set_cursor_screen_pos(imgui.ImVec2(*self.image_origin))
        tex = self.viewport.draw(self.view_size, self.state.view_mode, self.state.threshold)
        # The picture goes on the screen under imgui's windows (Window.end_frame), opaque; the viewport window has
        # no background, so only the bars the photo frame leaves beside it need clearing.
        rect = (*self.image_origin, *self.view_size)
        self._picture = None if tex is None else (tex, rect)
        self._bare = None if tex is None else _bars((pos.x, pos.y, avail.x, avail.y), rect)
        if tex is not None:
            imgui.dummy(imgui.ImVec2(*self.view_size))
        else:
            imgui.invisible_button("##viewport", imgui.ImVec2(*self.view_size))
            msg = "loading..." if self.state.loading else ("waiting for the first render..." if self.camera else
                                                          "open a scene (Scene panel)")
            imgui.set_cursor_screen_pos(imgui.ImVec2(pos.x + 20, pos.y + 20))
            imgui.text(msg)
        hovered = imgui.is_window_hovered()
        self._viewport_input(hovered)
        if self.drag_rect is not None:
            x0, y0, x1, y1 = self.drag_rect
            dl = imgui.get_window_draw_list()
            ox, oy = self.image_origin
            w, h = self.view_size
            dl.add_rect(imgui.ImVec2(ox + x0 * w, oy + y0 * h), imgui.ImVec2(ox + x1 * w, oy + y1 * h),
                        imgui.get_color_u32(imgui.ImVec4(1.0, 1.0, 0.2, 1.0)), rounding=0.0, thickness=2.0)
        imgui.end()
        imgui.pop_style_var()

    def _draw_panels(self, x: float, top: float, width: float, height: float) -> None:
        imgui.set_next_window_pos(imgui.ImVec2(x, top))
        imgui.set_next_window_size(imgui.ImVec2(width, height))
        imgui.begin("Editor", None, imgui.WindowFlags_.no_resize | imgui.WindowFlags_.no_move
                    | imgui.WindowFlags_.no_collapse)
        self._panel = (imgui.get_window_draw_list(), (x, top, width, height))
        s = self.state
        if s.error:
            imgui.text_colored(imgui.ImVec4(1, 0.35, 0.3, 1), s.error.strip().splitlines()[-1][:200])
            if imgui.is_item_hovered():
                imgui.set_tooltip(s.error[-3000:])
            if imgui.button("Dismiss"):
                s.error = None
            imgui.separator()
        # Fields leave room for their labels on the right at any panel width (imgui's default is a fixed share).
        imgui.push_item_width(-min(9.0 * imgui.get_font_size(), 0.4 * width))
        for panel in (scene_panel, view_panel, selection_panel, repaint_panel, export_panel):
            try:
                panel.draw(self)
            except Exception:  # a bug in one panel must not take the editor down
                s.error = f"panel {panel.__name__}:\n{traceback.format_exc()}"
        imgui.pop_item_width()
        imgui.separator()
        for kind, text in s.messages:
            color = imgui.ImVec4(1, 0.5, 0.4, 1) if kind == "error" else imgui.ImVec4(0.8, 0.8, 0.8, 1)
            imgui.push_style_color(imgui.Col_.text, color)
            imgui.text_wrapped(text[:300])
            imgui.pop_style_color()
        if not self.worker.alive():
            imgui.text_colored(imgui.ImVec4(1, 0.3, 0.3, 1), "the worker thread stopped")
        imgui.end()

    def frame(self, capture: bool = False) -> np.ndarray | None:
        """Run one UI frame: messages, input, render requests, panels, draw. Returns a screenshot on request.

        Frames are paced to at most `max_fps`: without a GPU (or vsync, as under Xvfb) an unpaced loop
        spends both cores drawing the same picture and the training worker got 0.7 steps/s instead of 5.6.
        An idle UI (no input, no new result) draws at `idle_fps`, woken at once by input or the worker.
        """
        idle = not (self._active or self.window.has_pending_input())
        wait = self._frame_started + 1.0 / (self.idle_fps if idle else self.max_fps) - time.perf_counter()
        if wait > 0 and not self._answer_now():
            # An idle UI sleeps until input or the worker; an active one keeps its pace through mouse motion,
            # but a click (a patch's release), the first move of a view at rest, or a result from the worker
            # (a frame, a reply) ends the wait: it is answered, or goes on screen, without a pacing delay.
            deadline = time.perf_counter() + wait
            while (left := deadline - time.perf_counter()) > 0:
                self.window.wait_events(left)
                if idle or self.worker.result_ready() or self._answer_now():
                    break
        self._frame_started = time.perf_counter()
        self.window.begin_frame()
        msgs = self.worker.poll()
        for msg in msgs:
            self._handle(msg)
        io = imgui.get_io()
        self._active = (any(not isinstance(m, Status) for m in msgs) or imgui.is_any_mouse_down()
                        or io.mouse_delta.x != 0 or io.mouse_delta.y != 0 or io.mouse_wheel != 0
                        or imgui.is_any_item_active() or self.drag_start is not None)
        w, h = self.window.framebuffer_size()
        panel_w = min(PANEL_WIDTH, max(w // 3, 200))
        top = menu_bar.draw(self)
        self._draw_viewport(top, w - panel_w, h - top)
        self._request_view()  # before the panels and the draw: the worker starts on a camera move at once
        self._draw_panels(w - panel_w, top, panel_w, h - top)
        self._request_view()  # a panel changed the view (snap, reset, field of view, view mode, tool)
        present = capture or self._worth_drawing(msgs)  # a screenshot is always drawn
        shot = self.window.end_frame(capture=capture, present=present, bare=self._bare, underlay=self._picture,
                                     cached=self._panel)
        self.frame_work_ms = (time.perf_counter() - self._frame_started) * 1000.0
        if present:
            self._last_present = self._frame_started
            self.frames_presented += 1
            if self._hold_until_shown and not self.state.selection_busy:  # the patch's mask (or error) is shown
                self._hold_until_shown = False
                self.worker.hold(False)
            self._queue_vote()
        return shot

    def _answer_now(self) -> bool:
        """Input that ends the frame pacing's wait: a click, or a camera move while the view on screen is the
        one last asked for (no render in flight). The first move of a drag goes to the worker at once, up to a
        frame period (33 ms) sooner; the drag's later moves keep the pace while their views render."""
        if self.window.clicked():
            return True
        if self.requested_key is None or self.shown_key != self.requested_key:
            return False
        return self.window.navigated() or (self.camera is not None and self.camera.state() != self.requested_key[0])

    def _queue_vote(self) -> None:
        """Ask the training views' vote on the newest patch's threshold (Engine.refine_threshold) once its mask
        is on screen, not within the frame that shows it; it takes about a second of the worker, so it gives way
        to the user's next camera move, patch or command, and runs again when the view rests."""
        if self._refine_after is not None:
            own = self._refine_after
        elif self._vote_paused is not None and self._view_rests():
            own = self._vote_paused
        else:
            return
        self._refine_after = self._vote_paused = None
        if self.state.has_selection:
            self.call(self.engine.refine_threshold, own, tag=own, cancellable=True)

    def _view_rests(self) -> bool:
        """The requested view is on screen at full resolution and no gesture is under way."""
        return (self.last_frame is not None and self.last_frame.final and self.shown_key == self.requested_key
                and self.drag_start is None and not imgui.is_any_mouse_down() and not self.state.selection_busy)

    def _worth_drawing(self, msgs: list) -> bool:
        """False for a frame that would show the same old picture while the worker renders a moved camera's
        view: on a software rasterizer drawing it costs both cores 10-15 ms, taken from that very render. Such
        frames still take input; the screen is redrawn at least every STALE_REDRAW_S."""
        awaiting = self.requested_key is not None and self.requested_key != self.shown_key
        return (not awaiting or any(not isinstance(m, Status) for m in msgs) or self.drag_start is not None
                or imgui.is_any_item_active() or imgui.get_io().want_text_input
                or self._frame_started - self._last_present >= STALE_REDRAW_S)

    def _request_view(self) -> None:
        """Ask the worker for the current view when it differs from the last request."""
        if self.camera is None or not self.state.scene_info.get("loaded"):
            return
        # Features ride along while the patch tool is on, so a patch selects from the frame on screen.
        want_feature = self.state.view_mode == "feature" or self.state.tool == "select"
        outputs = ("rgb", "depth") + (("feature",) if want_feature else ())
        key = (self.camera.state(), self.view_size, outputs)
        if key != self.requested_key:
            self.requested_key = key
            self._active = True
            self.events.append((time.perf_counter(), "request", key))
            self.worker.request_render(self.camera.cameras(*self.view_size), key, outputs)

    def close(self) -> None:
        self.worker.stop()
        self.viewport.release()


def _bars(area: tuple, inner: tuple) -> list[tuple]:
    """The parts of rect `area` outside rect `inner` (both x, y, w, h, `inner` within `area`): up to four strips."""
    ax, ay, aw, ah = area
    ix, iy, iw, ih = inner
    strips = [(ax, ay, aw, iy - ay), (ax, iy + ih, aw, ay + ah - iy - ih),
              (ax, iy, ix - ax, ih), (ix + iw, iy, ax + aw - ix - iw, ih)]
    return [r for r in strips if r[2] > 0 and r[3] > 0]


def run_editor(path: str | None = None, workspace: str | None = None) -> int:
    """Open the editor window on `path` (None: the demo scene) and run until it is closed."""
    from repaint_nerf.core.engine import Engine

    window = Window(title="RePaint-NeRF" + (f" - {Path(path).name}" if path else ""))
    # SIGTERM closes the window as the close button does: the loop ends, the worker stops, no stack trace
    signal.signal(signal.SIGTERM, lambda signum, frame: window.request_close())
    app = EditorApp(window, Engine(), path, workspace)
    try:
        while not window.should_close():
            app.frame()
    finally:
        app.close()
        window.close()
    return 0
