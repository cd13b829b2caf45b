"""`repaint-nerf bench viewport`: the editor in a real window on the demo scene while it trains, driven by
scripted input; reports UI frame time p50/p99, camera move -> first new frame, frames per second and view
age during a continuous drag, patch release -> mask on screen (median of five patches, and one released while
the training views vote on the previous patch's threshold), and slider -> mask (in frames). Starts its
own Xvfb when there is no DISPLAY."""
from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

HELP = "viewport latency in a real window on the demo scene while training (UI frame p50/p99, move/patch/slider latency)"


def _slider_target(app) -> float:
    """A threshold in the slider's range [0, 1] that moves the mask: the median of the newest selection's
    similarity map (the farther of its quartiles when the median sits at the current threshold)."""
    replies = [m for _, what, m in app.events if what == "reply:select" and getattr(m, "value", None) is not None]
    if not replies:
        raise RuntimeError("no selection reply to take a similarity map from")
    sim = np.asarray(replies[-1].value.similarity, dtype=np.float64)
    q1, med, q3 = np.quantile(sim, [0.25, 0.5, 0.75])
    target = med if abs(med - app.state.threshold) > 0.02 else max((q1, q3), key=lambda q: abs(q - app.state.threshold))
    return float(np.clip(target, 0.0, 1.0))


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--json", required=True, help="output JSON file")
    p.add_argument("--scene", default=None, help="scene to open (default: the demo scene)")
    p.add_argument("--seconds", type=float, default=20.0, help="length of the scripted orbit phase")
    p.add_argument("--train-seconds", type=float, default=60.0,
                   help="seconds the scene trains in the window (camera at rest) before the measurements")
    p.add_argument("--drag-seconds", type=float, default=5.0,
                   help="length of the continuous-drag phase (the camera moves every UI frame)")
    p.add_argument("--width", type=int, default=1280)
    p.add_argument("--height", type=int, default=800)


def _ensure_display():
    """Start an Xvfb for the run when there is no DISPLAY; returns the process to stop (or None)."""
    if os.environ.get("DISPLAY"):
        return None
    from repaint_nerf.app.xvfb import start_xvfb

    try:
        return start_xvfb(140, 200, "1920x1080x24")[0]
    except FileNotFoundError:
        from repaint_nerf.core.errors import UserError

        raise UserError("no DISPLAY and Xvfb is not installed", hint="run `bash install.sh` or set DISPLAY") from None


def _pct(xs, q):
    return float(np.percentile(xs, q)) if len(xs) else None


def run(args: argparse.Namespace) -> int:
    from repaint_nerf.core.engine import Engine

    missing = {k: v for k, v in Engine.capabilities().items() if k in ("load", "demo", "field", "render", "train") and v}
    if missing:
        print("the viewport benchmark needs the stage-1 backends, which are not available yet:")
        for k, v in missing.items():
            print(f"  {k}: {v}")
        return 2
    os.environ.setdefault("REPAINT_NERF_NO_VSYNC", "1")
    xvfb = _ensure_display()
    try:
        return _bench(args, Engine())
    finally:
        if xvfb is not None:
            xvfb.terminate()
            xvfb.wait(timeout=10)


PATCH_DRAG_S = 0.3  # how long the scripted patch drag lasts, as a user's
# Patches near the view's centre, where the demo's object is; one sample swung 75-178 ms between runs.
PATCHES = ((0.45, 0.45, 0.55, 0.55), (0.40, 0.40, 0.50, 0.50), (0.50, 0.50, 0.60, 0.60),
           (0.42, 0.50, 0.52, 0.60), (0.50, 0.40, 0.60, 0.50))


