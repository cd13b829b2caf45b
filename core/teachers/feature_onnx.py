"""ONNX feature teacher: any image -> feature-map network a user exports (LSeg, CLIP-dense, DINO),
run through onnxruntime, its (1, D, h, w) output resized to the image (bilinear) and L2-normalised.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from repaint_nerf.core.errors import UserError
from repaint_nerf.core.teachers._onnx import open_session, prepare_input, resize_map, resolve_model
from repaint_nerf.core.teachers.base import check_image, l2_normalize

ENV_FEATURE_MODEL = "REPAINT_NERF_FEATURE_MODEL"
FLAG = "--feature-model"
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


class OnnxFeatureTeacher:
    """Dense features from a local ONNX model; `input_size=None` feeds the image at native size."""

    def __init__(self, path: str | Path | None = None, input_size: tuple[int, int] | None = None,
                 mean=IMAGENET_MEAN, std=IMAGENET_STD, output_name: str | None = None, multiple: int = 1):
        self.path = resolve_model(path, ENV_FEATURE_MODEL, FLAG, "feature")
        self.session = open_session(self.path, FLAG, ENV_FEATURE_MODEL, "feature")
        self.input_size = None if input_size is None else (int(input_size[0]), int(input_size[1]))
        self.mean, self.std = tuple(float(m) for m in mean), tuple(float(s) for s in std)
        self.multiple = int(multiple)
        self.input_name = self.session.get_inputs()[0].name
        names = [o.name for o in self.session.get_outputs()]
        if output_name is not None and output_name not in names:
            raise UserError(f"model has no output '{output_name}' (outputs: {', '.join(names)})", self.path,
                            "pick one of the listed output names")
        self.output_name = output_name or names[0]
        self.name = f"onnx-{self.path.stem}"

    def config(self) -> dict:
        st = self.path.stat()
        return {"path": str(self.path.resolve()), "size": st.st_size, "mtime": int(st.st_mtime),
                "input_size": self.input_size, "mean": self.mean, "std": self.std,
                "output": self.output_name, "multiple": self.multiple}

    def __call__(self, image: np.ndarray) -> np.ndarray:
        """(H, W, 3) uint8 -> (H, W, D) float32 unit vectors."""
        rgb = check_image(image)
        x = prepare_input(rgb, self.input_size, self.mean, self.std, self.multiple)
        (out,) = self.session.run([self.output_name], {self.input_name: x})
        out = np.asarray(out, dtype=np.float32)
        if out.ndim != 4 or out.shape[0] != 1:
            raise UserError(f"feature model output '{self.output_name}' has shape {out.shape}; expected (1, D, h, w)",
                            self.path, "export the model so its output is a (1, D, h, w) feature map")
        fmap = resize_map(out[0].transpose(1, 2, 0), rgb.shape[0], rgb.shape[1])
        return l2_normalize(fmap)
