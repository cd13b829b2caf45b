"""The engine facade: one object that owns a loaded scene, workspace, field, occupancy grid and trainers.

The editor's worker thread and scripts drive everything through it: load (dataset, photo folder via SfM,
or a saved workspace), stage-1 training with teacher features and depth priors (paper Eq. s1), render,
select (patch queries, similarity, masks for every view), repaint (paper Eq. s2) with pause/cancel,
undo/redo through workspace versions, save and export. It composes the public APIs of the other `core`
modules and holds no algorithm of its own; scenes and workspaces open through `core.session`.
"""
from __future__ import annotations

import dataclasses
import importlib.util
import time
from pathlib import Path
from typing import Any, Callable, NamedTuple

import numpy as np
import torch

from repaint_nerf.core.device import get_device
from repaint_nerf.core.errors import UserError, WorkspaceError
from repaint_nerf.core.render.renderer import RenderOptions, render_camera
from repaint_nerf.core.repaint import registry
from repaint_nerf.core.repaint.config import RepaintConfig
from repaint_nerf.core.repaint.trainer import RepaintTrainer
from repaint_nerf.core.select.autothreshold import EVAL_SIDE
from repaint_nerf.core.select.masks import (DEFAULT_THRESHOLD, FIRST_SURFACE, ViewCache, check_threshold, load_masks,
                                          masks_for_views)
from repaint_nerf.core.select.selection import Selection
from repaint_nerf.core.session import Teachers, start_reconstruction
from repaint_nerf.core.synth.demo import demo_scene_path
from repaint_nerf.core.train.stage1 import TrainConfig

# Optional packages (the `diffusion` extra) -> the features that need them; everything else is always built.
OPTIONAL = {"sd": ("diffusers", "transformers")}
# The viewport never renders finer than this multiple of the training images' long side (sharper than
# the data adds nothing and costs seconds per frame on a CPU).
MAX_RENDER_OVERSAMPLE = 2.0
VOTE_SIDE = 128  # long side of the training views rendered to vote on a free-view patch's threshold (the
# automatic threshold reads maps at 128 px at most: autothreshold.patch_auto_threshold_px)
# Samples per marching round of a cancellable (viewport) render, per CPU thread doing it: a cancel waits for at most
# one round, so a render on fewer threads (the worker's while the user navigates) takes smaller rounds.
INTERACTIVE_CHUNK_PER_THREAD = 1 << 15
INTERACTIVE_CHUNK_CUDA = 1 << 16  # a GPU's rounds do not depend on the CPU threads
# Early ray termination of what Engine.render draws (the viewport, PNG and video exports: 8-bit colour). A ray
# stopped at transmittance T changes its colour by at most T (samples behind it, against the background), so
# below half an 8-bit level (1/510) nothing on screen changes; training keeps TrainConfig.t_threshold (1e-4). On
# the fox capture (contracted room) a 288x512 frame: 33.8 -> 30.8 samples a ray, 4.05 -> 3.65 s (medians of 3
# alternating pairs), largest change 0.25 of a level.
DISPLAY_T_THRESHOLD = 1e-3


def editor_train_config(device: torch.device) -> TrainConfig:
    """Stage-1 settings for interactive training: on a CPU, smaller batches and occupancy grid, and grid updates
    spread over their 16 steps, so no step is long (a camera move or a patch waits for one step: on the demo
    about 45 ms, where an unspread warm-up sweep made every 16th step take 200-330 ms); on CUDA the paper's
    defaults, spread likewise."""
    if device.type == "cuda":
        return TrainConfig(grid_update_spread=True)
    return TrainConfig(rays_per_batch=1024, grid_resolution=64, max_samples=256, grid_update_spread=True)


SELECT_SIDE = 256.0  # px: the long side of the feature render a patch selects from when the view has none fine enough


class FeatureView(NamedTuple):
    """A rendered view's maps a patch selection reads: features (H, W, F), median and expected z-depth and opacity
    (H, W) (core.select.masks.ViewMaps says which part reads which depth), and the camera (field space) at the size
    they were rendered."""

    key: tuple
    feature: torch.Tensor
    depth: np.ndarray
    opacity: np.ndarray
    camera: object
    expected_depth: np.ndarray
    coarse: bool = False  # marched a longer step (a view's first frame at the scale floor): a patch re-renders


