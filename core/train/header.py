"""The checkpoint header schema: what a stage-1 checkpoint or a workspace version says about itself.

Both trainers write a `CheckpointHeader` and every reader (engine, commands, benchmarks) reads one, so the
JSON keys live only here. Each file records its format version; `from_dict` reads every older version
(upgrading it in memory) and rejects newer ones with a WorkspaceError. History:
  1: kind, step, train_seconds, field_config, train_config, grid, optim, budget, scene, edit
  2: + history (the stage-1 loss/PSNR curve, so a reopened workspace plots its past);
     + optional march.fog_cleared_step (older readers ignore it; files without it ramped from step 0)
"""
from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from repaint_nerf.core.errors import WorkspaceError
from repaint_nerf.core.train.history import TrainingHistory

FORMAT_VERSION = 2
READABLE_FORMATS = (1, 2)
HEADER_KEY = "repaint_nerf"  # the safetensors metadata entry that holds the header JSON
STAGE1, EDIT = "stage1", "edit"
DAMAGED_HINT = "the file is damaged or from another program version: delete it and train again"


@dataclass
class GridFacts:
    """The occupancy grid's shape and its non-tensor state (the tensors sit in the file under 'grid.')."""

    resolution: int
    cascades: int = 1
    bound: float = 1.0
    state: dict = field(default_factory=dict)


@dataclass
class SceneFacts:
    """What a checkpoint records about its scene, to reload it as trained and map depths back to world units."""

    root: str
    format: str = ""
    kind: str | None = None
    norm: dict | None = None  # core.scene.scene.Normalization.to_dict()
    background: list[float] | None = None

    @staticmethod
    def of(scene) -> "SceneFacts":
        return SceneFacts(root=str(scene.root), format=scene.format, kind=scene.kind, norm=scene.norm.to_dict(),
                          background=None if scene.background is None else [float(c) for c in scene.background])

    def normalization(self):
        """The world -> field transform the field was trained in (None when not recorded)."""
        from repaint_nerf.core.scene.scene import Normalization

        return Normalization.from_dict(self.norm) if self.norm else None


@dataclass
class EditFacts:
    """How an edit version was made (paper stage 2)."""

    guidance: str
    prompt: str = ""
    bg_prompt: str = ""
    steps: int = 0
    skipped_steps: int = 0
    config: dict = field(default_factory=dict)


