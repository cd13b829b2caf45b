"""`python -m repaint_nerf.app.screenshot`: every picture of the README's walkthrough, regenerated in one run.

Opens the editor on a fresh workspace of the demo scene (under Xvfb when there is no display) with fresh
first-run hints, and walks the first edit as a user does: the scene opened, trained, a patch dragged, the
threshold moved, a Repaint with the offline guidance, the two versions compared, and a mesh exported and drawn by
another program (trimesh + matplotlib). Writes the PICTURES below into --out-dir (`screenshot.png` is the
README's first picture). Run it again whenever the UI changes.

With `--capture WS` it pictures any trained workspace instead (a real capture: its opening view, a patch selection,
an offline Repaint), e.g. `python -m repaint_nerf.app.screenshot --capture ws/fox --patch 0.62,0.28,0.78,0.38`.
"""
from __future__ import annotations

import argparse
import contextlib
import os
import shutil
import tempfile
import time
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

# file name -> what it shows (the README's walkthrough names the same files)
PICTURES = {
    "walkthrough_1_open.png": "the demo scene a few seconds after opening: the field is still forming",
    "walkthrough_2_train.png": "trained: the PSNR curve has flattened and the view is sharp",
    "walkthrough_3_patch.png": "a patch being dragged over the block in the middle with the Select patch tool",
    "screenshot.png": "the selection: the block in every view, at its automatic threshold (the README's top)",
    "walkthrough_4_threshold.png": "the threshold slider: lower selects more, higher less",
    "walkthrough_5_repaint.png": "after Repaint with the prompt 'make it blue' (offline guidance)",
    "walkthrough_6_compare.png": "the versions compared with Undo and Redo",
    "walkthrough_7_export.png": "the exported mesh, as trimesh and matplotlib draw the file",
}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out-dir", default="docs", help="folder the PNGs go to")
    p.add_argument("--width", type=int, default=1280)
    p.add_argument("--height", type=int, default=800)
    p.add_argument("--steps", type=int, default=1200, help="stage-1 steps before the trained picture (at most)")
    p.add_argument("--seconds", type=float, default=240.0, help="training time budget before the trained picture")
    p.add_argument("--workspace", default=None,
                   help="a trained workspace of the demo scene to start from instead of training (it is copied, "
                        "not changed)")
    p.add_argument("--patch", default="0.47,0.47,0.53,0.53", help="x0,y0,x1,y1 of the patch in the view [0, 1]")
    p.add_argument("--prompt", default="make it blue", help="the Repaint prompt (offline guidance)")
    p.add_argument("--repaint-steps", type=int, default=150)
    p.add_argument("--mesh-resolution", type=int, default=96)
    p.add_argument("--capture", default=None, metavar="WS",
                   help="instead of the walkthrough: pictures of the trained workspace WS of any scene (a real "
                        "capture): NAME_view.png, NAME_patch.png (the selection of --patch) and with --repaint-steps "
                        "> 0 NAME_repaint.png (--prompt, offline guidance); WS is copied, not changed")
    p.add_argument("--name", default=None, help="--capture: the pictures' name prefix (default: the folder's name)")
    args = p.parse_args(argv)

    tmp = Path(tempfile.mkdtemp(prefix="repaint-nerf-shots-"))
    os.environ["REPAINT_NERF_CONFIG_DIR"] = str(tmp / "config")  # a first run: every hint, and the user's kept
    xvfb = None
    if not os.environ.get("DISPLAY"):
        from repaint_nerf.app.xvfb import start_xvfb

        xvfb, os.environ["DISPLAY"] = start_xvfb(97, 140)
    out = Path(args.out_dir)
    try:
        if args.capture:
            shutil.copytree(args.capture, tmp / "ws")
            with _editor(args, tmp / "ws", path=str(tmp / "ws")) as app:
                _capture_pictures(app, args, out, args.name or Path(args.capture).resolve().name)
            return 0
        with _editor(args, tmp / "fresh") as app:  # a new workspace: the field is still forming
            _until(app, lambda: app.state.scene_info.get("loaded") and _step(app) >= 10 and _sharp(app), 600)
            _shot(app, out / "walkthrough_1_open.png")
        _trained_workspace(args, tmp / "ws")
        with _editor(args, tmp / "ws") as app:
            _walkthrough(app, args, out, tmp)
    finally:
        if xvfb is not None:
            xvfb.terminate()
        shutil.rmtree(tmp, ignore_errors=True)
    return 0