@dataclasses.dataclass
class PatchSelected:
    """What a patch selection gives the view: its similarity map (H, W), the query's automatic threshold
    (None for a subtracted patch) and the overlay's map (Selection.region_map; None without anchors in view),
    all computed on the engine's thread."""

    similarity: np.ndarray
    auto_threshold: float | None
    region: np.ndarray | None = None


class FeatureUnavailable(UserError):
    """A feature whose optional packages are not installed."""


def _np(t: torch.Tensor) -> np.ndarray:
    return t.detach().float().cpu().numpy()


class Engine:
    """Everything the editor can do, headless. Not thread-safe: one thread (the worker) owns it."""

    def __init__(self, device: str | None = None, train_cfg: Any = None, features: bool = True,
                 depth: bool = True):
        self.device = get_device(device)
        self.train_cfg = train_cfg  # core.train.stage1.TrainConfig for new reconstructions (None: default)
        self.use_features, self.use_depth = features, depth
        self.scene = None
        self.workspace = None
        self.field = None
        self.grid = None
        self.trainer = None
        self.selection = None  # core.select.Selection (queries added / subtracted)
        self.masks: list[np.ndarray] | None = None  # per training view, what the repaint uses
        self.edit = None  # the running core.repaint.trainer.RepaintTrainer, if any
        self.paused = False
        self.stage1_frozen = False  # after an edit, stage 1 would pull the field back to the photos
        self.last_info: dict = {}
        self.notes: list[str] = []
        self._feature_cache: FeatureView | None = None  # the newest render's feature map, depth and opacity
        self._text_query: tuple | None = None  # (workspace root, clip path, (teacher, codec)) for select_text
        self._saved_step = -1  # stage-1 step of the newest saved version

    # ---- what exists
    @staticmethod
    def capabilities() -> dict[str, str | None]:
        """Optional feature -> None when its packages are installed, else why it is not available (the panels
        show it)."""
        out: dict[str, str | None] = {}
        for feature, packages in OPTIONAL.items():
            missing = [p for p in packages if importlib.util.find_spec(p) is None]
            out[feature] = None if not missing else (
                f"'{feature}' is not available in this install (missing {', '.join(missing)}: "
                f"pip install 'repaint-nerf[diffusion]')")
        return out

    # ---- scene
    def load(self, path: str | Path | None = None, workspace: str | Path | None = None,
             feature_model: str | None = None) -> dict:
        """Load a dataset, photo folder or saved workspace (None: the built-in demo scene) with its field.

        A workspace opens at its current version. Otherwise the workspace defaults to a folder next to the
        data (the dataset folder itself is never written to) and resumes its checkpoint when there is one.
        `feature_model` (a built-in name such as 'efficientnet-lite0', or a model path / id) is the feature
        teacher as `train --feature-model` takes it (a change of the saved one adds a note to `notes`); None keeps
        the workspace's saved choice, else the environment's, else stage1_targets.default_feature_model().
        """
        teachers = Teachers(features=self.use_features, depth=self.use_depth, feature_model=feature_model)
        rec = start_reconstruction(demo_scene_path() if path is None else path, workspace,
                                   train_cfg=self.train_cfg or editor_train_config(self.device),
                                   teachers=teachers, device=self.device)
        ws = rec.workspace
        if self.trainer is not None:
            self.trainer.close()  # its teacher thread, if any, stops (a failed load above keeps it)
        self.scene, self.workspace, self.trainer, self.notes = rec.scene, ws, rec.trainer, rec.notes
        self.field, self.grid = rec.trainer.field, rec.trainer.grid
        self.selection, self.masks, self.edit, self._feature_cache = None, None, None, None
        self._text_query = None
        self.paused = False
        self.stage1_frozen = any(v.kind == "edit" for v in ws.versions)
        self._saved_step = rec.trainer.step_count if ws.current_version is not None else -1
        return self.info()

    @staticmethod
    def repair(workspace: str | Path) -> list[str]:
        """Repair a damaged workspace so it opens again (core.workspace.repair): one line per action."""
        from repaint_nerf.core.workspace.repair import repair_workspace

        return repair_workspace(workspace)

    def info(self) -> dict:
        """Facts the panels show: scene name, views, field-space training cameras, what can be done."""
        if self.scene is None:
            return {"loaded": False}
        root = Path(self.scene.root)
        ver = self.workspace.current_version if self.workspace is not None else None
        return {"loaded": True, "name": root.name, "format": self.scene.format,
                "views": len(self.scene.train), "cameras": self.scene.field_cameras("train"),
                "workspace": str(self.workspace.root) if self.workspace is not None else None,
                "settings": dict(self.workspace.settings) if self.workspace is not None else {},
                "feature_head": self.has_feature_head(),
                "has_edited": (root / "edited" / "transforms_train.json").is_file(),
                "version": None if ver is None else {"id": ver.id, "name": ver.name, "kind": ver.kind},
                "step": int(self.trainer.step_count), "notes": list(self.notes), "device": str(self.device),
                "history": self.trainer.history.copy()}  # the loss/PSNR curve so far, kept in the checkpoint

    @property
    def sample_budget(self) -> int:
        """Steps across the field cube's diagonal the field is trained at, and so viewed, selected and edited at."""
        return int(getattr(self.trainer.cfg, "max_samples", 0) or 1024)

    def _need_scene(self) -> None:
        if self.scene is None:
            raise UserError("no scene is loaded", hint="open a dataset, a photo folder or the demo scene first")

    def _need_feature_head(self) -> None:
        if not self.has_feature_head():
            raise UserError("this field was trained without a feature head, so it cannot select",
                            self.workspace.root if self.workspace is not None else None,
                            hint="open the scene's dataset folder with a new workspace (features train with it)")

    def has_feature_head(self) -> bool:
        return self.field is not None and int(getattr(getattr(self.field, "cfg", None), "feature_dim", 0) or 0) > 0

    # ---- training
    def can_train(self) -> bool:
        """Whether `train_for` has work: a running edit, or stage 1 (until an edit froze it)."""
        if self.trainer is None or self.paused:
            return False
        if self.edit is not None:
            return not self.edit.done
        return not self.stage1_frozen and not getattr(self.trainer, "done", False)

    def train_for(self, seconds: float, stop: Callable[[], bool] | None = None,
                  interlude: Callable[[], None] | None = None) -> dict | None:
        """Advance the active job (the repaint edit if one runs, else stage 1) for about `seconds`, at least one
        step, ending early between steps once `stop()` turns true; each step runs `interlude()` before its backward
        pass (the worker renders a new view there)."""
        if not self.can_train():
            return None
        if self.edit is not None:
            info = dict(self.edit.train_for(seconds, stop, interlude))
            info["phase"] = "repaint"
            info["steps"] = int(self.edit.cfg.steps)
            if self.edit.done:
                ver = self.edit.version
                self.edit = None
                if ver is not None:  # the stage-1 optimiser's moments belong to the old field
                    self.trainer.load_version(self.workspace.version_path(ver))
                    info["version"] = ver.id
                self._feature_cache = None
        else:
            info = dict(self.trainer.train_for(seconds, stop, interlude))
            info["phase"] = "reconstruct"
        self.last_info = info
        return info

    def pause(self) -> None:
        self.paused = True

    def resume(self) -> None:
        self.paused = False

    # ---- rendering
    def max_scale(self, cameras) -> float:
        """The finest scale `render` gives camera 0 of `cameras` (the viewport's cap: MAX_RENDER_OVERSAMPLE times the
        training resolution), which may be over 1."""
        w0, h0 = self.scene.train.images[0].shape[1], self.scene.train.images[0].shape[0]
        side = float(max(int(cameras.width[0]), int(cameras.height[0])))
        return max(MAX_RENDER_OVERSAMPLE * max(w0, h0) / side, 1e-3)

    def render(self, cameras, scale: float = 1.0, outputs: tuple = ("rgb", "depth"),
               cancel: Callable[[], bool] | None = None, full: bool = False, stride: float = 1.0) -> dict | None:
        """Render camera 0 of `cameras` (field space) at `scale`: numpy 'rgb' (H,W,3), 'depth', 'feature',
        'similarity' (when something is selected). The viewport is capped at twice the training resolution
        unless `full`; `stride` > 1 marches a coarser step (a moving view's preview); returns None when
        `cancel()` turned true."""
        self._need_scene()
        want = tuple(o for o in outputs if o != "feature" or self.has_feature_head())
        if self.selection is not None and "feature" not in want and self.has_feature_head():
            want = want + ("feature",)
        if "feature" in want:  # a patch drawn on this view needs its surface points and edges (FeatureView)
            want = want + tuple(o for o in ("depth", "median_depth", "opacity") if o not in want)
        finest = self.max_scale(cameras)
        capped = not full and scale >= finest
        if capped:
            scale = finest
        opts = RenderOptions(outputs=want, background=self.trainer.eval_background(),
                             max_samples=self.sample_budget,
                             t_threshold=DISPLAY_T_THRESHOLD, step_stride=stride,
                             feature_first_surface=FIRST_SURFACE)  # as the selection's views read it
        if cancel is not None:  # interactive: smaller rounds, so a camera move cancels within ~20 ms, not ~80
            opts.chunk = (INTERACTIVE_CHUNK_CUDA if self.device.type == "cuda"
                          else INTERACTIVE_CHUNK_PER_THREAD * torch.get_num_threads())
        was_training = self.field.training
        self.field.eval()
        try:
            with torch.no_grad():
                out = render_camera(self.field, self.grid, cameras.to(self.device), 0, opts, scale=scale,
                                           cancel=cancel)
        finally:
            self.field.train(was_training)
        if out is None:
            return None
        if "feature" in out:
            cam = cameras.to("cpu")[0]
            self._feature_cache = FeatureView(self._camera_key(cameras), out["feature"].float().cpu(),
                                              _np(out["median_depth"]), _np(out["opacity"]),
                                              cam if scale == 1.0 else cam.scaled(scale), _np(out["depth"]),
                                              stride != 1.0)
        result: dict = {k: _np(v) for k, v in out.items() if isinstance(v, torch.Tensor)}
        result["capped"] = capped  # the finest render this view gets: the viewport needs no refinement
        if self.selection is not None and "feature" in out:
            result["similarity"] = _np(self.selection.similarity(out["feature"].float()))
            result["region"] = self._region(result["similarity"], self._feature_cache)
        return result

    def _region(self, similarity: np.ndarray, view: "FeatureView") -> np.ndarray | None:
        """The overlay's map of a view (Selection.region_map): None where it sees no anchor."""
        return self.selection.region_map(similarity, view.depth, view.opacity, view.camera, view.expected_depth)

    @staticmethod
    def _camera_key(cameras) -> tuple:
        c = cameras.to("cpu")
        return (tuple(np.round(c.c2w[0].double().numpy().reshape(-1), 6)), float(c.fx[0]),
                int(c.width[0]), int(c.height[0]))

    # ---- selection
    def _feature_view(self, cameras) -> "FeatureView":
        """The maps a patch on this view reads: the newest feature render of this camera, unless it is coarser
        than the automatic threshold evaluates (`autothreshold.EVAL_SIDE`), as the first frame after switching to
        the patch tool is (on the fox capture 49x27 or 61x34 px: the same patch took thresholds from 0.665 to 0.84
        with the scale of the frame on screen) or marched at a longer step; then a render of SELECT_SIDE px."""
        side = max(int(cameras.width[0]), int(cameras.height[0]))
        cached = self._feature_cache
        if (cached is not None and cached.key == self._camera_key(cameras) and not cached.coarse
                and max(cached.feature.shape[:2]) >= min(side, EVAL_SIDE)):
            return cached
        self.render(cameras, scale=min(1.0, SELECT_SIDE / side), outputs=("feature",))
        return self._feature_cache

    def select(self, cameras, patch: tuple[float, float, float, float], mode: str = "new") -> PatchSelected:
        """Add ('new', 'add') or subtract ('sub') the mean feature of `patch` (x0, y0, x1, y1 in [0, 1]) of this
        view, using the newest rendered feature map of this camera. Returns the view's similarity map.

        A positive patch also keeps its surface points (Selection.anchors): this camera is not a training view,
        and the points seed the training views' masks, so the field's geometry shapes them as it does `select`'s."""
        self._need_scene()
        self._need_feature_head()
        view = self._feature_view(cameras)
        if self.selection is None or mode == "new":
            self.selection = Selection(teacher=str(self.workspace.settings.get("teacher", "default")))
        self.selection.add_patch(view.feature, patch, subtract=(mode == "sub"))
        self.masks = None
        similarity = _np(self.selection.similarity(view.feature))
        auto = None
        if mode != "sub":  # saved with the selection, and the editor's slider starts at it
            auto = self.selection.anchor_patch(similarity, patch, view.depth, view.opacity, view.camera,
                                               view.expected_depth)
        # a first patch's region is its threshold's (no second pass); an added or subtracted one joins the others'
        region = self.selection.patch_region if mode == "new" else self._region(similarity, view)
        return PatchSelected(similarity, auto, region)

    def refine_threshold(self, own: float, cancel: Callable[[], bool] | None = None) -> float | None:
        """The newest free-view patch's automatic threshold (`own`, what `select` returned) once the training
        views that see its surface points vote (Selection.refine_auto_threshold): up to `geometry.VOTE_VIEWS`
        of them, rendered at most `VOTE_SIDE` px on a side. The editor asks for it after the patch's mask is on
        screen (about 1 s on one core), as work the user can interrupt: None when `cancel()` turns true before
        the vote, and when nothing with anchors is selected."""
        from repaint_nerf.core.select.geometry import anchor_views
        from repaint_nerf.core.select.masks import render_view_maps

        self._need_scene()
        sel = self.selection
        if sel is None or not len(sel.anchors):
            return None
        cams = self.scene.field_cameras("train").to("cpu")
        views = anchor_views(sel.anchor_points(), cams)
        if not views:
            return float(own)
        voters = cams[torch.tensor(views, dtype=torch.long)]
        side = max(int(voters.width.max()), int(voters.height.max()))
        if side > VOTE_SIDE:
            voters = voters.scaled(VOTE_SIDE / side)
        opts = RenderOptions(max_samples=self.sample_budget)
        was_training = self.field.training
        self.field.eval()
        maps = []
        try:
            with torch.no_grad():
                on_device = voters.to(self.device)
                for i in range(len(views)):
                    maps.append(render_view_maps(self.field, self.grid, on_device, i, opts, cancel=cancel))
                    if maps[-1] is None:
                        return None
        finally:
            self.field.train(was_training)
        return sel.refine_auto_threshold(own, maps, voters)

    def select_text(self, cameras, text: str, mode: str = "new", clip_path: str | None = None) -> np.ndarray:
        """Start ('new') or extend ('add') the selection with a text query through the workspace's CLIP-aligned
        teacher (`clip_path`, else $REPAINT_NERF_CLIP_PATH or the 'clip_path' setting). Returns this view's
        similarity map, as `select` does."""
        self._need_scene()
        if mode not in ("new", "add"):
            raise UserError(f"a text query can start or extend a selection, not {mode!r}",
                            hint="subtract with a patch (ctrl-drag) instead")
        self._need_feature_head()
        teacher, codec = self._text_teacher(clip_path)
        feat = self._feature_view(cameras).feature
        selection = self.selection if self.selection is not None and mode == "add" else \
            Selection(teacher=str(self.workspace.settings.get("teacher", "default")), cleanup=False)
        selection.add_text(text, teacher, codec)
        self.selection, self.masks = selection, None
        return _np(self.selection.similarity(feat))

    def _text_teacher(self, clip_path: str | None) -> tuple:
        """(teacher with encode_text, codec) of the workspace, loaded once per workspace and CLIP path."""
        from repaint_nerf.core.teachers.text import workspace_text_query

        key = (str(self.workspace.root), clip_path or None)
        if self._text_query is None or self._text_query[:2] != key:
            self._text_query = key + (workspace_text_query(self.scene, self.workspace, clip_path),)
        return self._text_query[2]

    def clear_selection(self) -> None:
        self.selection = None
        self.masks = None

    def masks_for_all_views(self, threshold: float, geometry: str | None = None) -> int:
        """Compute and save the selection's mask for every training view (what the repaint uses); returns the count.
        `geometry`: 'full' or 'basic' (core.select.geometry.parts_named; None: the selection's)."""
        self._need_scene()
        if self.selection is None:
            raise UserError("nothing is selected", hint="drag a rectangle over an object in the viewport first")
        if geometry is not None:
            from repaint_nerf.core.select.geometry import parts_named

            parts_named(geometry)  # an unknown name is a UserError
            self.selection.geometry = geometry
        from repaint_nerf.core.teachers.sam_refine import workspace_refiner  # the workspace's SAM choice (select --sam-path)

        self.selection.threshold = check_threshold(threshold)
        was_training = self.field.training
        self.field.eval()
        try:
            with torch.no_grad():
                cams = self.scene.field_cameras("train").to(self.device)
                opts = RenderOptions(max_samples=self.sample_budget)
                masks = masks_for_views(self.field, self.grid, cams, self.selection, threshold,
                                            workspace=self.workspace, cache=ViewCache(self.field, self.grid, cams,
                                                                                          render_opts=opts),
                                            names=list(self.scene.train.names or []) or None,
                                            refine=workspace_refiner(self.workspace, self.scene.train.images),
                                            images=self.scene.train.images)
        finally:
            self.field.train(was_training)
        self.selection.save(self.workspace)
        self.masks = masks
        return len(masks)

    # ---- repaint (stage 2)
    def repaint(self, prompt: str, bg_prompt: str = "", guidance: str = "offline", config: RepaintConfig | None = None,
                threshold: float | None = None, sd_path: str | None = None, clip_path: str | None = None,
                color: str | None = None) -> dict:
        """Start an edit of the masked region (paper Eq. s2); `train_for` then advances it.

        `guidance`: a backend of core.repaint.registry (offline, recolor, remove, sd, analytic). `config`: a
        core.repaint.config.RepaintConfig (None: its defaults). `threshold`: masks from the live selection when
        none were applied yet. `sd_path`, `clip_path`: model paths (else env / workspace settings); `color`:
        the recolour target (else a colour named in the prompt).
        """
        self._need_scene()
        missing = self.capabilities()[guidance] if guidance in OPTIONAL else None
        if missing:
            raise FeatureUnavailable(missing)
        if registry.get(guidance).needs_prompt and not prompt.strip():
            raise UserError("the prompt is empty", hint="type what the selected region should become")
        # The viewport re-renders the live field as the preview: no snapshots.
        config = dataclasses.replace(config or RepaintConfig(), snapshot_every=0)
        if self.edit is not None:
            self.cancel()
        if self.masks is None:
            if self.selection is not None:
                self.masks_for_all_views(DEFAULT_THRESHOLD if threshold is None else threshold)
            else:
                try:
                    self.masks = load_masks(self.workspace.masks_dir)
                except WorkspaceError:
                    raise UserError("nothing is selected",
                                    hint="drag a rectangle over an object (Select patch), then press Repaint") from None
        self._save_reconstruction()
        self.edit = RepaintTrainer(self.scene, self.field, self.grid, workspace=self.workspace, masks=self.masks,
                                   guidance=guidance, prompt=prompt, bg_prompt=bg_prompt, config=config,
                                   device=self.device, sd_path=sd_path, clip_path=clip_path, color=color,
                                   trained_samples=self.sample_budget)
        self.stage1_frozen = True
        self.paused = False
        return {"started": time.time(), "guidance": self.edit.kind, "steps": int(self.edit.cfg.steps)}

    def _save_reconstruction(self) -> None:
        """Save the stage-1 field as a version when it trained since the last one, so undo returns to it."""
        if self.stage1_frozen and self.workspace.current_version is not None:
            return
        if self.workspace.current_version is None or self.trainer.step_count != self._saved_step:
            self.trainer.save_checkpoint()
            self.trainer.save_version("reconstruction" if self.workspace.original_version is None
                                      else f"reconstruction (step {self.trainer.step_count})")
            self._saved_step = self.trainer.step_count

    def cancel(self) -> None:
        """Stop the running edit and go back to the field as it was before it."""
        if self.edit is not None:
            self.edit.cancel()
            self.edit = None
            self._feature_cache = None
            self.stage1_frozen = any(v.kind == "edit" for v in self.workspace.versions)

    def undo(self) -> bool:
        """Go back one workspace version (a running edit is cancelled first); False when there is none."""
        return self._step_version(-1)

    def redo(self) -> bool:
        return self._step_version(+1)

    def _step_version(self, direction: int) -> bool:
        self._need_scene()
        self.cancel()
        ws = self.workspace
        info = ws.undo() if direction < 0 else ws.redo()
        if info is None:
            return False
        self.trainer.load_version(ws.version_path(info))
        self._feature_cache = None
        self.masks = None
        return True

    # ---- persistence and export
    def save(self) -> str:
        """Write the training checkpoint and the selection; the reconstruction becomes the first version."""
        self._need_scene()
        if self.edit is None:
            self.trainer.save_checkpoint()
        if self.workspace.original_version is None:
            self.trainer.save_version("reconstruction")
            self._saved_step = self.trainer.step_count
        if self.selection is not None and not self.selection.empty:
            self.selection.save(self.workspace)
        return str(self.workspace.root)

    def export_png(self, cameras, path: str | Path) -> str:
        """Write the full-resolution render of `cameras` as a PNG."""
        import cv2

        rgb = self.render(cameras, outputs=("rgb",), full=True)["rgb"]
        img = (np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8)
        path = Path(path)
        if not cv2.imwrite(str(path), img[..., ::-1]):
            raise UserError("cannot write the image", path, hint="choose a folder you can write to, ending in .png")
        return str(path)

    def _export_source(self):
        """The live field for core.export, with the selection's masks (live, else the saved ones)."""
        from repaint_nerf.core.export.source import from_engine

        self._need_scene()
        return from_engine(self)

    def _exporting(self, fn, *args, **kwargs):
        was_training = self.field.training
        self.field.eval()
        try:
            with torch.no_grad():
                return fn(*args, **kwargs)
        finally:
            self.field.train(was_training)

    def export_mesh(self, path: str | Path, selection: bool = False, resolution: int = 256,
                    cancel: Callable[[], bool] | None = None,
                    progress: Callable[[float, str], None] | None = None) -> dict:
        """Write a coloured marching-cubes mesh (.ply/.obj/.glb, world units) of the field or the selection."""
        from repaint_nerf.core.export.mesh import MeshOptions, export_mesh

        src = self._export_source()
        return self._exporting(export_mesh, src, path, MeshOptions(resolution=resolution, selection=selection),
                               masks=self.masks, cancel=cancel, progress=progress)

    def export_points(self, path: str | Path, selection: bool = False, cancel: Callable[[], bool] | None = None,
                      progress: Callable[[float, str], None] | None = None) -> dict:
        """Write the coloured surface points of the training views (.ply, world units)."""
        from repaint_nerf.core.export.points import export_points

        src = self._export_source()
        return self._exporting(export_points, src, path, selection, masks=self.masks, cancel=cancel,
                               progress=progress)

    def export_dataset(self, folder: str | Path, cancel: Callable[[], bool] | None = None,
                       progress: Callable[[float, str], None] | None = None) -> dict:
        """Write the current version's renders at the training cameras + transforms.json (nerfstudio layout)."""
        from repaint_nerf.core.export.dataset import export_dataset

        src = self._export_source()
        return self._exporting(export_dataset, src, folder, masks=True if self.masks is None else self.masks,
                               cancel=cancel, progress=progress)

    def export_camera_path(self, key_c2w: np.ndarray, key_fov, path: str | Path, frames: int, width: int,
                           height: int, fps: float = 30.0) -> str:
        """Save key views (field-space camera-to-world, vertical fov in degrees) interpolated into `frames` as a
        nerfstudio camera_path.json in world units."""
        from repaint_nerf.core.export.camera_path import CameraPath, interpolate, save_camera_path

        self._need_scene()
        c2w, fov = interpolate(key_c2w, key_fov, frames)
        world = c2w.copy()
        world[:, :3, 3] = self.scene.norm.to_world(c2w[:, :3, 3])
        keys = [{"camera_to_world": k.reshape(-1).tolist(), "fov": float(f)}
                for k, f in zip(self._keys_world(key_c2w), np.asarray(key_fov).reshape(-1))]
        return str(save_camera_path(CameraPath(world, fov, width, height, fps), path, keys))

    def _keys_world(self, key_c2w) -> np.ndarray:
        keys = np.array(key_c2w, dtype=np.float64).reshape(-1, 4, 4)
        keys[:, :3, 3] = self.scene.norm.to_world(keys[:, :3, 3])
        return keys

    def export_turntable(self, cameras_list: list, path: str | Path, fps: float = 24,
                         cancel: Callable[[], bool] | None = None,
                         progress: Callable[[float, str], None] | None = None) -> str:
        """Write the given cameras' renders as an H.264 .mp4 or a .gif (the editor passes an orbit around the
        target, or its recorded camera path); frames stream into the encoder, the file appears only when done."""
        from repaint_nerf.core.export.common import checkpoint
        from repaint_nerf.core.export.video import write_video

        if not cameras_list:
            raise UserError("no frames to write", path)

        def frames():
            for i, c in enumerate(cameras_list):
                checkpoint(cancel, progress, i / len(cameras_list), f"rendering frame {i + 1}/{len(cameras_list)}")
                yield self.render(c, outputs=("rgb",), full=True)["rgb"]

        return write_video(frames(), path, fps)["path"]
