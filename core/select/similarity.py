"""Cosine similarity between rendered feature vectors and query vectors, safe for any input.

A zero vector (empty space renders a zero feature) has similarity 0, never NaN, and huge vectors stay
finite: each vector is divided by its largest component before its norm is taken (DESIGN.md, Numerics).
"""
from __future__ import annotations

import torch
from torch import Tensor

EPS = 1e-8


def normalize(x: Tensor, eps: float = EPS) -> Tensor:
    """Unit vectors along the last axis (float32); vectors shorter than `eps` (after scaling) become zero."""
    x = torch.nan_to_num(x.float(), nan=0.0, posinf=0.0, neginf=0.0)
    scale = x.abs().amax(dim=-1, keepdim=True)
    x = x / scale.clamp_min(torch.finfo(torch.float32).tiny)  # entries in [-1, 1]: the norm cannot overflow
    norm = torch.linalg.vector_norm(x, dim=-1, keepdim=True)
    return torch.where(norm > eps, x / norm.clamp_min(eps), torch.zeros_like(x))


def cosine_similarity(features: Tensor, queries: Tensor, eps: float = EPS) -> Tensor:
    """cos(f, q) for features (..., F) against one query (F,) -> (...) or several (Q, F) -> (..., Q).

    The patch-to-mask hot path: the queries are normalised, the features are not (two passes over the
    map: one matrix product and one norm). Where that overflows (huge vectors) the robust path redoes it.
    """
    f = features if features.dtype == torch.float32 else features.float()
    q = normalize(queries.to(f.device), eps)
    qm = q if q.dim() == 1 else q.T
    norm = torch.linalg.vector_norm(f, dim=-1)
    if not bool(torch.isfinite(norm).all()):  # overflow (or inf/NaN entries): take the robust path
        return normalize(f, eps) @ qm
    if q.dim() > 1:
        norm = norm[..., None]
    return (f @ qm) / norm.clamp_min(eps)
