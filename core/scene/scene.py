"""What every loader returns: cameras in one convention, images, optional points, bounds and the
world-to-field transform. Field space is the cube [-1, 1]^3 (bounded scenes); see `normalize.py`.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from repaint_nerf.core.scene.cameras import Cameras

SCENE_KINDS = ("bounded", "forward", "unbounded")


@dataclass
class Normalization:
    """Similarity transform world -> field: x_field = scale * (x_world - center).

    Renders and exports use `to_world` to report depths and positions in the dataset's own units.
    """

    center: np.ndarray = field(default_factory=lambda: np.zeros(3))
    scale: float = 1.0

    def to_field(self, x):
        return (x - torch.as_tensor(self.center, dtype=x.dtype, device=x.device)) * self.scale \
            if isinstance(x, torch.Tensor) else (np.asarray(x) - self.center) * self.scale

    def to_world(self, x):
        return x / self.scale + (torch.as_tensor(self.center, dtype=x.dtype, device=x.device)
                                 if isinstance(x, torch.Tensor) else self.center)

    def poses_to_field(self, c2w: torch.Tensor) -> torch.Tensor:
        """Camera-to-world poses expressed in field space (rotation unchanged, centre moved and scaled)."""
        out = c2w.clone()
        out[..., :3, 3] = self.to_field(c2w[..., :3, 3])
        return out

    def cameras_to_field(self, cams: Cameras) -> Cameras:
        """`cams` (world units) with their poses in field space: what the renderer and trainer use."""
        return cams.with_poses(self.poses_to_field(cams.c2w))

    def to_dict(self) -> dict:
        return {"center": [float(c) for c in self.center], "scale": float(self.scale)}

    @staticmethod
    def from_dict(d: dict) -> "Normalization":
        return Normalization(np.asarray(d["center"], dtype=np.float64), float(d["scale"]))


@dataclass
class SceneSplit:
    """One split (train / val / test) of a scene: cameras in world units and their images."""

    cameras: Cameras
    images: list[np.ndarray]  # each (H, W, 3|4) uint8, RGB(A); sizes match cameras.width/height
    names: list[str]
    paths: list[Path] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.images)

    @property
    def has_alpha(self) -> bool:
        """Its images are RGBA (a loader keeps one channel count per split, so the first one tells)."""
        shape = np.shape(self.images[0]) if self.images else ()
        return len(shape) == 3 and shape[2] == 4


@dataclass
class Scene:
    """A loaded scene. Camera poses in `splits` are in world units; `norm` maps them into field space."""

    root: Path
    format: str  # "blender", "nerfstudio", "llff", "colmap", "photos"
    splits: dict[str, SceneSplit]
    norm: Normalization = field(default_factory=Normalization)
    kind: str = "bounded"  # one of SCENE_KINDS
    background: tuple[float, float, float] | None = None  # composite colour for RGBA images, None = random in training
    near: float = 0.0  # world units along the ray
    far: float = 1e10
    points: np.ndarray | None = None  # (M, 3) float world-space sparse points (SfM), if any
    point_colors: np.ndarray | None = None  # (M, 3) uint8
    extra: dict = field(default_factory=dict)  # loader-specific facts (e.g. the LLFF bounds, the SfM report)

    @property
    def train(self) -> SceneSplit:
        return self.splits["train"]

    def split(self, name: str) -> SceneSplit:
        """The named split; a missing test split falls back to train, which the caller may note."""
        if name in self.splits:
            return self.splits[name]
        from repaint_nerf.core.errors import SceneError

        raise SceneError(f"this scene has no '{name}' split (it has: {', '.join(self.splits)})", self.root)

    def field_cameras(self, split: str = "train") -> Cameras:
        """Cameras of a split with poses moved into field space (what the renderer and trainer use)."""
        return self.norm.cameras_to_field(self.split(split).cameras)
