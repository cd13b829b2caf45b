"""The engine facade: one object that owns a loaded scene, workspace, field, occupancy grid and trainer.

The editor's worker thread and scripts drive everything through it. It composes the public APIs of the
other `core` modules and holds no algorithm of its own. A backend that is not built or not installed
raises `FeatureUnavailable` (a `UserError`), which the editor shows as "not available yet".
"""
from __future__ import annotations

import importlib
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from core.device import get_device
from core.errors import UserError

# Feature -> the module that provides it (checked by import, lazily: `core` stays fast to import).
BACKENDS = {
    "load": "core.scene.loaders.detect",
    "demo": "core.synth.demo",
    "field": "core.field.field",
    "render": "core.render.renderer",
    "train": "core.train.stage1",
    "select": "core.selection",
    "repaint": "core.repaint.trainer",
    "workspace": "core.workspace.workspace",
}


class FeatureUnavailable(UserError):
    """A feature whose backend module is not part of this build yet (or failed to import)."""


def _backend(feature: str):
    name = BACKENDS[feature]
    try:
        return importlib.import_module(name)
    except ImportError as exc:
        raise FeatureUnavailable(f"'{feature}' is not available in this build ({name}: {exc})") from None


def _np(t: torch.Tensor) -> np.ndarray:
    return t.detach().float().cpu().numpy()


