"""Depth priors of a scene's training images, in one class the trainer reads from.

Per image either sparse (u, v, z) points or a dense (H, W) z-depth with a validity mask. Depth is
z-depth in world units (multiply by `scene.norm.scale` for field units: `to_field`). The trainer
either samples rays at prior locations (`sample`) or looks up its own batch (`gather`).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from safetensors.numpy import load_file, save

from repaint_nerf.core.errors import WorkspaceError
from repaint_nerf.core.workspace.atomic import write_sealed
from repaint_nerf.core.workspace.integrity import sealed_metadata, verify_file


@dataclass
class SparseDepth:
    """Sparse z-depth: continuous pixel coordinates (centres at +0.5) and depths, all (P,) float32."""

    u: np.ndarray
    v: np.ndarray
    z: np.ndarray

    def __len__(self) -> int:
        return int(self.z.shape[0])


@dataclass
class DenseDepth:
    """Dense z-depth (H, W) float32 and where it holds (H, W) bool."""

    depth: np.ndarray
    valid: np.ndarray

    def __len__(self) -> int:
        return int(self.valid.sum())


class DepthPriors:
    """Depth targets for every training image (paper Eq. s1's depth term reads these)."""

    def __init__(self, priors: list[SparseDepth | DenseDepth], sizes: list[tuple[int, int]], source: str = ""):
        if len(priors) != len(sizes):
            raise ValueError("one prior per image size")
        self.priors, self.sizes, self.source = list(priors), list(sizes), source
        self._lookup: dict[int, tuple[torch.Tensor, torch.Tensor]] = {}

    def __len__(self) -> int:
        return len(self.priors)

    def for_image(self, i: int) -> SparseDepth | DenseDepth:
        return self.priors[i]

    def count(self) -> int:
        """Number of depth samples over all images (points, or valid pixels)."""
        return sum(len(p) for p in self.priors)

    def to_field(self, scale: float) -> "DepthPriors":
        """The same priors with depths multiplied by `scale` (world -> field units, Normalization.scale)."""
        out = []
        for p in self.priors:
            if isinstance(p, SparseDepth):
                out.append(SparseDepth(p.u, p.v, (p.z * scale).astype(np.float32)))
            else:
                out.append(DenseDepth((p.depth * scale).astype(np.float32), p.valid))
        return DepthPriors(out, self.sizes, self.source)

    def gather(self, image: torch.Tensor, u: torch.Tensor, v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Targets for rays at integer pixels (u, v) of `image`: (z (R,) float32, valid (R,) bool).

        A sparse point counts for the pixel that contains it (the median when several do).
        """
        image = torch.as_tensor(image).long().cpu()
        u, v = torch.as_tensor(u).long().cpu(), torch.as_tensor(v).long().cpu()
        z = torch.zeros(image.shape[0], dtype=torch.float32)
        ok = torch.zeros(image.shape[0], dtype=torch.bool)
        for i in torch.unique(image).tolist():
            sel = torch.nonzero(image == i)[:, 0]
            p = self.priors[i]
            h, w = self.sizes[i]
            uu, vv = u[sel].clamp(0, w - 1), v[sel].clamp(0, h - 1)
            if isinstance(p, DenseDepth):
                z[sel] = torch.from_numpy(p.depth)[vv, uu]
                ok[sel] = torch.from_numpy(p.valid)[vv, uu]
            else:
                keys, vals = self._pixel_table(i)
                q = vv * w + uu
                if keys.numel():
                    pos = torch.searchsorted(keys, q).clamp(max=keys.numel() - 1)
                    found = keys[pos] == q
                    z[sel] = torch.where(found, vals[pos], torch.zeros_like(vals[pos]))
                    ok[sel] = found
        return z, ok

    def sample(self, n: int, generator: torch.Generator | None = None
               ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """n random depth samples over all images: (image (n,), u (n,), v (n,), z (n,)).

        u, v are pixel indices in the convention of `Cameras.rays` (which adds 0.5), as floats so a
        ray passes exactly through a sparse point.
        """
        counts = np.array([len(p) for p in self.priors], np.int64)
        if counts.sum() == 0:
            e = torch.zeros(0)
            return e.long(), e, e, e
        flat = torch.randint(int(counts.sum()), (n,), generator=generator)
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
        img = torch.from_numpy(np.searchsorted(np.cumsum(counts), flat.numpy(), side="right"))
        local = flat - torch.from_numpy(starts)[img]
        us, vs, zs = torch.empty(n), torch.empty(n), torch.empty(n)
        for i in torch.unique(img).tolist():
            sel = img == i
            p = self.priors[i]
            k = local[sel].numpy()
            if isinstance(p, DenseDepth):
                vv, uu = np.nonzero(p.valid)
                us[sel] = torch.from_numpy(uu[k].astype(np.float32))
                vs[sel] = torch.from_numpy(vv[k].astype(np.float32))
                zs[sel] = torch.from_numpy(p.depth[vv[k], uu[k]])
            else:
                us[sel] = torch.from_numpy(p.u[k] - 0.5)
                vs[sel] = torch.from_numpy(p.v[k] - 0.5)
                zs[sel] = torch.from_numpy(p.z[k])
        return img, us, vs, zs

    def _pixel_table(self, i: int) -> tuple[torch.Tensor, torch.Tensor]:
        if i not in self._lookup:
            p = self.priors[i]
            h, w = self.sizes[i]
            key = (np.clip(np.floor(p.v), 0, h - 1).astype(np.int64) * w
                   + np.clip(np.floor(p.u), 0, w - 1).astype(np.int64))
            uniq, inv = np.unique(key, return_inverse=True)
            vals = np.array([np.median(p.z[inv == k]) for k in range(len(uniq))], np.float32) \
                if len(uniq) < len(key) else p.z[np.argsort(key)].astype(np.float32)
            self._lookup[i] = (torch.from_numpy(uniq), torch.from_numpy(vals))
        return self._lookup[i]

    # -- storage (workspace cache) --------------------------------------------------------------
    def save(self, path: str | Path) -> None:
        """Write every image's prior to one safetensors file (atomic)."""
        arrays: dict[str, np.ndarray] = {}
        for i, p in enumerate(self.priors):
            if isinstance(p, SparseDepth):
                arrays[f"{i}.u"], arrays[f"{i}.v"], arrays[f"{i}.z"] = p.u, p.v, p.z
            else:
                arrays[f"{i}.depth"], arrays[f"{i}.valid"] = p.depth, p.valid.astype(np.uint8)
        arrays["sizes"] = np.asarray(self.sizes, np.int64).reshape(-1, 2)
        write_sealed(path, save(arrays, metadata=sealed_metadata({"source": self.source, "version": "1"})))

    @staticmethod
    def load(path: str | Path) -> "DepthPriors":
        """Read priors written by `save`; a damaged file is a WorkspaceError naming it."""
        try:
            verify_file(path)
            d = load_file(str(path))
            from safetensors import safe_open

            with safe_open(str(path), "np") as f:
                source = (f.metadata() or {}).get("source", "")
        except Exception as exc:
            raise WorkspaceError(f"cannot read depth priors ({exc})", path,
                                 "delete the file; it is recomputed from the scene") from exc
        sizes = [tuple(int(x) for x in s) for s in d["sizes"]]
        priors: list[SparseDepth | DenseDepth] = []
        for i in range(len(sizes)):
            if f"{i}.z" in d:
                priors.append(SparseDepth(d[f"{i}.u"], d[f"{i}.v"], d[f"{i}.z"]))
            else:
                priors.append(DenseDepth(d[f"{i}.depth"], d[f"{i}.valid"].astype(bool)))
        return DepthPriors(priors, sizes, source)
