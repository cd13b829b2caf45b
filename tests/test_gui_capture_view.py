"""The editor's view of a real-capture-like scene (issue 32, item 5): a portrait instant-ngp capture of objects in a
room whose walls lie far beyond the field cube (aabb_scale 4, contracted). The view keeps the photos' aspect, orbits
the objects (not the room's or the cube's centre) and reaches the far walls. Synthetic and small: the room360 preset
at 48 px, cropped to 27x48 portrait photos."""
from __future__ import annotations

import os

import numpy as np
import pytest
import torch

from scene_writers import write_ngp_capture
from test_gui_editor import frames, full_frame, run_until

os.environ.setdefault("REPAINT_NERF_COMPILE", "0")
PORTRAIT = (27, 48)  # w, h: the fox capture's 9:16
ROOM_TARGET = (0.0, 0.0, 0.35)  # world: where the room360 rig's cameras look (the objects on the floor)


@pytest.fixture(scope="module")
def portrait_room(scene_factory, tmp_path_factory):
    """(path, scene): room360 as a portrait instant-ngp capture whose content reaches 4x its unit cube."""
    from repaint_nerf.core.scene.loaders.detect import load_scene

    out = tmp_path_factory.mktemp("portrait_room") / "cap"
    write_ngp_capture(scene_factory("room360", size=PORTRAIT[1], views=10, test_views=2), out,
                      width=PORTRAIT[0], extra={"aabb_scale": 4})
    scene = load_scene(out)
    assert scene.kind == "unbounded" and scene.train.images[0].shape[:2] == (PORTRAIT[1], PORTRAIT[0])
    return out, scene


def test_fit_aspect_fits_the_photo_frame_inside_the_view_area():
    from repaint_nerf.app.camera_control import fit_aspect

    assert fit_aspect(880, 780, 9 / 16) == (220, 0, 439, 780)  # portrait in landscape: bars left and right
    assert fit_aspect(300, 800, 4 / 3) == (0, 287, 300, 225)  # landscape in a tall area: bars above and below
    assert fit_aspect(880, 780, None) == (0, 0, 880, 780)
    x, y, w, h = fit_aspect(1001, 999, 1.0)
    assert (w, h) == (999, 999) and x == 1


def test_orbit_centre_is_the_object_the_cameras_look_at(portrait_room, scene_factory):
    """The framing orbits the point the training cameras look at: the objects, inside the field cube, not the far
    walls (3.3 field units out) nor anything off the view axis; the view starts at a training camera (outside every
    surface). A forward-facing rig (near-parallel views) gets a centre in front of the cameras, between the nearest
    and the farthest content, on the first camera's axis."""
    from repaint_nerf.app.camera_control import CameraControl
    from repaint_nerf.core.scene.loaders.detect import load_scene

    _, scene = portrait_room
    cams = scene.field_cameras("train")
    ctl = CameraControl.framing(cams)
    target = scene.norm.to_field(np.asarray(ROOM_TARGET))
    assert np.linalg.norm(ctl.target - target) < 0.1 * scene.norm.scale * 2.6, (ctl.target, target)
    assert np.allclose(ctl.eye(), cams.c2w[0, :3, 3].double().numpy(), atol=1e-6)

    fwd = load_scene(scene_factory("forward", size=24, views=8, test_views=2))
    assert fwd.kind == "forward"
    cams = fwd.field_cameras("train")
    ctl = CameraControl.framing(cams)
    c2w = cams.c2w[0].double().numpy()
    along = float((ctl.target - c2w[:3, 3]) @ -c2w[:3, 2])
    near, far = fwd.near * fwd.norm.scale, fwd.far * fwd.norm.scale
    assert near <= along <= far, (near, along, far)
    assert np.allclose(ctl.target, c2w[:3, 3] - c2w[:3, 2] * along, atol=1e-6)


class _FarShell(torch.nn.Module):
    """A wall of density on the L-inf shell lo <= |x| <= hi (field units), outside the unit cube, marched as the
    real field it stands in for (its warp's extent and cone)."""

    def __init__(self, real, lo: float, hi: float):
        super().__init__()
        self.real, self.lo, self.hi = real, lo, hi

    def march(self):
        return self.real.march()

    def density(self, x):
        n = x.abs().amax(-1)
        return 50.0 * ((n >= self.lo) & (n <= self.hi)).float()

    def forward(self, x, d, outputs=("rgb",), **kw):
        out = {"sigma": self.density(x)}
        if "rgb" in outputs:
            out["rgb"] = torch.full((x.shape[0], 3), 0.8)
        return out


