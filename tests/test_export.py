"""Exports read back by independent readers: meshes and point clouds by trimesh (vertex counts, bounds in world
units against the field's known content, colours against the field), datasets by our own loader (and trained on),
plus bad input and cancelled exports leaving no file."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch
import trimesh

from repaint_nerf.core.errors import UserError
from repaint_nerf.core.export.common import ExportCancelled
from repaint_nerf.core.export.dataset import export_dataset
from repaint_nerf.core.export.mesh import MeshOptions, export_mesh
from repaint_nerf.core.export.points import export_points
from repaint_nerf.core.export.source import ExportSource
from repaint_nerf.core.render.analytic import SphereField
from repaint_nerf.core.render.occupancy import OccupancyGrid
from repaint_nerf.core.scene.scene import Normalization, Scene, SceneSplit
from repaint_scene import BALL_RGB, make_field, make_grid, make_scene

NORM = Normalization(np.array([1.0, -2.0, 0.5]), 0.5)  # world = field / 0.5 + centre


def _in_world(scene: Scene, norm: Normalization) -> Scene:
    """The same scene with world units that differ from field space (field cameras unchanged)."""
    splits = {}
    for name, s in scene.splits.items():
        c2w = s.cameras.c2w.clone()
        c2w[:, :3, 3] = norm.to_world(c2w[:, :3, 3])
        splits[name] = SceneSplit(s.cameras.with_poses(c2w), s.images, s.names, s.paths)
    return Scene(root=scene.root, format=scene.format, splits=splits, norm=norm, background=scene.background)


@pytest.fixture(scope="module")
def ball_scene():
    """A red ball (radius 0.35 at the field origin) on a checker slab, 6 views, with the ball's masks."""
    scene, masks = make_scene()
    field = make_field()
    return ExportSource(field, make_grid(field), _in_world(scene, NORM), None, 256), masks


def _sphere_source(**kw) -> ExportSource:
    field = SphereField(center=(0.1, 0.0, 0.0), radius=0.5, sigma=500.0, **kw)
    grid = OccupancyGrid(32, bound=1.0, device="cpu")
    grid.update(0, field.density)
    return ExportSource(field, grid, Scene(root=".", format="test", splits={}, norm=NORM), None, 512)


@pytest.mark.parametrize("suffix", [".ply", ".obj", ".glb"])
def test_sphere_mesh_in_world_units_with_field_colours(tmp_path, suffix):
    src = _sphere_source(color_slope=2.0)
    info = export_mesh(src, tmp_path / f"ball{suffix}", MeshOptions(resolution=48))
    mesh = trimesh.load(tmp_path / f"ball{suffix}", force="mesh")
    assert len(mesh.vertices) == info["vertices"] > 500 and len(mesh.faces) > 500
    centre = NORM.to_world(np.array([0.1, 0.0, 0.0]))
    r = np.linalg.norm(mesh.vertices - centre, axis=1)
    voxel = 2.0 / 47 / NORM.scale  # one lattice spacing in world units
    assert np.all(np.abs(r - 0.5 / NORM.scale) < voxel)  # radius 0.5 field = 1.0 world
    ref = src.field.color(torch.as_tensor(NORM.to_field(mesh.vertices), dtype=torch.float32)).detach().numpy()
    got = mesh.visual.vertex_colors[:, :3] / 255.0
    assert np.median(np.abs(got - ref)) < 0.02 and np.abs(got - ref).max() < 0.1
    assert not list(tmp_path.glob(".*.tmp")) and (tmp_path / f"ball{suffix}").stat().st_mode & 0o777 == 0o644


