"""The editor on the real engine for GUI tests: a workspace reconstructed headless first, then a window on it."""
from __future__ import annotations

import contextlib
from typing import Iterator


def pretrain(scene: str, workspace: str, steps: int) -> None:
    """Reconstruct `scene` into `workspace` headless for `steps` steps and save, so a test's GUI steps never wait
    on how fast a loaded machine trains (the feature field needs a few hundred steps to separate objects)."""
    from repaint_nerf.core.engine import Engine

    pre = Engine("cpu")
    pre.load(scene, workspace)
    while pre.trainer.step_count < steps:
        pre.train_for(1.0)
    pre.save()


@contextlib.contextmanager
def real_editor(scene: str, workspace: str, width: int, height: int, train_budget_s: float) -> Iterator:
    """An EditorApp on the real CPU engine in a `width` x `height` window, closed on leaving."""
    from repaint_nerf.app.editor import EditorApp
    from repaint_nerf.app.window import Window
    from repaint_nerf.core.engine import Engine

    window = Window(width=width, height=height)
    app = EditorApp(window, Engine("cpu"), scene, workspace,
                    worker_kwargs={"train_budget_s": train_budget_s, "rest_s": 0.05, "preview_interval_s": 0.5})
    try:
        yield app
    finally:
        app.close()
        window.close()