def test_the_view_reaches_far_content_beyond_the_cube(portrait_room, tmp_path):
    """The editor's renders march a contracted scene to its aabb_scale reach (field units of the cube that holds the
    cameras): a wall beyond the unit cube, near that reach, shows in every pixel of the opening view, at its
    distance."""
    from repaint_nerf.app.camera_control import CameraControl
    from repaint_nerf.core.engine import Engine
    from repaint_nerf.core.field.contraction import contract_extent

    path, scene = portrait_room
    engine = Engine("cpu", features=False, depth=False)
    info = engine.load(path, tmp_path / "ws")
    reach = engine.field.march()[0]
    assert reach == pytest.approx(contract_extent(scene)) and reach > 1.5  # aabb_scale 4, in the grown cube
    lo, hi = 1.0 + 0.6 * (reach - 1.0), 1.0 + 0.9 * (reach - 1.0)
    engine.field = _FarShell(engine.field, lo, hi)
    engine.grid.occupied[:] = True  # a fresh grid: every cell may hold content
    cams = CameraControl.framing(info["cameras"]).cameras(*PORTRAIT)
    out = engine.render(cams, outputs=("rgb", "depth", "opacity"))
    assert out["opacity"].min() > 0.9, out["opacity"].min()
    eye = cams.c2w[0, :3, 3].numpy()
    assert np.abs(eye).max() <= 1.0 and np.median(out["depth"]) > lo - np.abs(eye).max()


@pytest.mark.gui
@pytest.mark.timeout(300)
def test_the_view_shows_a_portrait_capture_upright_in_its_frame(portrait_room, xvfb_display, tmp_path, artifacts_dir):
    """Opened in a landscape window, a portrait capture is shown in its own aspect (pillarboxed, centred), with the
    training camera's fields of view in both directions (neither stretched nor cropped); the bars beside it are
    cleared; 'Photo frame' off fills the area again."""
    import cv2

    from repaint_nerf.app.editor import EditorApp
    from repaint_nerf.app.window import Window
    from repaint_nerf.core.engine import Engine

    path, scene = portrait_room
    window = Window(width=900, height=500)
    app = EditorApp(window, Engine("cpu", features=False, depth=False), str(path), str(tmp_path / "ws"),
                    worker_kwargs={"train_budget_s": 0.05, "rest_s": 0.05})
    try:
        run_until(app, lambda: app.state.scene_info.get("loaded"), timeout=120)
        app.set_training(False)
        shot = run_until(app, lambda: full_frame(app), timeout=120)
        shot = frames(app, 2)
        cv2.imwrite(str(artifacts_dir / "capture_view_portrait.png"), shot[..., ::-1])
        w, h = app.view_size
        assert abs(w / h - PORTRAIT[0] / PORTRAIT[1]) < 2.0 / h, (w, h)
        assert app.last_frame.data["rgb"].shape[1] / app.last_frame.data["rgb"].shape[0] == pytest.approx(w / h, abs=0.05)
        train, view = scene.train.cameras, app.camera.cameras(w, h)
        for f, size in (("fx", "width"), ("fy", "height")):  # the same angles of view as the photos
            assert float(getattr(view, f)[0] / getattr(view, size)[0]) == pytest.approx(
                float(getattr(train, f)[0] / getattr(train, size)[0]), rel=0.03)
        ox, oy = app.image_origin
        left = shot[int(oy) + 5:int(oy) + h - 5, 2:int(ox) - 2].astype(np.int32)
        assert left.shape[1] > 50 and np.ptp(left.reshape(-1, 3), axis=0).max() <= 2, "the bar beside the frame is plain"
        image = shot[int(oy):int(oy) + h, int(ox):int(ox) + w].astype(np.int32)
        assert image.std() > 5, "the render fills the frame"
        app.state.photo_frame = False
        frames(app, 2)
        assert app.view_size[0] > app.view_size[1] and app.image_origin[0] < ox
    finally:
        app.close()
        window.close()