def _select_ms(app, patch, drag_s: float = PATCH_DRAG_S) -> float | None:
    """A patch dragged over the viewport as a user does (press, `drag_s` seconds of movement, release, by
    injected mouse input); milliseconds from the release to the end of the frame that shows its mask."""
    from repaint_nerf.app.window import mouse_event

    ox, oy = app.image_origin
    w, h = app.view_size
    p0, p1 = (ox + patch[0] * w, oy + patch[1] * h), (ox + patch[2] * w, oy + patch[3] * h)
    app.state.has_selection = False
    app.window.inject(mouse_event(*p0))
    app.frame()
    app.window.inject(mouse_event(*p0, button=0, down=True))
    app.frame()
    t0 = time.perf_counter()
    while (a := (time.perf_counter() - t0) / max(drag_s, 1e-9)) < 1.0:
        app.window.inject(mouse_event(p0[0] + a * (p1[0] - p0[0]), p0[1] + a * (p1[1] - p0[1])))
        app.frame()
    app.window.inject(mouse_event(*p1, button=0, down=False))
    t_rel = time.perf_counter()
    while not app.state.has_selection and time.perf_counter() - t_rel < 60:
        app.frame()  # the frame that takes the reply draws the mask before it returns
    return (time.perf_counter() - t_rel) * 1000 if app.state.has_selection else None


TOOL_SWITCHES = 3  # one switch swung 83-122 ms between runs: a training step may be under way


def _settled(app, since: float, timeout: float = 60.0) -> tuple[float | None, float]:
    """Run frames until the requested view is on screen at full resolution: (seconds from `since` to its first
    frame at any scale or None, seconds to the sharp one)."""
    first = None
    while time.perf_counter() - since < timeout:
        app.frame()
        if app.last_frame is not None and app.shown_key == app.requested_key:
            first = first or time.perf_counter()
            if app.last_frame.final:
                break
    return (None if first is None else first - since), time.perf_counter() - since


def _tool_switches(app) -> dict:
    """Switching to the patch tool -> its first feature frame (any scale) and the sharp one, median of
    TOOL_SWITCHES switches, each from the navigate tool's settled view. Ends with the patch tool on."""
    firsts, sharps = [], []
    for i in range(TOOL_SWITCHES):
        if i:
            app.state.tool = "navigate"
            _settled(app, time.perf_counter())
        app.state.tool = "select"
        first, sharp = _settled(app, time.perf_counter())
        if first is not None:
            firsts.append(first * 1000)
        sharps.append(sharp * 1000)
    return {"tool_to_first_feature_frame_ms": _pct(firsts, 50), "tool_to_feature_frame_ms": _pct(sharps, 50),
            "tool_to_first_feature_frame_ms_all": firsts}


def _vote_ms(app, since: float, timeout: float = 30.0) -> float | None:
    """Run frames until the training views' vote on the newest patch's threshold replies (not one a user's
    action interrupted); milliseconds from `since`, or None when it did not within `timeout` seconds."""
    while time.perf_counter() - since < timeout:
        for t, what, msg in reversed(app.events):
            if t < since:
                break
            if what == "reply:refine_threshold" and not getattr(msg, "cancelled", False):
                return (t - since) * 1000
        app.frame()
    return None


def _patches(app) -> dict:
    """Patch release -> mask on screen for each of PATCHES, each after the previous patch's vote finished
    (median and all), the vote's time from the release, and one more patch released while a vote runs."""
    masks, votes = [], []
    for patch in PATCHES:
        released = time.perf_counter()
        masks.append(_select_ms(app, patch))
        votes.append(_vote_ms(app, released))
    _select_ms(app, PATCHES[0])
    during = _select_ms(app, PATCHES[1])  # its drag starts a frame after the first patch's mask: the vote runs
    _vote_ms(app, time.perf_counter())
    done = [m for m in masks if m is not None]
    return {"patch_to_mask_ms": float(np.median(done)) if done else None, "patch_to_mask_ms_all": masks,
            "patch_during_vote_ms": during, "vote_ms_p50": _pct([v for v in votes if v is not None], 50),
            "patch_drag_s": PATCH_DRAG_S}


def _drag(app, seconds: float) -> dict:
    """A continuous orbit, as a mouse drag: the camera moves every UI frame. Reports the frames the viewport
    shows per second, how old the view in each is (from the camera state's first frame to the frame that shows
    it), and the render scale that holds that rate."""
    requested: dict = {}
    ages, scales = [], []
    shown = app.frames_shown
    t0 = time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        app.camera.orbit(3, 0)
        app.window.wake()
        t = time.perf_counter()
        app.frame()
        requested.setdefault(app.requested_key, t)
        if app.shown_key in requested and app.last_frame is not None:
            ages.append((time.perf_counter() - requested.pop(app.shown_key)) * 1000)
            scales.append(app.last_frame.scale)
    frames = app.frames_shown - shown
    return {"drag_seconds": seconds, "drag_frames_per_s": frames / seconds,
            "drag_view_age_ms_p50": _pct(ages, 50), "drag_view_age_ms_p99": _pct(ages, 99),
            "drag_render_scale_p50": _pct(scales, 50)}


