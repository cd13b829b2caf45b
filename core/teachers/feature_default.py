"""The weight-free default feature teacher: colour + multi-scale texture, pooled over superpixels,
embedded with fixed random Fourier features so that cosine similarity is a Gaussian kernel.

Why this shape: the paper's mask is `cos(F_patch, F(pixel)) > alpha`. Random Fourier features
phi(x) = [cos(Wx), sin(Wx)] / sqrt(m) have |phi| = 1 exactly and phi(x).phi(y) ~= exp(-|x-y|^2 / 2h^2),
so one threshold means one radius in a descriptor space whose axes are scaled to "same object"
units (shading-tolerant chroma, Weber-normalised texture energy). Pooling the descriptor inside
superpixels (SLIC on the descriptor itself, so texture boundaries count) gives a region one vector.
"""
from __future__ import annotations

import hashlib
import threading
from dataclasses import asdict, dataclass

import cv2
import numpy as np
import torch

from repaint_nerf.core.teachers.base import check_image


@dataclass(frozen=True)
class DefaultTeacherConfig:
    """Weights and scales of the default teacher; the cache is keyed by these values."""

    dim: int = 64                  # output dimension (2 x number of random frequencies)
    bandwidth: float = 1.75        # kernel width h in descriptor units
    seed: int = 0                  # random frequencies are fixed by this seed
    ref_size: int = 128            # blur scales are in pixels of an image whose short side is this
    colour_sigmas: tuple = (0.5,)  # fine: a 2-3 px pole keeps its colour (a 2 px blur erased it)
    intensity_sigma: float = 1.0   # blur of the log-intensity channel, reference pixels
    dark: float = 0.04             # intensity floor: chroma of near-black pixels fades to grey
    w_chroma: float = 4.0          # per unit of opponent chromaticity (shading-invariant)
    w_intensity: float = 0.35      # per unit of log intensity (shading moves it: low weight)
    texture_scales: tuple = (0.7, 1.4)
    w_texture: float = 5.0         # per unit of log-intensity band amplitude (Weber contrast)
    w_colour_texture: float = 2.0  # per unit of chromaticity band amplitude (two-colour patterns)
    superpixel: float = 8.0        # SLIC region size in reference pixels (0 = no pooling)
    slic_ruler: float = 10.0       # SLIC compactness on the Lab image
    pooled_weight: float = 0.9     # mix of region-pooled and per-pixel descriptor


class DefaultFeatureTeacher:
    """Weight-free dense features for any RGB image; fast enough to run on every training image."""

    name = "default"

    def __init__(self, config: DefaultTeacherConfig | None = None, **overrides):
        cfg = config or DefaultTeacherConfig()
        if overrides:
            cfg = DefaultTeacherConfig(**{**asdict(cfg), **overrides})
        self.cfg = cfg
        if cfg.dim < 2 or cfg.dim % 2:
            raise ValueError("dim must be an even number >= 2")
        self._freqs: np.ndarray | None = None

    def config(self) -> dict:
        d = asdict(self.cfg)
        return {k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}

    @property
    def dim(self) -> int:
        return self.cfg.dim

    def __call__(self, image: np.ndarray) -> np.ndarray:
        """(H, W, 3) uint8 -> (H, W, dim) float32, unit length per pixel."""
        desc = self.descriptor(image)
        return self.embed(desc)

    # -- descriptor: a few scaled channels where "same object" means "close" -------------------
    def descriptor(self, image: np.ndarray) -> np.ndarray:
        """Per-pixel descriptor (H, W, C) float32 in kernel units, region-pooled."""
        rgb8 = check_image(image)
        h, w = rgb8.shape[:2]
        cfg = self.cfg
        unit = min(h, w) / float(cfg.ref_size)
        rgb = rgb8.astype(np.float32) * np.float32(1.0 / 255.0)
        inten = rgb.mean(axis=2) + cfg.dark
        r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
        # opponent chromaticity divided by intensity: a shaded side of one surface keeps its value
        opp = np.stack([(r - g) * (1.0 / np.sqrt(2.0)), (r + g - 2.0 * b) * (1.0 / np.sqrt(6.0))], 2)
        chroma = opp / inten[..., None]
        logi = np.log(inten)
        chans = []
        for s in cfg.colour_sigmas:
            chans.append(_blur(chroma, s * unit) * cfg.w_chroma)
        chans.append(_blur(logi, cfg.intensity_sigma * unit)[..., None] * cfg.w_intensity)
        stack = np.concatenate([logi[..., None], chroma], axis=2)
        for s in cfg.texture_scales:
            sig = s * unit
            band = _blur(stack, sig) - _blur(stack, 2.0 * sig)
            energy = _blur(band * band, 1.5 * sig)
            chans.append(np.sqrt(energy[..., :1]) * cfg.w_texture)
            chans.append(np.sqrt(energy[..., 1:2] + energy[..., 2:3]) * cfg.w_colour_texture)
        desc = np.concatenate(chans, axis=2).astype(np.float32)
        if cfg.superpixel > 0 and cfg.pooled_weight > 0:
            desc = self._pool(desc, rgb8, unit)
        return desc

    def _pool(self, desc: np.ndarray, rgb8: np.ndarray, unit: float) -> np.ndarray:
        cfg = self.cfg
        return region_pool(desc, rgb8, max(3, int(round(cfg.superpixel * unit))), cfg.slic_ruler, cfg.pooled_weight)

    # -- embedding: cosine of the output ~= Gaussian kernel of the descriptor distance ----------
    def embed(self, desc: np.ndarray) -> np.ndarray:
        """Random Fourier features of a descriptor (..., C) -> (..., dim), exactly unit length."""
        c = desc.shape[-1]
        if self._freqs is None or self._freqs.shape[0] != c:
            rng = np.random.default_rng(self.cfg.seed)
            m = self.cfg.dim // 2
            # orthogonal random features (Yu et al. 2016): lower kernel error than i.i.d. Gaussians
            blocks, left = [], m
            while left > 0:
                q, _ = np.linalg.qr(rng.standard_normal((c, c)))
                norms = np.sqrt(rng.chisquare(c, size=c))
                blocks.append((q * norms[None, :])[:, :min(c, left)])
                left -= c
            self._freqs = (np.concatenate(blocks, 1) / self.cfg.bandwidth).astype(np.float32)
        proj = desc.reshape(-1, c) @ self._freqs
        out = np.empty((proj.shape[0], self.cfg.dim), dtype=np.float32)
        m = proj.shape[1]
        scale = np.float32(1.0 / np.sqrt(m))
        np.cos(proj, out=out[:, :m])
        np.sin(proj, out=out[:, m:])
        out *= scale
        return out.reshape(*desc.shape[:-1], self.cfg.dim)


