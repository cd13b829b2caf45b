"""`repaint-nerf export mesh|points|dataset WS --out PATH`: take the workspace's current version elsewhere: a
coloured mesh (.ply/.obj/.glb) or point cloud (.ply) in the scene's world units, of the whole field or the saved
selection, or the renders at the training cameras as a nerfstudio / instant-ngp dataset."""
from __future__ import annotations

import argparse
import contextlib

NAME = "export"
HELP = "export the workspace's current version as a mesh, a point cloud or an edited dataset"


def _common(p: argparse.ArgumentParser, out_help: str) -> None:
    p.add_argument("workspace", help="workspace folder written by `repaint-nerf train`")
    p.add_argument("--out", required=True, help=out_help)
    p.add_argument("--device", default=None, help="cpu, cuda, cuda:1 (default: $REPAINT_NERF_DEVICE, else CUDA if present)")


def _bbox(text: str) -> tuple:
    try:
        vals = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not six numbers xmin,ymin,zmin,xmax,ymax,zmax") from None
    if len(vals) != 6:
        raise argparse.ArgumentTypeError(f"'{text}' has {len(vals)} numbers, not six (xmin,ymin,zmin,xmax,ymax,zmax)")
    return vals


def add_arguments(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="kind", metavar="KIND", required=True)
    m = sub.add_parser("mesh", help="marching-cubes mesh with vertex colours (.ply, .obj, .glb), world units")
    _common(m, "mesh file: .ply, .obj or .glb")
    m.add_argument("--selection", action="store_true", help="only the saved selection's 3D region")
    m.add_argument("--resolution", type=int, default=256, help="lattice points per axis (default 256)")
    m.add_argument("--level", type=float, default=None,
                   help="density iso-level (default: the median density at the surfaces the training views render)")
    m.add_argument("--bbox", type=_bbox, default=None, metavar="X0,Y0,Z0,X1,Y1,Z1",
                   help="only this box, in the scene's world units (default: the whole field)")
    m.add_argument("--min-component", type=float, default=0.0, metavar="FRACTION",
                   help="drop floaters: connected pieces with fewer than this fraction of the faces (e.g. 0.01)")
    pt = sub.add_parser("points", help="coloured surface points from the training views (.ply), world units")
    _common(pt, "point cloud file (.ply)")
    pt.add_argument("--selection", action="store_true", help="only the selected pixels")
    pt.add_argument("--max-points", type=int, default=None, help="keep at most this many points (random subset)")
    d = sub.add_parser("dataset", help="renders at the training cameras + transforms.json (nerfstudio/instant-ngp)")
    _common(d, "output folder (new or empty)")
    d.add_argument("--no-masks", action="store_true", help="leave out the selection's masks (mask_path)")


@contextlib.contextmanager
def _bar(label: str):
    """A tqdm bar driven by an export's progress(fraction, text) callback (none on a pipe: logs stay clean)."""
    from tqdm import tqdm

    with tqdm(total=1000, desc=label, unit="‰", bar_format="{desc} {bar} {percentage:3.0f}% {elapsed}<{remaining} "
              "{postfix}", leave=False, disable=None) as bar:
        def progress(frac: float, text: str) -> None:
            if bar.disable:
                return
            bar.update(int(frac * 1000) - bar.n)
            bar.set_postfix_str(text, refresh=False)

        yield progress


def _size(n: int) -> str:
    return f"{n / 1e6:.2f} MB" if n >= 1e5 else f"{n / 1e3:.1f} kB"


def run(args: argparse.Namespace) -> int:
    from repaint_nerf.core.export.source import open_workspace

    source = open_workspace(args.workspace, args.device)
    with _bar(f"export {args.kind}") as progress:
        if args.kind == "mesh":
            from repaint_nerf.core.export.mesh import MeshOptions, export_mesh

            opts = MeshOptions(args.resolution, args.level, args.bbox, args.min_component, args.selection)
            info = export_mesh(source, args.out, opts, progress=progress)
            what = f"{info['vertices']} vertices, {info['faces']} faces, level {info['level']:.3g}"
        elif args.kind == "points":
            from repaint_nerf.core.export.points import export_points

            info = export_points(source, args.out, args.selection, max_points=args.max_points, progress=progress)
            what = f"{info['points']} points"
        else:
            from repaint_nerf.core.export.dataset import export_dataset

            info = export_dataset(source, args.out, masks=not args.no_masks, progress=progress)
            what = f"{info['frames']} frames" + (" with masks" if info["masks"] else "")
    print(f"wrote {info['path']} ({what}, {_size(info['bytes'])}, {info['seconds']:.1f} s)")
    if args.kind in ("mesh", "points"):
        lo, hi = info["bounds"]
        print("world units (the dataset's own): bounds " + " .. ".join(
            "(" + ", ".join(f"{v:.3f}" for v in c) + ")" for c in (lo, hi)))
    return 0
