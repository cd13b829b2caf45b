"""Feature maps to RGB for display: a 3-component PCA fitted once per scene so colours stay stable."""
from __future__ import annotations

import numpy as np


class FeatureProjector:
    """Projects (H, W, F) feature maps on the principal axes of the first map it sees."""

    def __init__(self, max_fit_pixels: int = 4096, seed: int = 0):
        self.mean: np.ndarray | None = None
        self.axes: np.ndarray | None = None  # (F, 3)
        self.max_fit_pixels = max_fit_pixels
        self.rng = np.random.default_rng(seed)

    def reset(self) -> None:
        self.mean = self.axes = None

    def __call__(self, feature: np.ndarray) -> np.ndarray:
        """(H, W, F) float -> (H, W, 3) float32 projections (the shader rescales them to colours)."""
        h, w, f = feature.shape
        flat = feature.reshape(-1, f).astype(np.float64)
        if self.axes is None or self.axes.shape[0] != f:
            pick = flat[self.rng.choice(len(flat), min(len(flat), self.max_fit_pixels), replace=False)]
            self.mean = pick.mean(axis=0)
            _, _, vt = np.linalg.svd(pick - self.mean, full_matrices=False)
            axes = np.zeros((f, 3))
            axes[:, :min(3, vt.shape[0])] = vt[:3].T
            self.axes = axes
        return ((flat - self.mean) @ self.axes).reshape(h, w, 3).astype(np.float32)