def region_pool(desc: np.ndarray, rgb8: np.ndarray, size: int, ruler: float, weight: float) -> np.ndarray:
    """Per-pixel descriptors (H, W, C) mixed with their mean over SLIC superpixels of the image (region size
    `size` px, compactness `ruler` on Lab): `weight` x region mean + (1 - weight) x the pixel's own. Why: a
    region gets one vector, so a mask follows the image's edges, not the descriptor's blur or stride."""
    labels = superpixels(rgb8, size, ruler)
    n = int(labels.max()) + 1
    flat = torch.from_numpy(np.ascontiguousarray(desc, dtype=np.float32).reshape(-1, desc.shape[2]))
    sums = torch.zeros(n, flat.shape[1]).index_add_(0, labels, flat)
    counts = torch.bincount(labels, minlength=n).clamp_min_(1).float()
    pooled = sums / counts[:, None]
    return torch.lerp(flat, pooled[labels], float(weight)).reshape(desc.shape).numpy()


def superpixels(rgb8: np.ndarray, size: int, ruler: float) -> torch.Tensor:
    """SLIC superpixel labels (H * W,) int64 of an image: region size `size` px, compactness `ruler` on Lab. The
    last result is kept: the blended teacher's two parts ask for the same regions of each image."""
    rgb8 = np.ascontiguousarray(rgb8)
    key = (rgb8.shape, int(size), float(ruler), hashlib.blake2b(rgb8.data, digest_size=16).digest())
    with _LAST_LOCK:
        if _LAST_LABELS and _LAST_LABELS[0] == key:
            return _LAST_LABELS[1]
    lab = cv2.cvtColor(rgb8, cv2.COLOR_RGB2Lab)
    slic = cv2.ximgproc.createSuperpixelSLIC(lab, algorithm=cv2.ximgproc.SLIC, region_size=int(size),
                                             ruler=float(ruler))
    slic.iterate(4)
    labels = torch.from_numpy(slic.getLabels().reshape(-1).astype(np.int64))
    with _LAST_LOCK:
        _LAST_LABELS[:] = [key, labels]
    return labels


_LAST_LOCK = threading.Lock()
_LAST_LABELS: list = []  # [key, labels] of the last `superpixels` call


def _blur(x: np.ndarray, sigma: float) -> np.ndarray:
    if sigma <= 0.3:
        return x
    return cv2.GaussianBlur(x, (0, 0), sigmaX=float(sigma), borderType=cv2.BORDER_REFLECT)


# The one threshold the kernel design is tuned for: cos >= 0.5 <=> descriptor distance <~ 1.18 h.
DEFAULT_THRESHOLD = 0.5
