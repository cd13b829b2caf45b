"""A small trained workspace for the workspace-repair tests and the editor's repair offer: a reconstruction and
two edits of a tiny field, a selection with its masks, teacher caches, and another workspace to take foreign
files from."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch

from repaint_nerf.core.workspace.workspace import Workspace


@dataclass
class Base:
    """A small trained workspace: a reconstruction and two edits, a selection with masks, teacher caches."""

    root: Path
    scene: object
    trainer: object
    masks: list
    other: Path  # another workspace with versions of its own (the source of foreign files)


def _tiny_field():
    from repaint_nerf.core.field.field import FieldConfig

    return FieldConfig(levels=4, log2_table=10, base_res=8, finest_res=64, hidden=16, geo_feat_dim=7, sh_degree=2,
                       feature_dim=4, feature_levels=2, feature_log2_table=10, feature_hidden=8,
                       encoding_impl="indexed", compile=False)


def _edit(base_scene, trainer, ws, masks, prompt: str) -> None:
    from repaint_nerf.core.repaint.trainer import RepaintTrainer

    RepaintTrainer(base_scene, trainer.field, trainer.grid, workspace=ws, masks=masks, guidance="recolor",
                   prompt=prompt, steps=2, resolution=16, max_samples=32, snapshot_every=0,
                   region_resolution=16).run()


def small_workspace(path: Path, root: Path) -> Base:
    """Train and save it at `root` on the scene at `path` (a few seconds on one core)."""
    from repaint_nerf.core.scene.loaders.detect import load_scene
    from repaint_nerf.core.select.masks import ViewCache, masks_for_views
    from repaint_nerf.core.select.query import Patch
    from repaint_nerf.core.select.selection import Selection
    from repaint_nerf.core.teachers.stage1_targets import depth_priors, feature_targets
    from repaint_nerf.core.train.stage1 import Stage1Trainer, TrainConfig

    ws = Workspace.create(root, {"scene": str(path), "downscale": 1.0})
    scene = load_scene(path, 1.0, workspace=root)
    cfg = TrainConfig(rays_per_batch=64, grid_resolution=16, max_samples=32, grid_warmup_steps=2)
    trainer = Stage1Trainer(scene, ws, cfg, _tiny_field(), device="cpu",
                            feature_targets=feature_targets(scene, ws, dims=4), depth_priors=depth_priors(scene, ws))
    trainer.train(steps=3)
    trainer.save_checkpoint()
    trainer.save_version("reconstruction")
    cams = scene.field_cameras("train")
    cache = ViewCache(trainer.field, trainer.grid, cams)
    sel = Selection(threshold=0.5, cleanup=False, teacher="default")
    sel.add_patch(cache.get(0).feature, Patch(0, 4, 4, 12, 12))
    with torch.no_grad():
        masks = masks_for_views(trainer.field, trainer.grid, cams, sel, workspace=ws, cache=cache,
                                names=list(scene.train.names), images=scene.train.images)
    sel.save(ws)
    for prompt in ("a blue box", "a red box"):
        _edit(scene, trainer, ws, masks, prompt)
    other = Workspace.create(root.parent / "other", {"scene": str(path)})
    for name in ("theirs", "theirs too"):
        other.save_version(name, trainer.checkpoint(), kind="stage1")
    return Base(root, scene, trainer, masks, other.root)