class Engine:
    """Everything the editor can do, headless. Not thread-safe: one thread (the worker) owns it."""

    def __init__(self, device: str | None = None):
        self.device = get_device(device)
        self.scene = None
        self.workspace = None
        self.field = None
        self.grid = None
        self.trainer = None
        self.selection = None  # core.selection state (queries added / subtracted)
        self.edit = None  # the running repaint job, if any
        self.paused = False
        self.last_info: dict = {}

    # ---- what exists
    @staticmethod
    def capabilities() -> dict[str, str | None]:
        """Feature -> None when available, else the reason it is not (shown in the panels)."""
        out: dict[str, str | None] = {}
        for feature in BACKENDS:
            try:
                _backend(feature)
                out[feature] = None
            except FeatureUnavailable as exc:
                out[feature] = str(exc)
        return out

    # ---- scene
    def load(self, path: str | Path | None = None, workspace: str | Path | None = None) -> dict:
        """Load a dataset, photo folder or workspace (None: the built-in demo scene); build field and trainer."""
        if path is None:
            path = _backend("demo").demo_scene_path()
        path = Path(path)
        if not path.exists():
            raise UserError("no such dataset, photo folder or workspace", path,
                            hint="check the path, or open the demo scene")
        scene = _backend("load").load_scene(path, workspace=workspace)  # a photo folder caches its SfM there
        _backend("field"), _backend("render")  # a clear "not available" before any work
        ws_mod = _backend("workspace")
        # Default workspace: next to the data, so the dataset folder itself is never written to.
        ws_root = Path(workspace) if workspace else path.parent / f"{path.name}.repaint-nerf"
        ws = ws_mod.Workspace.open_or_create(ws_root)
        ws.update_settings(scene=str(path.resolve()))
        trainer = _backend("train").Stage1Trainer(scene, ws, device=self.device)
        trainer.resume()
        self.scene, self.workspace, self.trainer = scene, ws, trainer
        self.field, self.grid = trainer.field, trainer.grid
        self.selection = None
        self.edit = None
        return self.info()

    def info(self) -> dict:
        """Facts the panels show: scene name, views, field-space training cameras."""
        if self.scene is None:
            return {"loaded": False}
        return {"loaded": True, "name": Path(self.scene.root).name, "format": self.scene.format,
                "views": len(self.scene.train), "cameras": self.scene.field_cameras("train"),
                "workspace": str(self.workspace.root) if self.workspace is not None else None}

    def _need_scene(self) -> None:
        if self.scene is None:
            raise UserError("no scene is loaded", hint="open a dataset, a photo folder or the demo scene first")

    # ---- training
    def can_train(self) -> bool:
        return self.trainer is not None and not self.paused and not getattr(self.trainer, "done", False)

    def train_for(self, seconds: float) -> dict | None:
        """Advance the active job (the repaint edit if one runs, else stage 1) for about `seconds`."""
        if not self.can_train():
            return None
        job = self.edit if self.edit is not None else self.trainer
        info = dict(job.train_for(seconds))
        info["phase"] = "repaint" if job is self.edit else "reconstruct"
        self.last_info = info
        return info

    def pause(self) -> None:
        self.paused = True

    def resume(self) -> None:
        self.paused = False

    # ---- rendering
    def render(self, cameras, scale: float = 1.0, outputs: tuple = ("rgb", "depth"),
               cancel: Callable[[], bool] | None = None) -> dict | None:
        """Render camera 0 of `cameras` (field space) at `scale`: numpy 'rgb' (H,W,3), 'depth', 'feature', 'similarity'."""
        self._need_scene()
        render = _backend("render")
        want = tuple(outputs)
        if self.selection is not None and "feature" not in want:
            want = want + ("feature",)
        opts = render.RenderOptions(outputs=want, background=self.trainer.eval_background())
        with torch.no_grad():
            out = render.render_camera(self.field, self.grid, cameras.to(self.device), 0, opts, scale=scale,
                                       cancel=cancel)
        if out is None:
            return None
        result = {k: _np(v) for k, v in out.items() if isinstance(v, torch.Tensor)}
        if self.selection is not None and "feature" in out:
            result["similarity"] = _np(self.selection.similarity(out["feature"]))
        return result

    # ---- selection
    def select(self, cameras, patch: tuple[float, float, float, float], mode: str = "new") -> np.ndarray:
        """Add ('new', 'add') or subtract ('sub') the mean feature of `patch` (x0, y0, x1, y1 in [0, 1]) of this view.

        Returns the similarity map of the view at full resolution.
        """
        self._need_scene()
        sel = _backend("select")
        feat = self.render(cameras, outputs=("feature",))["feature"]
        if self.selection is None or mode == "new":
            self.selection = sel.Selection()
        self.selection.add_patch(torch.from_numpy(feat), patch, subtract=(mode == "sub"))
        return _np(self.selection.similarity(torch.from_numpy(feat)))

    def clear_selection(self) -> None:
        self.selection = None

    def masks_for_all_views(self, threshold: float) -> int:
        """Compute and save the selection's mask for every training view (what the repaint uses); returns the count."""
        self._need_scene()
        if self.selection is None:
            raise UserError("nothing is selected", hint="drag a rectangle over an object in the viewport first")
        sel = _backend("select")
        masks = sel.masks_for_views(self.field, self.grid, self.scene.field_cameras("train"), self.selection,
                                    threshold, workspace=self.workspace)
        return len(masks)

    # ---- repaint (stage 2)
    def repaint(self, prompt: str, bg_prompt: str = "", backend: str = "offline", options: dict | None = None) -> dict:
        """Start an edit of the masked region; `train_for` then advances it and renders preview it."""
        self._need_scene()
        if not prompt.strip():
            raise UserError("the prompt is empty", hint="type what the selected region should become")
        rep = _backend("repaint")
        self.edit = rep.RepaintTrainer(self.scene, self.field, self.grid, workspace=self.workspace, prompt=prompt,
                                       bg_prompt=bg_prompt, backend=backend, **(options or {}))
        self.paused = False
        return {"started": time.time()}

    def cancel(self) -> None:
        """Stop the running edit and go back to the field as it was before it."""
        if self.edit is not None:
            self.edit.cancel()
            self.edit = None

    def undo(self) -> bool:
        return self._step_version(-1)

    def redo(self) -> bool:
        return self._step_version(+1)

    def _step_version(self, direction: int) -> bool:
        self._need_scene()
        ws = self.workspace
        info = (ws.undo() if direction < 0 else ws.redo()) if ws is not None else None
        if info is None:
            return False
        self.trainer.load_version(ws.version_path(info))
        return True

    # ---- persistence and export
    def save(self) -> str:
        """Write the training checkpoint, and the reconstruction as the first version if there is none yet."""
        self._need_scene()
        self.trainer.save_checkpoint()
        if self.workspace.original_version is None:
            self.trainer.save_version("reconstruction")
        return str(self.workspace.root)

    def export_png(self, cameras, path: str | Path) -> str:
        """Write the full-resolution render of `cameras` as a PNG."""
        import cv2

        rgb = self.render(cameras, outputs=("rgb",))["rgb"]
        img = (np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8)
        path = Path(path)
        if not cv2.imwrite(str(path), img[..., ::-1]):
            raise UserError("cannot write the image", path, hint="choose a folder you can write to, ending in .png")
        return str(path)

    def export_turntable(self, cameras_list: list, path: str | Path, fps: int = 24) -> str:
        """Write an MP4 of the given cameras' renders (the editor passes an orbit around the target)."""
        import cv2

        path = Path(path)
        frames = [(np.clip(self.render(c, outputs=("rgb",))["rgb"], 0, 1) * 255 + 0.5).astype(np.uint8)
                  for c in cameras_list]
        h, w = frames[0].shape[:2]
        writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, (w, h))
        if not writer.isOpened():
            raise UserError("cannot write the video", path, hint="choose a writable path ending in .mp4")
        for f in frames:
            writer.write(f[..., ::-1])
        writer.release()
        return str(path)