def test_normals_point_out_and_bbox_cuts_in_world_units(tmp_path):
    src = _sphere_source()
    centre = NORM.to_world(np.array([0.1, 0.0, 0.0]))
    box = (*(centre - 2.0), centre[0] + 2.0, centre[1] + 2.0, centre[2])  # the lower half of the ball
    export_mesh(src, tmp_path / "half.ply", MeshOptions(resolution=40, bbox=box))
    mesh = trimesh.load(tmp_path / "half.ply")
    assert mesh.vertices[:, 2].max() <= centre[2] + 1e-6 and mesh.vertices[:, 2].min() < centre[2] - 0.9
    assert mesh.is_watertight and mesh.volume > 0  # closed by the box, faces wound outwards
    normals = trimesh.Trimesh(mesh.vertices, mesh.faces).vertex_normals  # from the winding, not the file
    outward = np.einsum("ij,ij->i", normals, mesh.vertices - centre)
    assert np.mean(outward > 0) > 0.6  # the sphere's part (the flat cap's normals point down, also out)


def test_floaters_dropped_on_request(tmp_path):
    class TwoBalls(SphereField):
        def shape(self, x):
            small = ((x - torch.tensor([-0.7, -0.7, -0.7])).norm(dim=-1) <= 0.12).to(x.dtype)
            return torch.maximum(super().shape(x), small)

    field = TwoBalls(radius=0.5, sigma=500.0)
    grid = OccupancyGrid(32, bound=1.0, device="cpu")
    grid.update(0, field.density)
    src = ExportSource(field, grid, Scene(root=".", format="test", splits={}, norm=NORM), None, 512)
    export_mesh(src, tmp_path / "both.ply", MeshOptions(resolution=48))
    export_mesh(src, tmp_path / "clean.ply", MeshOptions(resolution=48, min_component=0.2))
    both, clean = trimesh.load(tmp_path / "both.ply"), trimesh.load(tmp_path / "clean.ply")
    assert len(both.split(only_watertight=False)) == 2 and len(clean.split(only_watertight=False)) == 1
    assert np.linalg.norm(clean.vertices - NORM.to_world(np.zeros(3)), axis=1).max() < 0.6 / NORM.scale


def test_selection_mesh_holds_the_selected_ball_only(ball_scene, tmp_path):
    src, masks = ball_scene
    export_mesh(src, tmp_path / "all.ply", MeshOptions(resolution=48))
    export_mesh(src, tmp_path / "ball.ply", MeshOptions(resolution=48, selection=True), masks=masks)
    whole, ball = trimesh.load(tmp_path / "all.ply"), trimesh.load(tmp_path / "ball.ply")
    origin = NORM.to_world(np.zeros(3))
    r_ball = np.linalg.norm(ball.vertices - origin, axis=1) * NORM.scale  # field units
    assert len(ball.vertices) > 200 and np.percentile(r_ball, 95) < 0.5  # the ball (radius 0.35), not the slab
    assert np.linalg.norm(whole.vertices - origin, axis=1).max() * NORM.scale > 1.0  # the slab's corners
    colours = ball.visual.vertex_colors[:, :3] / 255.0
    near = r_ball < 0.4
    assert np.median(np.abs(colours[near] - BALL_RGB), axis=0).max() < 0.08


def test_points_on_the_ball_with_its_colour(ball_scene, tmp_path):
    src, masks = ball_scene
    info = export_points(src, tmp_path / "ball_pts.ply", selection=True, masks=masks)
    cloud = trimesh.load(tmp_path / "ball_pts.ply")
    assert isinstance(cloud, trimesh.PointCloud) and len(cloud.vertices) == info["points"] > 50
    r = np.linalg.norm(cloud.vertices - NORM.to_world(np.zeros(3)), axis=1) * NORM.scale
    assert np.median(np.abs(r - 0.35)) < 0.05
    assert np.median(np.abs(cloud.colors[:, :3] / 255.0 - BALL_RGB), axis=0).max() < 0.08
    export_points(src, tmp_path / "few.ply", max_points=40)
    assert len(trimesh.load(tmp_path / "few.ply").vertices) == 40


