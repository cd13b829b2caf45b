"""`python -m repaint_nerf.app.screenshot --out docs/screenshot.png`: the README's picture of the editor, regenerated.

Trains the demo scene headlessly first (so the picture shows a trained field, not fog), opens the editor at a
common window size under Xvfb when there is no display, drags a patch on the object at the centre of the view
and saves the window with its mask once the view is sharp. Run it again whenever the UI changes.
"""
from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default="docs/screenshot.png", help="PNG to write")
    p.add_argument("--width", type=int, default=1280)
    p.add_argument("--height", type=int, default=800)
    p.add_argument("--steps", type=int, default=1500, help="stage-1 steps before the picture (at most)")
    p.add_argument("--seconds", type=float, default=600.0, help="training time budget before the picture")
    p.add_argument("--patch", default="0.47,0.47,0.53,0.53", help="x0,y0,x1,y1 of the patch in the view [0, 1]")
    args = p.parse_args(argv)

    import cv2

    from repaint_nerf.app.bench.viewport import _select_ms
    from repaint_nerf.core.engine import Engine

    xvfb = None
    if not os.environ.get("DISPLAY"):
        from repaint_nerf.app.xvfb import start_xvfb

        xvfb, os.environ["DISPLAY"] = start_xvfb(97, 140)
    ws = Path(tempfile.mkdtemp(prefix="repaint-nerf-shot-")) / "ws"
    try:
        pre = Engine()
        pre.load(None, ws)  # the demo scene
        t0 = time.perf_counter()
        while pre.trainer.step_count < args.steps and time.perf_counter() - t0 < args.seconds:
            pre.train_for(2.0)
        pre.save()
        print(f"trained {pre.trainer.step_count} steps")
        del pre
        from repaint_nerf.app.editor import EditorApp
        from repaint_nerf.app.window import Window

        window = Window(width=args.width, height=args.height)
        app = EditorApp(window, Engine(), None, str(ws))
        try:
            _until(app, lambda: app.state.scene_info.get("loaded"), 300)
            app.set_training(False)
            app.state.tool = "select"
            _until(app, lambda: _sharp(app), 300)
            patch = tuple(float(v) for v in args.patch.split(","))
            if _select_ms(app, patch) is None:
                raise RuntimeError("the patch selected nothing within a minute")
            app.state.tool = "navigate"
            shown = app.frames_shown
            app.worker.refresh()
            _until(app, lambda: app.frames_shown > shown and _sharp(app), 300)  # the refreshed view, refined
            for _ in range(3):
                shot = app.frame(capture=True)
            out = Path(args.out)
            out.parent.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(out), shot[..., ::-1])
            print(f"wrote {out} ({shot.shape[1]}x{shot.shape[0]}, step {app.state.last_status.get('step')})")
        finally:
            app.close()
            window.close()
    finally:
        if xvfb is not None:
            xvfb.terminate()
    return 0


def _sharp(app) -> bool:
    f = app.last_frame
    return f is not None and f.final and app.shown_key == app.requested_key


def _until(app, pred, timeout: float) -> None:
    t0 = time.perf_counter()
    while not pred():
        if time.perf_counter() - t0 > timeout:
            raise TimeoutError("the editor did not get there in time")
        app.frame()


if __name__ == "__main__":
    raise SystemExit(main())