@dataclass
class CheckpointHeader:
    """The JSON header of a checkpoint or version file (see the module docstring for its versions)."""

    kind: str  # STAGE1 (a reconstruction or its training state) or EDIT
    field_config: dict  # core.field.field.FieldConfig as a dict
    grid: GridFacts
    scene: SceneFacts | None = None
    step: int = 0
    train_seconds: float = 0.0
    train_config: dict | None = None  # core.train.stage1.TrainConfig as a dict (stage 1)
    optim: dict | None = None  # optimiser param groups and scalars (stage 1; tensors under 'optim.')
    budget_steps: int | None = None
    budget_seconds: float | None = None
    edit: EditFacts | None = None
    history: TrainingHistory = field(default_factory=TrainingHistory)
    # the step stage 1's fog cleared (Stage1Trainer.fog_cleared_step; None = not yet); -1 = not recorded (a file
    # from before it was: its march ramp started at step 0)
    fog_cleared_step: int | None = -1
    format: int = FORMAT_VERSION

    @property
    def march_start(self) -> int | None:
        """The fog-cleared step to resume with (0 for files that did not record it: they ramped from step 0)."""
        return 0 if self.fog_cleared_step == -1 else self.fog_cleared_step

    def field_cfg(self):
        """The FieldConfig the field was built with (unknown keys from newer versions ignored)."""
        from repaint_nerf.core.field.field import FieldConfig

        return FieldConfig.from_dict(self.field_config)

    def train_cfg(self):
        """The stage-1 TrainConfig it trained with, or None (an edit, or not recorded)."""
        if not self.train_config:
            return None
        from repaint_nerf.core.train.stage1 import TrainConfig  # stage1 writes headers: imported when read

        return TrainConfig.from_dict(self.train_config)

    @property
    def feature_dim(self) -> int:
        return int(self.field_config.get("feature_dim", 0) or 0)

    @property
    def trained_samples(self) -> int | None:
        """The full sample budget (steps across the cube's diagonal) stage 1 trained the field with, or an edit
        version's edit marched at; None when not recorded."""
        recorded = (self.edit.config if self.edit is not None else {}) if self.kind == EDIT else \
            (self.train_config or {})
        value = recorded.get("max_samples")
        return int(value) if value and int(value) > 0 else None

    @property
    def max_samples(self) -> int:
        """The sample budget it was trained with at its step (1024, the renderer's default, when not recorded);
        early stage-1 steps march coarser (stage1.march_budget)."""
        tc = self.train_config or {}
        full = self.trained_samples or 1024
        if self.kind != STAGE1 or not tc.get("early_max_samples"):
            return full
        from repaint_nerf.core.train.stage1 import march_budget

        return march_budget(self.step, full, int(tc["early_max_samples"]), int(tc.get("grid_warmup_steps", 256)),
                            self.march_start)

    def to_dict(self) -> dict[str, Any]:
        d = {"format": FORMAT_VERSION, "kind": self.kind, "step": int(self.step),
             "train_seconds": float(self.train_seconds), "field_config": self.field_config,
             "grid": dataclasses.asdict(self.grid),
             "scene": None if self.scene is None else dataclasses.asdict(self.scene),
             "budget": {"steps": self.budget_steps, "seconds": self.budget_seconds},
             "history": self.history.to_dict()}
        if self.kind == STAGE1 and self.fog_cleared_step != -1:
            d["march"] = {"fog_cleared_step": self.fog_cleared_step}
        if self.train_config is not None:
            d["train_config"] = self.train_config
        if self.optim is not None:
            d["optim"] = self.optim
        if self.edit is not None:
            d["edit"] = dataclasses.asdict(self.edit)
        json.dumps(d)  # fail on save, not on load, if anything is not JSON
        return d

    @staticmethod
    def from_dict(d: dict, where: str | Path | None = None) -> "CheckpointHeader":
        """Read a header of any readable format; another version or a malformed one is a WorkspaceError."""
        fmt = check_format(d.get("format") if isinstance(d, dict) else None, where)
        try:
            budget = d.get("budget") or {}
            scene = d.get("scene")
            edit = d.get("edit")
            return CheckpointHeader(
                kind=str(d.get("kind", STAGE1)), field_config=dict(d["field_config"]), grid=GridFacts(**d["grid"]),
                scene=None if not scene else SceneFacts(**scene), step=int(d.get("step", 0)),
                train_seconds=float(d.get("train_seconds", 0.0)), train_config=d.get("train_config"),
                optim=d.get("optim"), budget_steps=budget.get("steps"), budget_seconds=budget.get("seconds"),
                edit=None if not edit else EditFacts(**edit),
                history=TrainingHistory.from_dict(d.get("history")),  # format 1 had none
                fog_cleared_step=(d.get("march") or {}).get("fog_cleared_step", -1),
                format=fmt)
        except (KeyError, TypeError, ValueError) as exc:
            raise WorkspaceError(f"the checkpoint header is malformed ({exc.__class__.__name__}: {exc})", where,
                                 hint=DAMAGED_HINT) from exc


def check_format(fmt: Any, where: str | Path | None = None) -> int:
    """`fmt` when this program reads that format version, else a WorkspaceError naming the file."""
    if fmt not in READABLE_FORMATS:
        raise WorkspaceError(f"checkpoint format version {fmt!r}; this program reads versions "
                             f"{', '.join(map(str, READABLE_FORMATS))}", where, hint=DAMAGED_HINT)
    return int(fmt)
