"""A tiny scene for repaint tests whose images are rendered from a known voxel field (so the field fits them
exactly, no stage-1 training needed): a red ball on a grey checker slab, 6 views on a ring, white background.

`VoxelField` has NGPField's interface (density, forward, parameter_groups, cfg) on dense trilinear grids,
fast enough on a shared CPU for edit tests to run hundreds of whole-view steps in seconds.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from repaint_nerf.core.render.occupancy import OccupancyGrid
from repaint_nerf.core.render.renderer import RenderOptions, render_camera
from repaint_nerf.core.scene.cameras import Cameras, look_at
from repaint_nerf.core.scene.scene import Normalization, Scene, SceneSplit

BALL_RGB = (0.85, 0.12, 0.10)
BG = (1.0, 1.0, 1.0)


@dataclass
class VoxelConfig:
    res: int = 24
    bound: float = 1.0


class VoxelField(torch.nn.Module):
    """sigma = 40 softplus(density logits), rgb = sigmoid(colour logits), trilinear on res^3 grids."""

    def __init__(self, cfg: VoxelConfig | None = None):
        super().__init__()
        self.cfg = cfg or VoxelConfig()
        r = self.cfg.res
        self.dens = torch.nn.Parameter(torch.full((1, 1, r, r, r), -8.0))
        self.col = torch.nn.Parameter(torch.zeros(1, 3, r, r, r))

    def _sample(self, g: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        p = (x / self.cfg.bound).flip(-1)[None, None, None]  # grid_sample wants (x=W, y=H, z=D) = (k, j, i)
        return F.grid_sample(g, p, align_corners=True).reshape(g.shape[1], -1).T

    def density(self, x: torch.Tensor) -> torch.Tensor:
        inside = (x.abs().amax(-1) <= self.cfg.bound).to(x.dtype)
        return 40.0 * F.softplus(self._sample(self.dens, x)[:, 0]) * inside

    def forward(self, x, d=None, outputs=("rgb",)) -> dict:
        out = {"sigma": self.density(x)}
        if "rgb" in outputs:
            out["rgb"] = torch.sigmoid(self._sample(self.col, x))
        return out

    def parameter_groups(self) -> dict:
        return {"grid": [self.dens, self.col], "mlp": [], "feature": []}


def _coords(r: int) -> torch.Tensor:
    ax = torch.linspace(-1, 1, r)
    return torch.stack(torch.meshgrid(ax, ax, ax, indexing="ij"), -1)


def _logit(c):
    c = torch.as_tensor(c, dtype=torch.float32).clamp(1e-3, 1 - 1e-3)
    return torch.log(c / (1 - c))


def make_field(with_ball: bool = True, with_slab: bool = True, ball_rgb=BALL_RGB) -> VoxelField:
    """The scene's field: ball of radius 0.35 at the origin, slab z in [-0.75, -0.4] (checker grey)."""
    f = VoxelField()
    x = _coords(f.cfg.res)
    ball = x.norm(dim=-1) <= 0.35
    slab = (x[..., 2] >= -0.75) & (x[..., 2] <= -0.4) & (x[..., :2].abs().amax(-1) <= 0.85)
    occ = torch.zeros_like(ball)
    col = torch.zeros(3, *ball.shape)
    if with_slab:
        occ |= slab
        checker = ((torch.floor(x[..., 0] * 3) + torch.floor(x[..., 1] * 3)) % 2 == 0)
        grey = torch.where(checker, 0.75, 0.35)
        for c in range(3):
            col[c] = torch.where(slab, _logit(grey), col[c])
    if with_ball:
        occ |= ball
        for c in range(3):
            col[c] = torch.where(ball, _logit(ball_rgb[c]), col[c])
    with torch.no_grad():
        f.dens.copy_(torch.where(occ, 2.0, -8.0)[None, None])
        f.col.copy_(col[None])
    return f


def make_grid(field) -> OccupancyGrid:
    g = OccupancyGrid(32, bound=1.0, device="cpu")
    g.update(0, field.density)
    return g


def make_cameras(n: int = 6, size: int = 16) -> Cameras:
    poses = [look_at((2.6 * math.cos(a), 2.6 * math.sin(a), 1.5), (0, 0, -0.2))
             for a in np.linspace(0, 2 * math.pi, n, endpoint=False)]
    f = 0.5 * size / math.tan(math.radians(24))
    return Cameras.create(np.stack(poses), f, f, size / 2, size / 2, size, size)


@torch.no_grad()
def render_images(field, cams: Cameras, outputs=("rgb",)) -> list[dict]:
    grid = make_grid(field)
    opts = RenderOptions(outputs=outputs, background=torch.tensor(BG), max_samples=256)
    return [render_camera(field, grid, cams, i, opts) for i in range(len(cams))]


def to_uint8(rgb: torch.Tensor) -> np.ndarray:
    return (rgb.clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8)


def make_scene(root: Path | None = None, n: int = 6, size: int = 16, edited_rgb=None):
    """(scene, masks): images rendered from `make_field()`; masks = pixels the ball covers (opacity > 0.5).

    With `edited_rgb` and `root`, also writes root/edited/ (the ball in that colour) for the analytic guidance.
    """
    cams = make_cameras(n, size)
    field = make_field()
    images = [to_uint8(o["rgb"]) for o in render_images(field, cams)]
    ball = render_images(make_field(with_slab=False), cams, ("rgb", "opacity"))
    masks = [(o["opacity"] > 0.5).numpy() for o in ball]
    root = Path(root) if root is not None else Path("/nonexistent-repaint-test-scene")
    names = [f"r_{i}" for i in range(n)]
    paths = [root / "train" / f"{nm}.png" for nm in names]
    if edited_rgb is not None:
        import cv2

        ed = [to_uint8(o["rgb"]) for o in render_images(make_field(ball_rgb=edited_rgb), cams)]
        (root / "edited" / "train").mkdir(parents=True, exist_ok=True)
        (root / "edited" / "transforms_train.json").write_text("{}")
        for nm, im in zip(names, ed):
            cv2.imwrite(str(root / "edited" / "train" / f"{nm}.png"), im[..., ::-1])
    split = SceneSplit(cams, images, names, paths)
    scene = Scene(root=root, format="blender", splits={"train": split, "test": split}, norm=Normalization(),
                  background=BG)
    return scene, masks
