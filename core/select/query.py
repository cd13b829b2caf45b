"""Query vectors: a patch (rectangle in a view) gives the mean rendered feature over it (paper, "Semantic
Mask Extraction": the patch's mean feature is the query); a text prompt gives one through a teacher
that has a CLIP-aligned text encoder.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import torch
from torch import Tensor

from repaint_nerf.core.errors import UserError


@dataclass(frozen=True)
class Patch:
    """A pixel rectangle [x0, x1) x [y0, y1) in training view `view`; `positive=False` subtracts it."""

    view: int
    x0: int
    y0: int
    x1: int
    y1: int
    positive: bool = True

    @staticmethod
    def parse(text: str, view: int, positive: bool = True) -> "Patch":
        """'x0,y0,x1,y1' (pixels, x1/y1 exclusive) -> Patch; malformed text is a UserError."""
        parts = [p.strip() for p in str(text).split(",")]
        try:
            x0, y0, x1, y1 = (int(round(float(p))) for p in parts)
        except ValueError:
            raise UserError(f"patch '{text}' is not four numbers x0,y0,x1,y1",
                            hint="give pixel corners, e.g. --patch 40,30,60,50") from None
        return Patch(int(view), x0, y0, x1, y1, positive)

    @staticmethod
    def from_normalized(rect, view: int, width: int, height: int, positive: bool = True) -> "Patch":
        """A rectangle (x0, y0, x1, y1) in [0, 1] image fractions (the editor's drag) -> pixels, at least 1x1."""
        x0, y0, x1, y1 = (float(v) for v in rect)
        x0, x1 = sorted((x0, x1))
        y0, y1 = sorted((y0, y1))
        px0, py0 = int(np.floor(x0 * width)), int(np.floor(y0 * height))
        px1, py1 = max(px0 + 1, int(np.ceil(x1 * width))), max(py0 + 1, int(np.ceil(y1 * height)))
        return Patch(int(view), px0, py0, px1, py1, positive)

    def check(self, width: int, height: int) -> "Patch":
        """Raise a UserError unless the patch is non-empty and inside a width x height image."""
        if self.x1 <= self.x0 or self.y1 <= self.y0:
            raise UserError(f"patch {self.x0},{self.y0},{self.x1},{self.y1} is empty",
                            hint="x1 must be greater than x0 and y1 greater than y0 (x1, y1 exclusive)")
        if self.x0 < 0 or self.y0 < 0 or self.x1 > width or self.y1 > height:
            raise UserError(f"patch {self.x0},{self.y0},{self.x1},{self.y1} lies outside view {self.view}, "
                            f"which is {width}x{height} pixels",
                            hint=f"keep 0 <= x0 < x1 <= {width} and 0 <= y0 < y1 <= {height}")
        return self

    def to_dict(self) -> dict:
        return asdict(self)

    @staticmethod
    def from_dict(d: dict) -> "Patch":
        return Patch(int(d["view"]), int(d["x0"]), int(d["y0"]), int(d["x1"]), int(d["y1"]),
                     bool(d.get("positive", True)))


def patch_query(features: Tensor, patch: Patch) -> Tensor:
    """The query of a patch: the mean rendered feature (F,) over its pixels of a (H, W, F) feature map."""
    h, w = int(features.shape[0]), int(features.shape[1])
    patch.check(w, h)
    region = torch.as_tensor(features)[patch.y0:patch.y1, patch.x0:patch.x1]
    return region.reshape(-1, region.shape[-1]).float().mean(0)


def text_query(text: str, teacher, codec=None) -> Tensor:
    """The query of a text prompt: the teacher's text embedding, projected into the field's feature codes
    when the features were compressed (`codec.encode`, e.g. the cache's PCA basis)."""
    if not str(text).strip():
        raise UserError("the text query is empty", hint="type what to select, e.g. 'a red ball'")
    encode = getattr(teacher, "encode_text", None)
    if encode is None:
        name = getattr(teacher, "name", type(teacher).__name__)
        raise UserError(f"the feature teacher '{name}' has no text encoder, so it cannot select by text",
                        hint="select with a patch, or train with a CLIP-aligned teacher (e.g. an LSeg ONNX "
                             "export with its text encoder)")
    emb = np.asarray(encode(str(text)), dtype=np.float32).reshape(-1)
    if codec is not None:
        emb = np.asarray(codec.encode(emb[None, None, :]), dtype=np.float32).reshape(-1)
    return torch.from_numpy(emb)
