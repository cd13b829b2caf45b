"""Teachers combined: the unit features of several teachers concatenated, each scaled by the square root of
its weight, then L2-normalised. The cosine of two pixels is then the weight-averaged cosine of the parts
(sum of weights 1), so an ImageNet network's "what it is" and the built-in teacher's colour can both
vote on one mask.
"""
from __future__ import annotations

import numpy as np

from repaint_nerf.core.teachers.base import FeatureTeacher, check_image, l2_normalize


class BlendFeatureTeacher:
    """Concatenated unit features of `parts` [(teacher, weight), ...]; named '<a>+<b>'."""

    def __init__(self, parts: list[tuple[FeatureTeacher, float]]):
        if len(parts) < 2 or any(w <= 0 for _, w in parts):
            raise ValueError("a blend needs at least two teachers with positive weights")
        total = float(sum(w for _, w in parts))
        self.parts = [(t, float(w) / total) for t, w in parts]
        self.name = "+".join(t.name for t, _ in self.parts)

    def config(self) -> dict:
        return {"parts": [{"name": t.name, "weight": w, "config": t.config()} for t, w in self.parts]}

    @property
    def dim(self) -> int:
        return int(sum(getattr(t, "dim", 0) for t, _ in self.parts))

    def __call__(self, image: np.ndarray) -> np.ndarray:
        """(H, W, 3) uint8 -> (H, W, sum of dims) float32, unit length per pixel."""
        rgb = check_image(image)
        feats = [t(rgb) for t, _ in self.parts]  # each unit per pixel (the protocol): no normalising again
        out = np.empty(feats[0].shape[:2] + (sum(f.shape[2] for f in feats),), np.float32)
        at = 0
        for f, (_, w) in zip(feats, self.parts):
            np.multiply(f, np.float32(np.sqrt(w)), out=out[..., at:at + f.shape[2]])
            at += f.shape[2]
        return l2_normalize(out)  # a part's zero vector leaves the rest short of unit length

    def prepare(self, image: np.ndarray):
        """The features as the feature cache reads them (core.teachers.projected), each part prepared its way."""
        from repaint_nerf.core.teachers.projected import Blended, prepared

        rgb = check_image(image)
        return Blended([(float(np.sqrt(w)), prepared(t, rgb)) for t, w in self.parts])