@contextlib.contextmanager
def _editor(args, workspace: Path, path: str | None = None) -> Iterator:
    """The editor on `path` (None: the demo scene) in `workspace`, in a window of the asked size; closed on
    leaving."""
    from repaint_nerf.app.editor import EditorApp
    from repaint_nerf.app.window import Window
    from repaint_nerf.core.engine import Engine

    window = Window(width=args.width, height=args.height)
    app = EditorApp(window, Engine(), path, str(workspace))
    try:
        yield app
    finally:
        app.close()
        window.close()


def _trained_workspace(args, ws: Path) -> None:
    """`ws`: a copy of --workspace, else the demo scene trained headless (faster than in the window, whose views
    of a still foggy field cost seconds each) for --steps or --seconds."""
    if args.workspace:
        shutil.copytree(args.workspace, ws)
        return
    from repaint_nerf.core.engine import Engine

    pre = Engine()
    pre.load(None, ws)
    t0 = time.perf_counter()
    while pre.trainer.step_count < args.steps and time.perf_counter() - t0 < args.seconds:
        pre.train_for(2.0)
    pre.save()
    print(f"trained {pre.trainer.step_count} steps in {time.perf_counter() - t0:.0f} s", flush=True)


def _shot(app, path: Path) -> np.ndarray:
    """Draw a few frames (the last result on screen, the hint up to date) and save the window as `path`."""
    from repaint_nerf.app.pictures import save_png

    for _ in range(3):
        img = app.frame(capture=True)
    save_png(img, path)
    print(f"wrote {path} (step {app.state.last_status.get('step')})", flush=True)
    return img


def _walkthrough(app, args, out: Path, tmp: Path) -> None:
    from repaint_nerf.app.mesh_picture import render_mesh
    from repaint_nerf.app.pictures import save_png, side_by_side

    s = app.state

    def shot(name: str) -> np.ndarray:
        return _shot(app, out / name)

    _until(app, lambda: s.scene_info.get("loaded") and s.last_status, 600)  # a step in the window: its status line
    app.set_training(False)  # still pictures of the trained field from here (its saved curve is plotted)
    _until(app, lambda: _sharp(app), 300)
    shot("walkthrough_2_train.png")

    app.guide.done("orbit")  # the user has looked around; the hint moves on to the patch
    s.tool = "select"
    _until(app, lambda: _sharp(app), 300)  # the view with its features, for the patch
    patch = tuple(float(v) for v in args.patch.split(","))
    _drag_patch(app, patch, lambda: shot("walkthrough_3_patch.png"))
    _until(app, lambda: s.has_selection, 120)
    _refreshed(app)
    shot("screenshot.png")

    auto = s.threshold
    crops = []
    for t in (max(0.0, auto - 0.15), auto, min(1.0, auto + 0.1)):
        s.threshold = t
        crops.append(_viewport(app, app.frame(capture=True)))
    save_png(side_by_side(crops, [f"threshold {t:.2f}" + (" (automatic)" if t == auto else "")
                                  for t in (max(0.0, auto - 0.15), auto, min(1.0, auto + 0.1))]),
             out / "walkthrough_4_threshold.png")
    s.threshold = auto
    app.guide.done("threshold")

    s.tool, s.view_mode = "navigate", "rgb"
    s.prompt, s.backend, s.repaint_config.steps = args.prompt, "offline", args.repaint_steps
    app.start_repaint()
    _until(app, lambda: s.repaint_running, 900)  # masks for every view first: minutes on a busy CPU
    _until(app, lambda: not s.repaint_running, 900)
    app.set_training(False)
    _refreshed(app)
    edited = shot("walkthrough_5_repaint.png")

    for name in ("undo", "redo"):
        n = len(app.events)
        app.call(getattr(app.engine, name))
        _until(app, lambda: any(e[1] == f"reply:{name}" for e in app.events[n:]), 300)
        _refreshed(app)
        if name == "undo":
            before = _viewport(app, app.frame(capture=True))
    save_png(side_by_side([before, _viewport(app, edited)], ["version 1: the photos' scene",
                                                            f"version 2: '{args.prompt}'"]),
             out / "walkthrough_6_compare.png")

    mesh = tmp / "mesh.glb"
    app.start_export(app.engine.export_mesh, str(mesh), resolution=int(args.mesh_resolution))
    _until(app, lambda: s.export_job is None and mesh.is_file(), 900)
    render_mesh(mesh, out / "walkthrough_7_export.png")
    print(f"wrote {out / 'walkthrough_7_export.png'}")


