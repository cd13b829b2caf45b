"""Object masks shipped beside a capture's images (NeRD's turntable layout, `masks/` next to `images/`): they become
the images' alpha, matched by file stem, decoded at a reduced size when far larger than the images; a capture with
masks for only some images keeps its full images; nerfacto's side-by-side run gets the same cut-outs."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from repaint_nerf.core.errors import SceneError, SceneWarning
from repaint_nerf.core.scene.loaders.detect import load_scene
from repaint_nerf.core.scene.loaders.summary import format_summary, scene_summary
from scene_writers import ring_poses, write_image, write_llff

H, W, N = 12, 16, 10


def _disc(h: int, w: int, i: int) -> np.ndarray:
    """A uint8 mask: an ellipse whose size follows the image index (so a mismatched mask is noticed)."""
    yy, xx = np.mgrid[0:h, 0:w]
    r = 0.25 + 0.02 * i
    return np.where(((xx + 0.5) / w - 0.5) ** 2 + ((yy + 0.5) / h - 0.5) ** 2 < r * r, 255, 0).astype(np.uint8)


def _turntable(root: Path, scale: int = 8, folder: str = "masks", ext: str = ".jpg", skip=()) -> list[np.ndarray]:
    """An LLFF capture with cameras around a centre and one mask per image, `scale` times the image size, named
    with the image's stem and another extension (as NeRD ships them: DSC_0007.JPG and masks/DSC_0007.jpg)."""
    write_llff(root, ring_poses(N), H, W, 14.0, np.tile([2.0, 6.0], (N, 1)))
    masks = []
    for i in range(N):
        m = _disc(H * scale, W * scale, i)
        masks.append(m)
        if i not in skip:
            write_image(root / folder / f"IMG_{i:03d}{ext}", m)
    return masks


def test_masks_become_the_images_alpha_matched_by_stem(tmp_path):
    masks = _turntable(tmp_path / "cap")
    scene = load_scene(tmp_path / "cap")
    train = scene.split("train")
    assert train.images[0].shape == (H, W, 4) and scene.extra["masks_dir"] == "masks"
    for name, img in zip(train.names, train.images):
        i = int(Path(name).stem.split("_")[1])
        want = cv2.resize(masks[i], (W, H), interpolation=cv2.INTER_AREA)  # the plain reference: full decode
        assert np.abs(img[..., 3].astype(int) - want.astype(int)).max() <= 40, name  # JPEG and reduced decode
        assert (img[..., 3] > 128).mean() == pytest.approx((want > 128).mean(), abs=0.05)
    assert scene.kind == "bounded" and scene.split("test").images[0].shape[-1] == 4
    text = format_summary(scene_summary(scene))
    assert "object masks in masks/" in text and "white for evaluation" in text


def test_masks_for_only_some_images_are_not_used_and_say_so(tmp_path):
    _turntable(tmp_path / "cap", ext=".png", skip=(3,))
    with pytest.warns(SceneWarning, match="9 of 10 images have a mask.*IMG_003"):
        scene = load_scene(tmp_path / "cap")
    assert scene.split("train").images[0].shape[-1] == 3 and "masks_dir" not in scene.extra


def test_a_mask_of_another_aspect_is_a_clear_error(tmp_path):
    _turntable(tmp_path / "cap", scale=1, ext=".png")
    write_image(tmp_path / "cap" / "masks" / "IMG_001.png", np.zeros((H, H), np.uint8))
    with pytest.raises(SceneError, match="IMG_001.png.*aspect"):
        load_scene(tmp_path / "cap")


def test_nerfacto_trains_and_scores_the_same_cut_outs_on_white(tmp_path):
    from repaint_nerf.core.bench.nerfacto import export_scene, train_command

    _turntable(tmp_path / "cap", scale=2, ext=".png")
    scene = load_scene(tmp_path / "cap")
    meta = export_scene(scene, tmp_path / "ns")
    written = cv2.imread(str(tmp_path / "ns" / meta["test_filenames"][0]), cv2.IMREAD_UNCHANGED)
    assert written.shape == (H, W, 4)
    assert np.array_equal(written[..., 3], scene.split("test").images[0][..., 3])
    cmd = train_command(Path("/venv/bin"), tmp_path / "ns", tmp_path / "out", 25, alpha=True)
    assert cmd[cmd.index("--pipeline.model.background-color") + 1] == "white"
    assert "--pipeline.model.background-color" not in train_command(Path("/v"), tmp_path, tmp_path, 25)
