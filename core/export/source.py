"""What an export reads: a field with its occupancy grid, the scene (cameras, world <-> field transform) and the
workspace (saved masks), taken from a workspace's current version (command line) or from the live engine (editor)."""
from __future__ import annotations

from dataclasses import dataclass, field as dc_field
from pathlib import Path

import torch


@dataclass
class ExportSource:
    """A field ready to query in field space, and what maps it to the scene's world units."""

    field: torch.nn.Module
    grid: object  # core.render.occupancy.OccupancyGrid or None
    scene: object  # core.scene.scene.Scene
    workspace: object = None  # core.workspace.workspace.Workspace, for the saved selection masks
    max_samples: int = 1024  # the renderer's steps across the cube, as the field was trained
    _maps: dict = dc_field(default_factory=dict, repr=False)  # view -> (z-depth, opacity), rendered once

    @property
    def device(self) -> torch.device:
        return next(self.field.parameters()).device

    def background(self) -> tuple[float, float, float]:
        return tuple(self.scene.background or (1.0, 1.0, 1.0))

    def render_options(self, outputs: tuple, background=None):
        """Deterministic render options at the trained sample budget (background None = black, i.e. none)."""
        from repaint_nerf.core.render.renderer import RenderOptions

        bg = None if background is None else torch.as_tensor(background, dtype=torch.float32, device=self.device)
        return RenderOptions(outputs=outputs, background=bg, perturb=False, max_samples=self.max_samples)


    def train_views(self, at_most: int) -> list[int]:
        """Up to `at_most` training views spread evenly over the capture (renders cost seconds each on a CPU)."""
        from repaint_nerf.core.train.stage1 import spread_views

        return spread_views(len(self.scene.train) if "train" in self.scene.splits else 0, at_most)

    @torch.no_grad()
    def depth_opacity(self, view: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Rendered z-depth and opacity (H, W) of a training view, on the CPU; cached for this export."""
        if view not in self._maps:
            from repaint_nerf.core.render.renderer import render_camera

            cams = self.scene.field_cameras("train").to(self.device)
            out = render_camera(self.field, self.grid, cams, int(view), self.render_options(("depth", "opacity")))
            self._maps[view] = (out["depth"].float().cpu(), out["opacity"].float().cpu())
        return self._maps[view]


def open_workspace(path: str | Path, device: str | None = None) -> ExportSource:
    """The current version of a trained workspace (else its stage-1 checkpoint) with its scene."""
    from repaint_nerf.core.session import open_trained

    t = open_trained(path, device)
    return ExportSource(t.field, t.grid, t.scene, t.workspace, t.header.max_samples)


def from_engine(engine) -> ExportSource:
    """The engine's live field (the editor exports what it shows)."""
    return ExportSource(engine.field, engine.grid, engine.scene, engine.workspace,
                        int(getattr(engine.trainer.cfg, "max_samples", 1024)))
