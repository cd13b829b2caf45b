"""The editor offers repair on a damaged workspace (issue 36): in a real window under Xvfb, with the real
engine, a workspace whose current version was cut short fails to open with a message naming the file, the
Scene panel offers "Repair workspace", a click repairs it (the damaged version set aside) and the workspace
opens at its newest good version."""
from __future__ import annotations

import shutil

import pytest
import torch

from small_workspace import small_workspace
from test_gui_editor import click, frames, run_until

pytestmark = pytest.mark.gui


@pytest.mark.timeout(240)
def test_editor_offers_repair_and_the_workspace_opens(xvfb_display, scene_factory, tmp_path, artifacts_dir):
    import cv2

    from repaint_nerf.app.editor import EditorApp
    from repaint_nerf.app.window import Window
    from repaint_nerf.core.engine import Engine
    from repaint_nerf.core.workspace.workspace import Workspace

    torch.set_num_threads(1)
    root = small_workspace(scene_factory("demo", size=16, views=4, test_views=1), tmp_path / "ws").root
    current = root / "versions" / "v0003.safetensors"
    current.write_bytes(current.read_bytes()[: current.stat().st_size // 2])  # a save cut short

    window = Window(width=1000, height=960)
    app = EditorApp(window, Engine(device="cpu"), str(root),
                    worker_kwargs={"train_budget_s": 0.02, "rest_s": 0.05, "preview_interval_s": 0.05})
    try:
        shot = run_until(app, lambda: "Repair workspace" in app.cache.get("items", {}), timeout=120)
        shot = frames(app, 2)
        cv2.imwrite(str(artifacts_dir / "gui_repair_offer.png"), shot[..., ::-1])
        errors = [text for kind, text in app.state.messages if kind == "error"]
        assert any("v0003.safetensors" in t and "repaint-nerf repair" in t for t in errors), errors
        assert not app.state.scene_info.get("loaded")

        click(app, "Repair workspace")
        run_until(app, lambda: app.state.scene_info.get("loaded") and app.last_frame is not None, timeout=120)
        shot = frames(app, 3)
        cv2.imwrite(str(artifacts_dir / "gui_repair_done.png"), shot[..., ::-1])
        said = [text for _, text in app.state.messages]
        assert any(t.startswith("repair: versions/v0003.safetensors") and "damaged/" in t for t in said), said
        assert (root / "damaged" / "versions" / "v0003.safetensors").exists()
        assert app.state.repair_offer is None
        assert Workspace.open(root).current_version.id == "v0002"
    finally:
        app.close()
        window.close()
