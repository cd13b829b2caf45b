"""Monocular depth through a local ONNX model (MiDaS-style relative inverse depth), aligned per image
in scale and shift to the sparse depth (paper: "a rough depth of a monocular image" as supervision).
"""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from repaint_nerf.core.errors import UserError
from repaint_nerf.core.teachers._onnx import open_session, prepare_input, resize_map, resolve_model
from repaint_nerf.core.teachers.align import align_inverse_depth
from repaint_nerf.core.teachers.base import check_image
from repaint_nerf.core.teachers.depth import DenseDepth, DepthPriors, SparseDepth

ENV_DEPTH_MODEL = "REPAINT_NERF_DEPTH_MODEL"
FLAG = "--depth-model"
MIDAS_MEAN = (0.5, 0.5, 0.5)
MIDAS_STD = (0.5, 0.5, 0.5)


class OnnxDepthTeacher:
    """Relative depth from a local ONNX model. `inverse=True` (MiDaS, DPT): larger means nearer."""

    def __init__(self, path: str | Path | None = None, input_size: tuple[int, int] | None = (384, 384),
                 mean=MIDAS_MEAN, std=MIDAS_STD, output_name: str | None = None, inverse: bool = True,
                 multiple: int = 32):
        self.path = resolve_model(path, ENV_DEPTH_MODEL, FLAG, "depth")
        self.session = open_session(self.path, FLAG, ENV_DEPTH_MODEL, "depth")
        self.input_size = None if input_size is None else (int(input_size[0]), int(input_size[1]))
        self.mean, self.std, self.inverse, self.multiple = tuple(mean), tuple(std), bool(inverse), int(multiple)
        self.input_name = self.session.get_inputs()[0].name
        self.output_name = output_name or self.session.get_outputs()[0].name
        self.name = f"onnx-depth-{self.path.stem}"

    def config(self) -> dict:
        return {"path": str(self.path.resolve()), "size": self.path.stat().st_size, "input_size": self.input_size,
                "mean": list(self.mean), "std": list(self.std), "inverse": self.inverse}

    def __call__(self, image: np.ndarray) -> np.ndarray:
        """(H, W, 3) uint8 -> (H, W) float32 relative inverse depth (or relative depth if not inverse)."""
        rgb = check_image(image)
        x = prepare_input(rgb, self.input_size, self.mean, self.std, self.multiple)
        (out,) = self.session.run([self.output_name], {self.input_name: x})
        out = np.asarray(out, dtype=np.float32)
        out = out.reshape(out.shape[-2:]) if out.size == out.shape[-1] * out.shape[-2] else None
        if out is None:
            raise UserError("depth model output is not a single (h, w) map", self.path,
                            "export a model whose output is (1, h, w) or (1, 1, h, w)")
        return resize_map(out, rgb.shape[0], rgb.shape[1])


def aligned_monocular_depth(teacher, images: Sequence[np.ndarray], sparse: DepthPriors,
                            min_points: int = 8) -> DepthPriors:
    """Dense z-depth per image: the teacher's map (any depth teacher with `inverse` and `name`: ONNX or
    transformers) aligned in scale and shift to that image's sparse
    depth (in inverse depth when the teacher predicts inverse depth). Images with fewer than
    `min_points` sparse points keep their sparse prior instead.
    """
    out: list[SparseDepth | DenseDepth] = []
    for i, im in enumerate(images):
        sp = sparse.for_image(i)
        if not isinstance(sp, SparseDepth) or len(sp) < min_points:
            out.append(sp)
            continue
        rel = teacher(im)
        if not teacher.inverse:
            rel = 1.0 / np.maximum(rel, 1e-6)
        depth, valid, _ = align_inverse_depth(rel, sp.u, sp.v, sp.z)
        out.append(DenseDepth(depth, valid))
    return DepthPriors(out, sparse.sizes, source=f"{teacher.name}+{sparse.source}")