def test_bad_input_gets_clear_messages_and_no_file(ball_scene, tmp_path):
    src, masks = ball_scene
    with pytest.raises(UserError, match="no surface at density level"):
        export_mesh(src, tmp_path / "m.ply", MeshOptions(resolution=16, level=1e9))
    with pytest.raises(UserError, match="selection is empty"):
        export_mesh(src, tmp_path / "m.ply", MeshOptions(resolution=16, selection=True),
                    masks=[np.zeros_like(m) for m in masks])
    with pytest.raises(UserError, match="nothing is selected"):
        export_points(src, tmp_path / "p.ply", selection=True)
    with pytest.raises(UserError, match="format"):
        export_mesh(src, tmp_path / "m.stl")
    (tmp_path / "a_file").write_text("not a folder")  # unwritable even for root
    with pytest.raises(UserError, match="cannot make the folder") as err:
        export_mesh(src, tmp_path / "a_file" / "m.ply", MeshOptions(resolution=16))
    assert "a_file" in str(err.value)
    with pytest.raises(ExportCancelled):
        export_mesh(src, tmp_path / "m.ply", MeshOptions(resolution=16), cancel=lambda: True)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a_file"]


def test_cancel_midway_leaves_no_file(ball_scene, tmp_path):
    src, _ = ball_scene
    calls = []

    def cancel():  # stop during the vertex colouring, after the density is sampled
        calls.append(1)
        return len(calls) > 40

    import repaint_nerf.core.export.mesh as mesh_mod

    old = mesh_mod.COLOR_CHUNK
    mesh_mod.COLOR_CHUNK = 64
    try:
        with pytest.raises(ExportCancelled):
            export_mesh(src, tmp_path / "m.glb", MeshOptions(resolution=48), cancel=cancel)
    finally:
        mesh_mod.COLOR_CHUNK = old
    assert list(tmp_path.iterdir()) == []


def test_dataset_round_trip_through_our_loader(ball_scene, tmp_path):
    from repaint_nerf.core.scene.loaders.detect import load_scene
    from repaint_nerf.core.train.stage1 import Stage1Trainer, TrainConfig

    src, masks = ball_scene
    info = export_dataset(src, tmp_path / "edited", masks=masks)
    assert (tmp_path / "edited").stat().st_mode & 0o777 == 0o755
    meta = json.loads((tmp_path / "edited" / "transforms.json").read_text())
    assert info["frames"] == 6 and meta["w"] == meta["h"] == 16 and "fl_x" in meta
    assert all("mask_path" in f for f in meta["frames"])
    scene = load_scene(tmp_path / "edited", 1.0)
    assert len(scene.train) == 6 and scene.background == (1.0, 1.0, 1.0)
    # same world cameras and the same normalisation -> the same field-space cameras
    assert torch.allclose(scene.train.cameras.c2w.float(), src.scene.train.cameras.c2w.float(), atol=1e-5)
    assert torch.allclose(scene.field_cameras("train").c2w.float(), src.scene.field_cameras("train").c2w.float(),
                          atol=1e-4)
    import cv2

    img = cv2.imread(str(tmp_path / "edited" / meta["frames"][0]["file_path"]), cv2.IMREAD_UNCHANGED)
    assert img.shape == (16, 16, 4)
    mask = cv2.imread(str(tmp_path / "edited" / meta["frames"][0]["mask_path"]), cv2.IMREAD_GRAYSCALE)
    assert np.array_equal(mask > 127, masks[0])
    # the loader's composited image is the render on the scene's background (the photos it was trained on)
    rgba = scene.train.images[0].astype(np.float64) / 255
    composited = rgba[..., :3] * rgba[..., 3:] + (1 - rgba[..., 3:]) * np.asarray(scene.background)
    assert np.abs(composited * 255 - src.scene.train.images[0]).mean() < 4
    trainer = Stage1Trainer(scene, None, TrainConfig(rays_per_batch=256, max_samples=64, grid_resolution=16))
    losses = [trainer.step()["loss"] for _ in range(3)]
    assert all(np.isfinite(losses))
    with pytest.raises(UserError, match="not empty"):
        export_dataset(src, tmp_path / "edited")
