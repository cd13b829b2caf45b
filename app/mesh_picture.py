"""A picture of an exported mesh file as another program sees it: trimesh reads the file, matplotlib draws it.

The README's export step shows this (not the editor's own render), so what it shows is what the file holds.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np


def render_mesh(mesh_path: str | Path, out: str | Path, title: str = "", max_faces: int = 60000) -> Path:
    """Draw the mesh at `mesh_path` from two directions with its vertex colours into the PNG `out`."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import trimesh
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    mesh = trimesh.load(str(mesh_path), force="mesh")
    faces = np.asarray(mesh.faces)
    if len(faces) > max_faces:  # matplotlib draws polygons one by one: a subset shows the same shape
        faces = faces[np.random.default_rng(0).choice(len(faces), max_faces, replace=False)]
    verts = np.asarray(mesh.vertices)
    colors = np.asarray(mesh.visual.vertex_colors, dtype=np.float64)[:, :3] / 255.0 \
        if getattr(mesh.visual, "kind", None) == "vertex" else np.full((len(verts), 3), 0.7)
    face_rgb = colors[faces].mean(axis=1)
    lo, hi = verts.min(0), verts.max(0)
    fig = plt.figure(figsize=(8.0, 4.2), dpi=100)
    for i, (elev, azim) in enumerate(((30, -60), (55, 30))):
        ax = fig.add_subplot(1, 2, i + 1, projection="3d")
        ax.add_collection3d(Poly3DCollection(verts[faces], facecolors=face_rgb, edgecolors="none"))
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
        ax.set_zlim(lo[2], hi[2])
        ax.set_box_aspect(tuple(np.maximum(hi - lo, 1e-6)))
        ax.view_init(elev=elev, azim=azim)
        ax.set_axis_off()
    fig.suptitle(title or f"{Path(mesh_path).name}: {len(mesh.vertices)} vertices, {len(mesh.faces)} faces "
                          "(trimesh + matplotlib)", fontsize=10)
    fig.tight_layout()
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out)
    plt.close(fig)
    return out
