"""Feature compression for the on-disk teacher cache: uncentred PCA to K <= 64 dims, fp16, optionally
at reduced resolution (sampled bilinearly at full-resolution pixel coordinates).

Why uncentred: with f ~= B c (B orthonormal, D x K) the dot product of two decoded vectors equals
c1 . c2, so cosine similarity in the K-dim code space is the best rank-K approximation of the
teacher's own cosine similarity. The field therefore learns the K-dim code c directly.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch

MAX_DIMS = 64


@dataclass
class PCACodec:
    """A fitted basis: `basis` (D, K) orthonormal columns, `mean` (D,) (zeros unless centred)."""

    basis: np.ndarray
    mean: np.ndarray
    explained: float = 1.0  # fraction of the features' energy the K dims keep (on the fit sample)

    @property
    def dims(self) -> int:
        return int(self.basis.shape[1])

    @staticmethod
    def fit(samples: np.ndarray, k: int = 16, center: bool = False, seed: int = 0) -> "PCACodec":
        """Fit on (N, D) feature samples (e.g. a random subsample of every image's pixels)."""
        x = np.asarray(samples, dtype=np.float32).reshape(-1, samples.shape[-1])
        d = x.shape[1]
        k = int(min(k, d, MAX_DIMS))
        mean = x.mean(0) if center else np.zeros(d, np.float32)
        xc = torch.from_numpy(x - mean)
        # exact SVD of the D x D second-moment matrix: D <= a few hundred, N can be large
        gram = (xc.T.double() @ xc.double()) / max(1, x.shape[0])
        evals, evecs = torch.linalg.eigh(gram)
        order = torch.argsort(evals, descending=True)
        evals, evecs = evals[order], evecs[:, order]
        basis = evecs[:, :k].float().numpy()
        # sign convention: the largest-magnitude entry of each column is positive (stable across runs)
        flip = np.sign(basis[np.abs(basis).argmax(0), np.arange(k)])
        basis = basis * np.where(flip == 0, 1.0, flip)[None, :].astype(np.float32)
        total = float(evals.clamp_min(0).sum())
        kept = float(evals[:k].clamp_min(0).sum())
        return PCACodec(np.ascontiguousarray(basis, dtype=np.float32), mean.astype(np.float32),
                        kept / total if total > 0 else 1.0)

    def encode(self, features: np.ndarray, scale: float = 1.0) -> np.ndarray:
        """(H, W, D) float -> (h, w, K) float16 codes, h = round(H * scale) (area-averaged when < 1)."""
        f = np.asarray(features, dtype=np.float32)
        return self.finish((f.reshape(-1, f.shape[-1]) @ self.basis).reshape(*f.shape[:2], self.dims), scale)

    def finish(self, projected: np.ndarray, scale: float = 1.0) -> np.ndarray:
        """Features already projected onto the basis, (H, W, K) float32 -> the codes `encode` makes: the mean's
        projection taken off, area-averaged to `scale` (a linear map, so after the projection as well as before)."""
        codes = projected - self.mean @ self.basis if np.any(self.mean) else projected
        if scale != 1.0:
            codes = _resize(codes, code_size(codes.shape[:2], scale), cv2.INTER_AREA)
        return codes.astype(np.float16)

    def decode(self, codes: np.ndarray) -> np.ndarray:
        """K-dim codes -> D-dim features (what the teacher's space looks like after compression)."""
        c = np.asarray(codes, dtype=np.float32)
        return c @ self.basis.T + self.mean

    def to_arrays(self) -> dict[str, np.ndarray]:
        return {"basis": self.basis, "mean": self.mean, "explained": np.array([self.explained], np.float32)}

    @staticmethod
    def from_arrays(d: dict[str, np.ndarray]) -> "PCACodec":
        return PCACodec(np.asarray(d["basis"], np.float32), np.asarray(d["mean"], np.float32),
                        float(np.asarray(d.get("explained", [1.0]))[0]))


def code_size(size: tuple[int, int], scale: float = 1.0) -> tuple[int, int]:
    """(h, w) of the codes `PCACodec.encode` makes of an (H, W) feature map at `scale`."""
    if scale == 1.0:
        return int(size[0]), int(size[1])
    return max(1, int(round(size[0] * scale))), max(1, int(round(size[1] * scale)))


def upsample_codes(codes: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Stored (h, w, K) codes -> float32 (H, W, K) at full resolution, bilinear with pixel centres aligned."""
    return _resize(np.asarray(codes, dtype=np.float32), size, cv2.INTER_LINEAR)


def bilinear_taps(pos: torch.Tensor, n_out: int, n_in: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Bilinear taps at integer positions `pos` of an n_out-sample axis resized from n_in samples, by cv2.resize's
    rule (half-pixel centres, clamped at the edges): (i0, i1, frac), value = (1 - frac) src[i0] + frac src[i1]."""
    s = ((pos.float() + 0.5) * (n_in / n_out) - 0.5).clamp(0, n_in - 1)
    i0 = s.floor().long()
    return i0, (i0 + 1).clamp(max=n_in - 1), s - i0


def sample_codes(codes: torch.Tensor, size: tuple[int, int], u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Bilinear lookup of (h, w, K) codes at full-resolution integer pixels (u, v) of an (H, W) image.

    Pixel centres line up the way cv2.resize and the cameras agree: full-res pixel u has its centre
    at (u + 0.5) * w / W - 0.5 in the stored grid. Returns (R, K) float32.
    """
    h, w, _ = codes.shape
    big_h, big_w = size
    x0, x1, fx = bilinear_taps(u, big_w, w)
    y0, y1, fy = bilinear_taps(v, big_h, h)
    fx, fy = fx[:, None], fy[:, None]
    c = codes.float()
    top = c[y0, x0] * (1 - fx) + c[y0, x1] * fx
    bot = c[y1, x0] * (1 - fx) + c[y1, x1] * fx
    return top * (1 - fy) + bot * fy


def _resize(f: np.ndarray, size: tuple[int, int], interp: int) -> np.ndarray:
    h, w = size
    if f.shape[:2] == (h, w):
        return f.astype(np.float32, copy=False)
    # cv2 handles at most 512 channels per call, and its area resize by a non-integer factor at most 4
    step = 4 if interp == cv2.INTER_AREA else 256
    parts = [cv2.resize(np.ascontiguousarray(f[..., i:i + step]), (w, h), interpolation=interp)
             for i in range(0, f.shape[-1], step)]
    parts = [p[..., None] if p.ndim == 2 else p for p in parts]
    return np.concatenate(parts, axis=-1).astype(np.float32, copy=False)
