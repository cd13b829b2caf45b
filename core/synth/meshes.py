"""Triangle meshes of simple primitives (numpy), built at their final size in object coordinates.

Each builder returns (vertices (N, 6) float32 = position xyz + unit normal xyz, indices (M, 3) uint32).
Objects stand along +z: their local origin is the centre of their bounding box.
"""
from __future__ import annotations

import numpy as np

Mesh = tuple[np.ndarray, np.ndarray]


def _grid_indices(rows: int, cols: int, offset: int = 0) -> np.ndarray:
    """Two triangles per cell of a (rows+1) x (cols+1) vertex grid laid out row-major."""
    r, c = np.meshgrid(np.arange(rows), np.arange(cols), indexing="ij")
    a = r * (cols + 1) + c
    b, d = a + 1, a + cols + 1
    e = d + 1
    tris = np.stack([np.stack([a, d, b], -1), np.stack([b, d, e], -1)], axis=2)
    return tris.reshape(-1, 3).astype(np.uint32) + offset


def _merge(*parts: Mesh) -> Mesh:
    verts, idx, n = [], [], 0
    for v, i in parts:
        verts.append(v)
        idx.append(i + n)
        n += len(v)
    return np.concatenate(verts).astype(np.float32), np.concatenate(idx).astype(np.uint32)


def _fan(center: np.ndarray, ring: np.ndarray, normal: np.ndarray) -> Mesh:
    """A flat fan from `center` to the closed polyline `ring` (K, 3), all with one normal."""
    pts = np.concatenate([center[None], ring])
    v = np.concatenate([pts, np.broadcast_to(normal, pts.shape)], axis=1)
    k = len(ring)
    j = np.arange(k)
    idx = np.stack([np.zeros(k, dtype=np.int64), 1 + j, 1 + (j + 1) % k], -1)
    return v.astype(np.float32), idx.astype(np.uint32)


def _circle(radius: float, z: float, n: int) -> np.ndarray:
    a = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    return np.stack([radius * np.cos(a), radius * np.sin(a), np.full(n, z)], -1)


def sphere(radius: float, segments: int = 64, rings: int = 32) -> Mesh:
    """UV sphere of `radius` centred at the origin."""
    theta = np.linspace(0.0, np.pi, rings + 1)[:, None]
    phi = np.linspace(0.0, 2 * np.pi, segments + 1)[None, :]
    n = np.stack(np.broadcast_arrays(np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi),
                                     np.cos(theta)), -1).reshape(-1, 3)
    return np.concatenate([radius * n, n], 1).astype(np.float32), _grid_indices(rings, segments)


def ellipsoid(rx: float, ry: float, rz: float, segments: int = 64, rings: int = 32) -> Mesh:
    """Ellipsoid with semi-axes (rx, ry, rz) centred at the origin (a loaf, a lemon)."""
    v, idx = sphere(1.0, segments, rings)
    axes = np.array([rx, ry, rz], np.float32)
    n = v[:, 3:] / axes
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    return np.concatenate([v[:, :3] * axes, n], 1).astype(np.float32), idx


def box(sx: float, sy: float, sz: float) -> Mesh:
    """Axis-aligned box with side lengths (sx, sy, sz) centred at the origin (flat-shaded faces)."""
    half = np.array([sx, sy, sz]) / 2
    parts = []
    for axis in range(3):
        for sign in (-1.0, 1.0):
            normal = np.zeros(3)
            normal[axis] = sign
            u_ax, v_ax = [a for a in range(3) if a != axis]
            corners = []
            for du, dv in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
                p = np.zeros(3)
                p[axis], p[u_ax], p[v_ax] = sign * half[axis], du * half[u_ax], dv * half[v_ax]
                corners.append(p)
            v = np.concatenate([np.array(corners), np.broadcast_to(normal, (4, 3))], 1)
            parts.append((v, np.array([[0, 1, 2], [0, 2, 3]])))
    return _merge(*parts)


def cylinder(radius: float, height: float, segments: int = 64, inward: bool = False,
             caps: bool = True) -> Mesh:
    """Closed cylinder along z centred at the origin; `inward` points normals inside (a room)."""
    s = -1.0 if inward else 1.0
    a = np.linspace(0.0, 2 * np.pi, segments + 1)
    radial = np.stack([np.cos(a), np.sin(a), np.zeros_like(a)], -1)
    rows = []
    for z in (-height / 2, height / 2):
        rows.append(np.concatenate([radius * radial + [0, 0, z], s * radial], 1))
    parts = [(np.concatenate(rows), _grid_indices(1, segments))]
    if caps:
        for z, nz in ((-height / 2, -s), (height / 2, s)):
            parts.append(_fan(np.array([0.0, 0.0, z]), _circle(radius, z, segments), np.array([0, 0, nz])))
    return _merge(*parts)


def cone(radius: float, height: float, segments: int = 64) -> Mesh:
    """Cone along z (apex up) with its bounding box centred at the origin."""
    a = np.linspace(0.0, 2 * np.pi, segments + 1)
    slope = radius / height
    normal = np.stack([np.cos(a), np.sin(a), np.full_like(a, slope)], -1)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    base = np.stack([radius * np.cos(a), radius * np.sin(a), np.full_like(a, -height / 2)], -1)
    apex = np.broadcast_to([0.0, 0.0, height / 2], base.shape)
    side = np.concatenate([np.concatenate([base, normal], 1), np.concatenate([apex, normal], 1)])
    bottom = _fan(np.array([0.0, 0.0, -height / 2]), _circle(radius, -height / 2, segments), np.array([0, 0, -1.0]))
    return _merge((side, _grid_indices(1, segments)), bottom)


def torus(major: float, minor: float, segments: int = 64, sides: int = 24) -> Mesh:
    """Torus lying in the xy plane around the z axis, centred at the origin."""
    u = np.linspace(0.0, 2 * np.pi, segments + 1)[None, :]
    v = np.linspace(0.0, 2 * np.pi, sides + 1)[:, None]
    n = np.stack(np.broadcast_arrays(np.cos(v) * np.cos(u), np.cos(v) * np.sin(u), np.sin(v) + 0 * u), -1)
    ring = np.stack(np.broadcast_arrays(np.cos(u), np.sin(u), 0 * u + 0 * v), -1)
    p = major * ring + minor * n
    v_ = np.concatenate([p.reshape(-1, 3), n.reshape(-1, 3)], 1)
    return v_.astype(np.float32), _grid_indices(sides, segments)


def disc(radius: float, segments: int = 96) -> Mesh:
    """Flat disc in the xy plane facing +z."""
    return _fan(np.zeros(3), _circle(radius, 0.0, segments), np.array([0.0, 0.0, 1.0]))


BUILDERS = {"sphere": sphere, "ellipsoid": ellipsoid, "box": box, "cylinder": cylinder, "cone": cone, "torus": torus, "disc": disc}


def build(kind: str, **params) -> Mesh:
    """Build a mesh by its primitive name (a key of BUILDERS) and keyword parameters."""
    return BUILDERS[kind](**params)
