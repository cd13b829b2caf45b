"""A teacher's features where the feature cache needs them, without their (H, W, D) map at full resolution: at
a few pixels (the PCA fit's samples, `at`) and projected onto the PCA basis (the codes, `project`).

Why: on a 512x288 photo the blended teacher spent 34 ms in its network and about 300 ms upsampling, pooling and
normalising 216 channels at every pixel, then projecting them to 12. The ImageNet part's map is a bilinear
upsampling of two small maps, mixed with its mean over superpixels and L2-normalised: everything before the
normalisation is linear, so its projection is the projection of the small maps, upsampled and pooled, and the
pixel's length follows from dot products of the small maps' cells (`PooledUpsampled`). The values are the dense
path's (`codec.encode(teacher(image))`) up to float rounding; a teacher without `prepare` takes that path
(`Dense`).
"""
from __future__ import annotations

from typing import Protocol

import numpy as np
import torch

from repaint_nerf.core.teachers.base import check_image, l2_normalize
from repaint_nerf.core.teachers.codec import bilinear_taps, sample_codes

EPS = 1e-8  # base.l2_normalize's: a shorter vector is left as zero


class Prepared(Protocol):
    """One image's teacher features, ready to be sampled or projected."""

    size: tuple[int, int]  # (H, W)
    dim: int

    def at(self, idx: np.ndarray) -> np.ndarray:
        """(n, dim) float32 features at flat pixel indices (row-major)."""
        ...

    def project(self, basis: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        """(H * W, K) features @ basis (dim, K) and (H * W,) the features' lengths (1, or 0 where zero), float32."""
        ...


def prepared(teacher, image: np.ndarray) -> Prepared:
    """The teacher's features of an image as `Prepared`: the teacher's own `prepare` when it has one, else its
    dense map."""
    rgb = check_image(image)
    prep = getattr(teacher, "prepare", None)
    return prep(rgb) if prep is not None else Dense(teacher(rgb))


def encode(codec, prep: Prepared, scale: float = 1.0) -> np.ndarray:
    """(h, w, K) float16 codes of prepared features: what `codec.encode` makes of the dense map."""
    proj, _ = prep.project(codec.basis)
    return codec.finish(proj.numpy().reshape(*prep.size, codec.dims), scale)


class Dense:
    """A teacher's full (H, W, D) map, held as float16 (features are unit vectors; 16 fit images of a real capture
    held 2 GB as float32 while the basis was fitted)."""

    def __init__(self, feats: np.ndarray):
        self.size = (int(feats.shape[0]), int(feats.shape[1]))
        self.dim = int(feats.shape[2])
        self._flat = torch.from_numpy(np.ascontiguousarray(feats.reshape(-1, self.dim))).to(torch.float16)

    def at(self, idx: np.ndarray) -> np.ndarray:
        return self._flat[torch.as_tensor(idx)].float().numpy()

    def project(self, basis: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        f = self._flat.float()
        return f @ torch.from_numpy(np.ascontiguousarray(basis, dtype=np.float32)), torch.linalg.vector_norm(f, dim=1)


class PooledUpsampled:
    """L2-normalised features v / |v|, v = (1 - w) u + w * (mean of u over the pixel's region), where u is the
    concatenation of maps (h_l, w_l, C_l) upsampled bilinearly to (H, W) (cv2's INTER_LINEAR): what
    LiteFeatureTeacher makes of its layers (`labels` (H * W,) its superpixels; w = 0: no pooling)."""

    def __init__(self, maps: list[np.ndarray], size: tuple[int, int], labels: torch.Tensor | None, weight: float):
        self.size = (int(size[0]), int(size[1]))
        self.w = float(weight) if labels is not None else 0.0
        self.maps = [torch.from_numpy(np.ascontiguousarray(m, dtype=np.float32)) for m in maps]
        self.dim = int(sum(m.shape[2] for m in self.maps))
        big_h, big_w = self.size
        self.ty = [bilinear_taps(torch.arange(big_h), big_h, m.shape[0]) for m in self.maps]
        self.tx = [bilinear_taps(torch.arange(big_w), big_w, m.shape[1]) for m in self.maps]
        self.labels = labels
        if self.w > 0:
            # region means of u: each region's share of each small-map cell (its pixels' taps), times the cells
            n = int(labels.max()) + 1
            counts = torch.bincount(labels, minlength=n).clamp_min_(1).double()
            self.pooled = []
            for m, (y0, y1, fy), (x0, x1, fx) in zip(self.maps, self.ty, self.tx):
                cells = m.shape[0] * m.shape[1]
                share = torch.zeros(n * cells, dtype=torch.float64)
                for yi, wy in ((y0, 1 - fy), (y1, fy)):
                    for xi, wx in ((x0, 1 - fx), (x1, fx)):
                        cell = (yi[:, None] * m.shape[1] + xi[None, :]).reshape(-1)
                        share.index_add_(0, labels * cells + cell, (wy[:, None] * wx[None, :]).reshape(-1).double())
                share = share.view(n, -1) / counts[:, None]
                self.pooled.append((share @ m.reshape(-1, m.shape[2]).double()).float())  # (regions, C_l)

    def at(self, idx: np.ndarray) -> np.ndarray:
        idx = torch.as_tensor(np.asarray(idx), dtype=torch.long)
        rows, cols = idx // self.size[1], idx % self.size[1]
        parts = []
        for l, m in enumerate(self.maps):
            u = sample_codes(m, self.size, cols, rows)  # the upsampled map at those pixels
            parts.append((1 - self.w) * u + self.w * self.pooled[l][self.labels[idx]] if self.w > 0 else u)
        return l2_normalize(torch.cat(parts, 1).numpy())

    def project(self, basis: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        big_h, big_w = self.size
        basis = torch.from_numpy(np.ascontiguousarray(basis, dtype=np.float32))
        w = self.w
        proj = sq = u_p = pooled_b = p_sq = None
        at = 0
        for l, m in enumerate(self.maps):
            c = m.shape[2]
            b = basis[at:at + c]
            at += c
            (y0, y1, fy), (x0, x1, fx) = self.ty[l], self.tx[l]
            fy, fx = fy.float(), fx.float()
            # along x on the small map's rows (its last row repeated, as y1 clamps), then rows gathered per pixel
            rows = torch.cat([m, m[-1:]], 0)
            ux = rows[:, x0] * (1 - fx)[None, :, None] + rows[:, x1] * fx[None, :, None]  # (h + 1, W, C)
            small = (ux.reshape(-1, c) @ b).view(ux.shape[0], big_w, -1)
            gy, gy1 = (1 - fy)[:, None], fy[:, None]
            term = small[y0] * gy[..., None] + small[y0 + 1] * gy1[..., None]  # u @ B, (H, W, K)
            proj = term if proj is None else proj.add_(term)
            # |u|^2 from the x-upsampled rows' squares and neighbouring rows' dot products
            self_dot = (ux * ux).sum(-1)
            next_dot = (ux[:-1] * ux[1:]).sum(-1)
            term = self_dot[y0] * gy ** 2 + next_dot[y0] * (2 * gy * gy1) + self_dot[y0 + 1] * gy1 ** 2
            sq = term if sq is None else sq.add_(term)
            if w > 0:  # u . (region mean): each tap cell's dot product with the pixel's region mean
                pooled = self.pooled[l]
                cell_region = m.reshape(-1, c) @ pooled.T
                regions = self.labels.view(big_h, big_w)
                for yi, wyi in ((y0, gy), (y1, gy1)):
                    for xi, wxi in ((x0, 1 - fx), (x1, fx)):
                        term = cell_region[yi[:, None] * m.shape[1] + xi[None, :], regions] * (wyi * wxi[None, :])
                        u_p = term if u_p is None else u_p.add_(term)
                pb, ps = pooled @ b, (pooled * pooled).sum(1)
                pooled_b, p_sq = (pb, ps) if pooled_b is None else (pooled_b + pb, p_sq + ps)
        proj, sq = proj.reshape(-1, proj.shape[-1]), sq.reshape(-1)
        if w > 0:
            proj = proj.mul_(1 - w).add_(pooled_b[self.labels], alpha=w)
            sq = sq.mul_((1 - w) ** 2).add_(u_p.reshape(-1), alpha=2 * w * (1 - w)).add_(p_sq[self.labels], alpha=w * w)
        length = sq.clamp_min_(0).sqrt_()
        scale = 1.0 / length.clamp_min(EPS)
        return proj.mul_(scale[:, None]), length.mul_(scale)


class Blended:
    """BlendFeatureTeacher's features from its parts' (`parts` [(sqrt of the weight, Prepared), ...]): the scaled
    parts concatenated and L2-normalised."""

    def __init__(self, parts: list[tuple[float, Prepared]]):
        self.parts = parts
        self.size = parts[0][1].size
        self.dim = int(sum(p.dim for _, p in parts))

    def at(self, idx: np.ndarray) -> np.ndarray:
        return l2_normalize(np.concatenate([np.float32(s) * p.at(idx) for s, p in self.parts], 1))

    def project(self, basis: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        proj, sq, at = None, None, 0
        for s, p in self.parts:
            c, length = p.project(basis[at:at + p.dim])
            at += p.dim
            proj = s * c if proj is None else proj + s * c
            sq = (s * length) ** 2 if sq is None else sq + (s * length) ** 2
        length = sq.sqrt()
        scale = 1.0 / length.clamp_min(EPS)
        return proj * scale[:, None], length * scale