def _bench(args, engine) -> int:
    from repaint_nerf.app.editor import EditorApp
    from repaint_nerf.app.window import Window

    window = Window(width=args.width, height=args.height)
    app = EditorApp(window, engine, args.scene)
    result: dict = {"scene": args.scene or "demo", "window": [args.width, args.height]}
    try:
        t0 = time.perf_counter()
        while app.last_frame is None:
            app.frame()
            if app.state.error or time.perf_counter() - t0 > 300:
                raise RuntimeError(app.state.error or "no first frame within 300 s")
        result["first_frame_s"] = time.perf_counter() - t0
        # Training phase: the window stays live with the camera at rest, as a user waits for the scene to form.
        t_train = time.perf_counter() + args.train_seconds
        while time.perf_counter() < t_train:
            app.frame()
        result["train_seconds"] = args.train_seconds
        result["step_before_orbit"] = app.state.last_status.get("step")
        # Orbit phase: a camera move every 0.5 s, frame times measured throughout (training runs between).
        frame_ms, drawn_ms, move_ms = [], [], []
        pending: tuple | None = None
        t_end = time.perf_counter() + args.seconds
        next_move = time.perf_counter()
        while time.perf_counter() < t_end:
            now = time.perf_counter()
            if now >= next_move and pending is None:
                app.camera.orbit(15, 0)
                window.wake()  # as the mouse event of a real drag would
                pending = (now, None)
                next_move = now + 0.5
            presented = app.frames_presented
            app.frame()
            frame_ms.append(app.frame_work_ms)  # the UI thread's work, not the pacing wait
            if app.frames_presented > presented:
                drawn_ms.append(app.frame_work_ms)
            if pending is not None:
                if pending[1] is None:
                    pending = (pending[0], app.requested_key)
                elif app.shown_key == pending[1]:
                    move_ms.append((time.perf_counter() - pending[0]) * 1000)
                    pending = None
        result.update(ui_frame_ms_p50=_pct(frame_ms, 50), ui_frame_ms_p99=_pct(frame_ms, 99),
                      ui_frames=len(frame_ms), ui_drawn_frame_ms_p50=_pct(drawn_ms, 50),
                      ui_drawn_frame_ms_p99=_pct(drawn_ms, 99), ui_drawn_frames=len(drawn_ms),
                      move_to_first_frame_ms_p50=_pct(move_ms, 50),
                      move_to_first_frame_ms_p99=_pct(move_ms, 99), moves=len(move_ms),
                      training_step=app.state.last_status.get("step"))
        result.update(_drag(app, args.drag_seconds))
        # Patch release -> mask on screen. A user turns the patch tool on, then presses and drags: the view
        # re-renders with features meanwhile (the editor asks for them while the tool is on), so the release
        # finds this view's feature map (a release on a view never rendered with features waits for a 256-px
        # feature render: 0.7-0.9 s on this CPU).
        if app.state.capabilities.get("select") is None:
            result.update(_tool_switches(app))
            result.update(_patches(app))
            # Slider -> mask: frames until the screen changes after a threshold change within the slider's range
            # [0, 1], to the median similarity of the selected view, so about half its pixels change side.
            base = app.frame(capture=True)
            result["slider_from"], app.state.threshold = app.state.threshold, _slider_target(app)
            result["slider_to"] = app.state.threshold
            n = 0
            while n < 10:
                n += 1
                if np.abs(app.frame(capture=True).astype(int) - base).sum() > 0:
                    break
            result["slider_to_mask_frames"] = n
        else:
            result["patch_to_mask_ms"] = result["slider_to_mask_frames"] = None
            result["selection"] = app.state.capabilities["select"]
    finally:
        app.close()
        window.close()
    from repaint_nerf.core.device import describe

    result["device"] = describe()
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(result, indent=2))
    print(json.dumps(result, indent=2))
    return 0
