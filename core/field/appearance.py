"""Per-image appearance codes, as nerfacto's (NeRF-W's appearance embedding): exposure and white balance change
between real photos, and a code per training image fed to the colour head explains that change instead of the
geometry (floaters) or the view dependence (colours that flicker between views).

The codes start at zero, so a field with codes starts as the field without. Rays of a training image use its code;
everything else (held-out views, the viewport, exports, edits) uses the mean code of the training images, as
nerfstudio evaluates (`use_average_appearance_embedding`). Whether a scene gets codes: `appearance_default`.
"""
from __future__ import annotations

import torch
from torch import Tensor, nn

APPEARANCE_DIM = 16  # nerfacto uses 32; 16 keeps the colour head cheap on a CPU and is plenty for a gain per channel
SYNTHETIC_FORMATS = ("blender",)  # rendered datasets: one exposure for all images
SETTINGS = ("auto", "on", "off")


def appearance_default(scene, setting: str = "auto") -> tuple[bool, str]:
    """(use codes, why): `setting` 'on'/'off' forces it; 'auto' turns them on for captures (photos, COLMAP, LLFF,
    nerfstudio / instant-ngp files) and off for rendered NeRF-synthetic scenes."""
    from repaint_nerf.core.errors import UserError

    if setting not in SETTINGS:
        raise UserError(f"unknown appearance setting {setting!r}", hint=f"use one of {', '.join(SETTINGS)}")
    if setting != "auto":
        return setting == "on", f"asked for ({setting})"
    if scene.format in SYNTHETIC_FORMATS:
        return False, f"a rendered ({scene.format}) scene has one exposure"
    return True, f"a {scene.format} capture: exposure and white balance may change between photos"


class AppearanceCodes(nn.Module):
    """One learned code per training image; `codes(index)` for those images, `codes(None, n)` the mean code n times."""

    def __init__(self, count: int, dim: int):
        super().__init__()
        self.embedding = nn.Embedding(count, dim)
        nn.init.zeros_(self.embedding.weight)

    def forward(self, index: Tensor | None, n: int) -> Tensor:
        if index is None:
            return self.embedding.weight.mean(0, keepdim=True).expand(n, -1)
        return self.embedding(index)


class RayAppearance:
    """A field seen through per-ray image indices: the renderer passes each sample's ray (`per_ray`), this picks
    the ray's image code. Everything else is the wrapped field's."""

    per_ray = True

    def __init__(self, field, image_of_ray: Tensor):
        self.field, self.image_of_ray = field, image_of_ray

    def __getattr__(self, name):
        return getattr(self.field, name)

    def rows(self, rays: Tensor) -> "RayAppearance":
        """The field seen through rays `rays` of this one only (the renderer's rays with samples in a round)."""
        return RayAppearance(self.field, self.image_of_ray[rays])

    def __call__(self, x: Tensor, d: Tensor, outputs=("rgb",), ray: Tensor | None = None, **kw) -> dict[str, Tensor]:
        if getattr(self.field, "view_per_ray", False):  # d is per ray, as the codes are
            return self.field(x, d, outputs=outputs, appearance=self.image_of_ray, ray=ray, **kw)
        return self.field(x, d, outputs=outputs, appearance=None if ray is None else self.image_of_ray[ray], **kw)


def with_ray_appearance(field, image_of_ray: Tensor | None, start: int, count: int):
    """The field for rays [start, start + count) of a render whose rays come from images `image_of_ray` (None, or
    a field without codes: the field itself)."""
    if image_of_ray is None or getattr(field, "appearance", None) is None:
        return field
    return RayAppearance(field, image_of_ray[start:start + count].to(torch.long))