def _capture_pictures(app, args, out: Path, name: str) -> None:
    """A trained workspace as a user meets it: its opening view (a training camera's, in the photos' frame), a patch
    selection over --patch, and an offline Repaint of it; training stays off so the pictures show that field."""
    s = app.state
    _until(app, lambda: s.scene_info.get("loaded"), 1800)
    app.set_training(False)
    _until(app, lambda: _sharp(app), 3600)
    from repaint_nerf.app.window import mouse_event

    app.window.inject(mouse_event(app.image_origin[0] + 4, app.image_origin[1] + 4))  # the pointer off the panels:
    _shot(app, out / f"{name}_view.png")  # no tooltip in the picture
    s.tool = "select"
    app.frame()  # the tool's request goes out (features ride along); before it the old view counts as shown
    _until(app, lambda: _sharp(app), 3600)  # the patch selects from the sharp feature frame, as a user who looks
    _drag_patch(app, tuple(float(v) for v in args.patch.split(",")), lambda: None)
    _until(app, lambda: s.has_selection, 1800)
    _refreshed(app, 3600)
    _shot(app, out / f"{name}_patch.png")
    if args.repaint_steps > 0:
        s.tool, s.view_mode = "navigate", "rgb"
        s.prompt, s.backend, s.repaint_config.steps = args.prompt, "offline", args.repaint_steps
        app.start_repaint()
        _until(app, lambda: s.repaint_running, 3600)
        _until(app, lambda: not s.repaint_running, 3600)
        app.set_training(False)
        _refreshed(app, 3600)
        _shot(app, out / f"{name}_repaint.png")


def _drag_patch(app, patch: tuple[float, ...], mid_drag: Callable[[], object]) -> None:
    """Press, drag and release over `patch` (fractions of the view) by injected mouse input, as a user does;
    `mid_drag` runs while the rectangle is drawn and the button still down."""
    from repaint_nerf.app.window import mouse_event

    ox, oy = app.image_origin
    w, h = app.view_size
    p0, p1 = (ox + patch[0] * w, oy + patch[1] * h), (ox + patch[2] * w, oy + patch[3] * h)
    app.window.inject(mouse_event(*p0))
    app.frame()
    app.window.inject(mouse_event(*p0, button=0, down=True))
    app.frame()
    for a in np.linspace(0.2, 1.0, 5):
        app.window.inject(mouse_event(p0[0] + a * (p1[0] - p0[0]), p0[1] + a * (p1[1] - p0[1])))
        app.frame()
    app.window.inject(mouse_event(*p1))
    mid_drag()
    app.window.inject(mouse_event(*p1, button=0, down=False))
    app.frame()


def _viewport(app, shot: np.ndarray) -> np.ndarray:
    x, y = (int(round(v)) for v in app.image_origin)
    w, h = app.view_size
    return shot[y:y + h, x:x + w]


def _step(app) -> int:
    return int(app.state.last_status.get("step", 0) or 0)


def _sharp(app) -> bool:
    f = app.last_frame
    return f is not None and f.final and app.shown_key == app.requested_key


def _refreshed(app, timeout: float = 300) -> None:
    """Until a new full-resolution frame of the current view is on screen (after a change of the model)."""
    shown = app.frames_shown
    app.worker.refresh()
    _until(app, lambda: app.frames_shown > shown and _sharp(app), timeout)


def _until(app, pred, timeout: float) -> None:
    t0 = time.perf_counter()
    while not pred():
        if time.perf_counter() - t0 > timeout:
            raise TimeoutError(f"the editor did not get there in time: {app.state.messages} {app.state.error}")
        if app.state.error:
            raise RuntimeError(app.state.error)
        app.frame()


if __name__ == "__main__":
    raise SystemExit(main())
