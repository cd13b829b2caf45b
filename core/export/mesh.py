"""A mesh of the field: marching cubes (scikit-image) on the density lattice, vertex colours from the radiance
field, floaters dropped on request, written by trimesh as .ply / .obj / .glb in the scene's world units.

Vertex colour: a ray is volume-rendered from just outside each vertex towards it, along the negative surface
normal, i.e. the colour a camera looking straight at the surface sees there (view-dependent effects are those
of that head-on view). `selection=True` keeps the density inside the saved selection's 3D region only.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from repaint_nerf.core.errors import UserError
from repaint_nerf.core.export.common import Cancel, Progress, atomic_output, check_output_file, checkpoint
from repaint_nerf.core.export.lattice import density_lattice, field_box, lattice_points
from repaint_nerf.core.export.region import saved_masks, selection_region

MESH_SUFFIXES = (".ply", ".obj", ".glb")
COLOR_OFFSET_VOXELS = 2.0  # the colour ray starts this many lattice spacings outside the vertex
COLOR_CHUNK = 1 << 16
REGION_CHUNK = 1 << 20  # lattice points per selection test
LEVEL_VIEWS = 8  # training views that choose the default iso-level


@dataclass
class MeshOptions:
    resolution: int = 256  # lattice points per axis of the box
    level: float | None = None  # density iso-level (field units); None: default_level (from the renders)
    bbox: tuple | None = None  # xmin, ymin, zmin, xmax, ymax, zmax in world units; None: the whole field
    min_component: float = 0.0  # drop connected pieces with fewer than this fraction of the faces
    selection: bool = False  # only the saved selection's 3D region


@torch.no_grad()
def default_level(source, views: int = LEVEL_VIEWS) -> float:
    """Half the density where the renders put surfaces: the median density at the expected-depth points of the
    pixels that `views` evenly spread training views see as opaque (opacity above one half). Read off the field
    itself, so it holds for weakly and strongly trained fields alike; half, so the iso-surface lies on the rising
    side of the surface (a solid of uniform density has that density at its surface points, and marching cubes
    needs a level below the peak). With no training view or no opaque pixel: the density at which one render
    step is half opaque (ln 2 / step)."""
    from repaint_nerf.core.render.occupancy import default_step
    from repaint_nerf.core.select.cleanup3d import backproject

    sigma = []
    for i in source.train_views(views):
        depth, opacity = source.depth_opacity(i)
        keep = (opacity > 0.5).reshape(-1)
        if keep.any():
            pts = backproject(depth, source.scene.field_cameras("train"), i)[keep].to(source.device)
            sigma.append(source.field.density(pts).float().cpu())
    if sigma:
        return 0.5 * float(torch.cat(sigma).median())
    bound = float(getattr(getattr(source.field, "cfg", None), "bound", getattr(source.field, "bound", 1.0)))
    return math.log(2.0) / default_step(bound, source.max_samples)


def check_options(opts: MeshOptions) -> None:
    if not 8 <= int(opts.resolution) <= 1024:
        raise UserError(f"--resolution must be between 8 and 1024, got {opts.resolution}")
    if opts.level is not None and not opts.level > 0:
        raise UserError(f"--level must be a positive density, got {opts.level}")
    if not 0.0 <= opts.min_component < 1.0:
        raise UserError(f"--min-component is a fraction of the faces in [0, 1), got {opts.min_component}")


def marching_cubes(volume: np.ndarray, level: float, lo: np.ndarray, hi: np.ndarray):
    """(vertices (V,3) field space, faces (F,3), outward normals (V,3)) of the iso-surface sigma = level."""
    from skimage import measure

    if not float(volume.max(initial=0.0)) > level:
        raise UserError(f"the field has no surface at density level {level:.4g} in this box "
                        f"(highest density {float(volume.max(initial=0.0)):.4g})",
                        hint="lower --level, widen --bbox, or train longer")
    # a shell of empty space around the lattice closes surfaces cut by the box
    padded = np.pad(volume, 1, constant_values=0.0)
    spacing = tuple((hi - lo) / (np.array(volume.shape) - 1))
    # density rises inwards: "ascent" winds the faces counter-clockwise seen from outside (normals point out either way)
    verts, faces, normals, _ = measure.marching_cubes(padded, level=level, spacing=spacing,
                                                      gradient_direction="ascent")
    # undo the padding shift; caps closing a cut surface lie on the box's faces
    verts = np.clip(verts - np.asarray(spacing) + lo, lo, hi)
    return verts, faces.astype(np.int64), np.ascontiguousarray(normals)


@torch.no_grad()
def vertex_colors(source, verts: np.ndarray, normals: np.ndarray, offset: float, cancel: Cancel | None = None,
                  progress: Progress | None = None, span=(0.0, 1.0)) -> np.ndarray:
    """uint8 (V, 3) colours: each vertex seen along its negative normal from `offset` outside (module docstring)."""
    from repaint_nerf.core.render.renderer import render_rays

    field, dev = source.field, source.device
    opts = source.render_options(("rgb", "opacity"))
    out = np.zeros((len(verts), 3), np.float32)
    for s in range(0, len(verts), COLOR_CHUNK):
        checkpoint(cancel, progress, span[0] + (span[1] - span[0]) * s / max(len(verts), 1), "colouring the vertices")
        v = torch.as_tensor(verts[s:s + COLOR_CHUNK], dtype=torch.float32, device=dev)
        n = torch.nn.functional.normalize(torch.as_tensor(normals[s:s + COLOR_CHUNK], dtype=torch.float32,
                                                          device=dev), dim=-1)
        r = render_rays(field, source.grid, v + offset * n, -n, opts)
        rgb, alpha = r["rgb"].float(), r["opacity"].float()[:, None]
        col = rgb / alpha.clamp_min(1e-4)  # un-composite the black background
        # a ray that met nothing (a sliver of surface): the field's own colour at the vertex
        miss = alpha[:, 0] < 0.05
        if miss.any():
            col[miss] = field(v[miss], -n[miss], outputs=("rgb",))["rgb"].float()
        out[s:s + len(v)] = col.clamp(0, 1).cpu().numpy()
    return (out * 255 + 0.5).astype(np.uint8)


def drop_small_pieces(mesh, min_fraction: float):
    """The mesh without connected pieces holding fewer than `min_fraction` of its faces (floaters)."""
    import trimesh

    if min_fraction <= 0 or len(mesh.faces) == 0:
        return mesh
    pieces = mesh.split(only_watertight=False)
    keep = [p for p in pieces if len(p.faces) >= min_fraction * len(mesh.faces)]
    if not keep:
        raise UserError(f"--min-component {min_fraction} removed every piece of the mesh", hint="give a smaller value")
    return trimesh.util.concatenate(keep)


def build_mesh(source, opts: MeshOptions, masks=None, cancel: Cancel | None = None,
               progress: Progress | None = None):
    """The coloured trimesh.Trimesh of the field (or the selection) in world units."""
    import trimesh

    check_options(opts)
    lo, hi = field_box(source, opts.bbox)
    res = int(opts.resolution)
    level = float(opts.level) if opts.level is not None else default_level(source)
    region = None
    if opts.selection:
        spacing = float(np.max((hi - lo) / (res - 1)))
        region = selection_region(source, saved_masks(source, masks), lo, hi, cancel, progress, span=(0.0, 0.3),
                                  tolerance=2.0 * spacing)
    volume = density_lattice(source, lo, hi, res, cancel, progress, span=(0.3 if region is not None else 0.0, 0.7))
    if region is not None:
        axes = lattice_points(lo, hi, res)
        occupied = np.nonzero(volume.reshape(-1) > 0)[0]
        for s in range(0, len(occupied), REGION_CHUNK):
            idx = occupied[s:s + REGION_CHUNK]
            ijk = np.unravel_index(idx, volume.shape)
            pts = np.stack([axes[a][ijk[a]] for a in range(3)], -1)
            volume.reshape(-1)[idx[~region.contains(pts)]] = 0.0
    checkpoint(cancel, progress, 0.7, "extracting the surface")
    verts, faces, normals = marching_cubes(volume, level, lo, hi)
    spacing = float(np.max((hi - lo) / (res - 1)))
    colors = vertex_colors(source, verts, normals, COLOR_OFFSET_VOXELS * spacing, cancel, progress, span=(0.75, 0.95))
    world = source.scene.norm.to_world(verts.astype(np.float64))
    mesh = trimesh.Trimesh(world, faces, vertex_normals=normals, vertex_colors=colors, process=False)
    mesh = drop_small_pieces(mesh, float(opts.min_component))
    mesh.metadata["level"] = level
    checkpoint(cancel, progress, 1.0, "mesh ready")
    return mesh


def write_mesh(mesh, path: str | Path) -> Path:
    """Write `mesh` by trimesh in the format of the path's suffix, atomically."""
    path = check_output_file(path, MESH_SUFFIXES, "mesh")
    data = mesh.export(file_type=path.suffix.lower()[1:])
    with atomic_output(path, "mesh") as tmp:
        tmp.write_bytes(data if isinstance(data, bytes) else data.encode("utf-8"))
    return path


def export_mesh(source, path: str | Path, opts: MeshOptions | None = None, masks=None,
                cancel: Cancel | None = None, progress: Progress | None = None) -> dict:
    """Build and write the mesh; returns facts for the message (path, vertices, faces, bytes, seconds)."""
    opts = opts or MeshOptions()
    path = check_output_file(path, MESH_SUFFIXES, "mesh")  # before minutes of work
    t0 = time.perf_counter()
    mesh = build_mesh(source, opts, masks, cancel, progress)
    write_mesh(mesh, path)
    return {"path": str(path), "vertices": int(len(mesh.vertices)), "faces": int(len(mesh.faces)),
            "bytes": path.stat().st_size, "seconds": time.perf_counter() - t0,
            "bounds": mesh.bounds.tolist(), "level": float(mesh.metadata["level"])}
