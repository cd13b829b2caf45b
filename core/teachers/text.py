"""Text queries through a CLIP-aligned feature teacher: an ONNX teacher whose features live in a CLIP
model's text space (LSeg's live in CLIP ViT-B/32's) paired with that CLIP model's text encoder, or a CLIP
model alone as the teacher (MaskCLIP features, core/teachers/feature_hf.py) with its own text encoder, so a
prompt's embedding can be compared with the features the field learned (paper: a text query instead of
a patch, through the teacher's text encoder).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from repaint_nerf.core.errors import UserError

HINT = ("text selection needs a CLIP-aligned feature teacher: a CLIP model folder or cached id (trained with "
        "--feature-model; MaskCLIP features), or an LSeg ONNX export (--feature-model) plus the CLIP model of its "
        "feature space (--clip-path or REPAINT_NERF_CLIP_PATH); otherwise select with a patch")


class TextAlignedTeacher:
    """A feature teacher with a CLIP text encoder of the same space: `encode_text` gives a (D,) unit vector."""

    def __init__(self, teacher, clip):
        dim, proj = teacher_feature_dim(teacher), clip_text_dim(clip)
        if dim != proj:
            raise UserError(f"the feature teacher '{teacher.name}' gives {dim}-dim features but the CLIP model's "
                            f"text embeddings have {proj} dims, so they are not one space", hint=HINT)
        self.teacher, self.clip, self.name, self.dim = teacher, clip, teacher.name, dim

    def config(self) -> dict:
        return self.teacher.config()

    def __call__(self, image: np.ndarray) -> np.ndarray:
        """The wrapped teacher's features (H, W, D)."""
        return self.teacher(image)

    def encode_text(self, text: str) -> np.ndarray:
        """A prompt's CLIP text embedding as a (D,) float32 unit vector (the space of the teacher's features)."""
        emb = self.clip.encode_text([str(text)])[0].detach().float().cpu().numpy()
        return (emb / max(float(np.linalg.norm(emb)), 1e-12)).astype(np.float32)


def teacher_feature_dim(teacher) -> int:
    """D of a CLIP-aligned teacher: a MaskCLIP teacher's projection dim, else an ONNX teacher's (1, D, h, w)
    output from the model's declared shape (else one tiny run)."""
    from repaint_nerf.core.teachers.feature_onnx import OnnxFeatureTeacher

    if getattr(teacher, "clip", None) is not None:
        return int(teacher.dim)
    if not isinstance(teacher, OnnxFeatureTeacher):
        raise UserError(f"the feature teacher '{getattr(teacher, 'name', type(teacher).__name__)}' is not "
                        "CLIP-aligned, so it cannot select by text", hint=HINT)
    out = next(o for o in teacher.session.get_outputs() if o.name == teacher.output_name)
    if len(out.shape) == 4 and isinstance(out.shape[1], int):
        return int(out.shape[1])
    return int(teacher(np.full((32, 32, 3), 128, np.uint8)).shape[-1])


def clip_text_dim(clip) -> int:
    """The dimension of a CLIP model's projected text embeddings."""
    return int(clip.model.config.projection_dim)


def text_teacher(teacher, clip_path: str | Path | None = None, settings: dict | None = None) -> TextAlignedTeacher:
    """`teacher` paired with the CLIP model at `clip_path` (else $REPAINT_NERF_CLIP_PATH, the models root or
    the workspace's 'clip_path' setting); the teacher is checked before CLIP is loaded. A MaskCLIP teacher
    is paired with its own CLIP model (no other is looked for)."""
    from repaint_nerf.core.models.clip import load_clip
    from repaint_nerf.core.models.paths import resolve_model_path

    own = getattr(teacher, "clip", None)
    if own is not None:
        return TextAlignedTeacher(teacher, own)
    teacher_feature_dim(teacher)  # a default teacher fails here, before a CLIP model is looked for
    return TextAlignedTeacher(teacher, load_clip(resolve_model_path("clip", clip_path, settings)))


def workspace_text_query(scene, ws, clip_path: str | Path | None = None):
    """(teacher with `encode_text`, codec) of a workspace: what `Selection.add_text` needs to select in it."""
    from repaint_nerf.core.teachers.stage1_targets import workspace_codec, workspace_feature_teacher

    teacher = text_teacher(workspace_feature_teacher(ws), clip_path, ws.settings)
    return teacher, workspace_codec(scene, ws, teacher.teacher)
