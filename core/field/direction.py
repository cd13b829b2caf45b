"""Spherical-harmonics encoding of view directions (real SH bands l = 0..degree-1, as instant-ngp's "degree")."""
from __future__ import annotations

import torch

# Normalisation constants of the real spherical harmonics, bands 0..3.
_C0 = 0.28209479177387814
_C1 = 0.4886025119029199
_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
       -0.4570457994644658, 1.445305721320277, -0.5900435899266435)


def sh_dim(degree: int) -> int:
    """Number of outputs for `degree` bands: degree^2 (16 for degree 4)."""
    return degree * degree


def sh_encode(d: torch.Tensor, degree: int = 4) -> torch.Tensor:
    """Directions (N, 3) (normalised here) -> (N, degree^2) real SH values; degree in 1..4."""
    from repaint_nerf.core.errors import UserError

    if not 1 <= degree <= 4:
        raise UserError(f"spherical-harmonics degree {degree} is not supported", hint="use a degree from 1 to 4")
    d = d / d.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    x, y, z = d.unbind(-1)
    out = [torch.full_like(x, _C0)]
    if degree > 1:
        out += [-_C1 * y, _C1 * z, -_C1 * x]
    if degree > 2:
        xx, yy, zz = x * x, y * y, z * z
        out += [_C2[0] * x * y, _C2[1] * y * z, _C2[2] * (2 * zz - xx - yy), _C2[3] * x * z, _C2[4] * (xx - yy)]
    if degree > 3:
        out += [_C3[0] * y * (3 * xx - yy), _C3[1] * x * y * z, _C3[2] * y * (4 * zz - xx - yy),
                _C3[3] * z * (2 * zz - 3 * xx - 3 * yy), _C3[4] * x * (4 * zz - xx - yy),
                _C3[5] * z * (xx - yy), _C3[6] * x * (xx - 3 * yy)]
    return torch.stack(out, dim=-1)
