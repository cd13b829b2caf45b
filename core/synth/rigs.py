"""Camera rigs for the synthetic scenes: each returns a function (n, rng) -> (n, 4, 4) OpenGL camera-to-world.

Positions are spread evenly and jittered from `rng`, so a scene is deterministic from its seed and
successive calls (train, then test) give different viewpoints.
"""
from __future__ import annotations

from typing import Callable

import numpy as np

from repaint_nerf.core.scene.cameras import look_at

Rig = Callable[[int, np.random.Generator], np.ndarray]
_GOLDEN = np.pi * (3.0 - np.sqrt(5.0))


def hemisphere(radius: float, target=(0.0, 0.0, 0.0), elevation_deg=(12.0, 72.0)) -> Rig:
    """Object-centric 360-degree views on the upper hemisphere, looking at `target` (Fibonacci spiral)."""
    lo, hi = np.sin(np.radians(elevation_deg))
    tgt = np.asarray(target, dtype=np.float64)

    def make(n: int, rng: np.random.Generator) -> np.ndarray:
        phase = rng.uniform(0.0, 2 * np.pi)
        h = (np.arange(n) + rng.uniform(0.2, 0.8, n)) / n
        elev = np.arcsin(lo + h * (hi - lo))
        azim = phase + np.arange(n) * _GOLDEN
        r = radius * rng.uniform(0.97, 1.03, n)
        eye = tgt + r[:, None] * np.stack([np.cos(elev) * np.cos(azim), np.cos(elev) * np.sin(azim),
                                           np.sin(elev)], -1)
        return np.stack([look_at(e, tgt) for e in eye])

    return make


def ring(radius: float, heights=(0.8, 1.8), target=(0.0, 0.0, 0.0)) -> Rig:
    """Inward-looking 360-degree views on a horizontal ring at heights within `heights` (a room capture)."""
    tgt = np.asarray(target, dtype=np.float64)

    def make(n: int, rng: np.random.Generator) -> np.ndarray:
        azim = rng.uniform(0.0, 2 * np.pi) + 2 * np.pi * (np.arange(n) + rng.uniform(-0.3, 0.3, n)) / n
        z = rng.uniform(*heights, n)
        r = radius * rng.uniform(0.9, 1.1, n)
        eye = np.stack([r * np.cos(azim), r * np.sin(azim), z], -1)
        return np.stack([look_at(e, tgt) for e in eye])

    return make


def forward_plane(center, target, extent=(0.8, 0.5)) -> Rig:
    """LLFF-like capture: parallel cameras on a small plane around `center`, all facing `target`'s direction.

    `extent` is the half-width and half-height of the plane (jittered grid of positions).
    """
    base = look_at(np.asarray(center, dtype=np.float64), np.asarray(target, dtype=np.float64))
    right, up = base[:3, 0], base[:3, 1]

    def make(n: int, rng: np.random.Generator) -> np.ndarray:
        k = int(np.ceil(np.sqrt(n)))
        cells = rng.permutation(k * k)[:n]
        gx = (cells % k + rng.uniform(0.0, 1.0, n)) / k * 2 - 1
        gy = (cells // k + rng.uniform(0.0, 1.0, n)) / k * 2 - 1
        out = np.repeat(base[None], n, axis=0)
        out[:, :3, 3] += gx[:, None] * extent[0] * right + gy[:, None] * extent[1] * up
        return out

    return make
