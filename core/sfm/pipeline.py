"""The pycolmap phases of structure-from-motion: features, matching, incremental mapping, undistortion.

Each phase is one function so the runner can time it and report progress. Matching is exhaustive
for small sets and sequential (capture order, quadratic overlap) for large ones.
"""
from __future__ import annotations

import contextlib
from collections.abc import Callable
from pathlib import Path

from repaint_nerf.core.colmap import pycolmap
from repaint_nerf.core.errors import SceneError, UserError

MATCHERS = ("auto", "exhaustive", "sequential")
EXHAUSTIVE_MAX = 60  # above this many photos "auto" matches sequentially (pairs grow as n^2)
SEQUENTIAL_OVERLAP = 12
MAX_FEATURES = 8192


@contextlib.contextmanager
def quiet_colmap(level: int = 2):
    """Silence COLMAP's INFO log (glog) during a call; restore the level afterwards."""
    log = getattr(pycolmap, "logging", None)
    old = getattr(log, "minloglevel", None) if log is not None else None
    if old is not None:
        log.minloglevel = level
    try:
        yield
    finally:
        if old is not None:
            log.minloglevel = old


def choose_matcher(matcher: str, n_images: int) -> str:
    """Resolve 'auto' to 'exhaustive' (up to EXHAUSTIVE_MAX photos) or 'sequential'."""
    if matcher not in MATCHERS:
        raise UserError(f"unknown matcher {matcher!r}", hint=f"use one of {', '.join(MATCHERS)}")
    if matcher == "auto":
        return "exhaustive" if n_images <= EXHAUSTIVE_MAX else "sequential"
    return matcher


def extract(db: Path, image_dir: Path, groups: list[list[str]], camera_model: str = "SIMPLE_RADIAL",
            per_image: bool = False) -> None:
    """SIFT features of the files in image_dir into the database; one shared camera per group (image size),
    or one camera per photo with `per_image`.

    One camera per size (not per image) is what makes small sets register: COLMAP's AUTO mode gives
    every photo without EXIF focal length its own intrinsics. A shared camera can also converge to a
    wrong focal length (core.sfm.judge), which is when the runner retries with `per_image`.
    """
    opts = pycolmap.FeatureExtractionOptions()
    opts.sift.max_num_features = MAX_FEATURES
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = camera_model
    mode = pycolmap.CameraMode.PER_IMAGE if per_image else pycolmap.CameraMode.SINGLE
    with quiet_colmap():
        for names in groups:
            pycolmap.extract_features(db, image_dir, image_names=names, camera_mode=mode,
                                      reader_options=reader, extraction_options=opts, device=pycolmap.Device.cpu)


def match(db: Path, kind: str) -> None:
    """Match features ('exhaustive' or 'sequential') and verify pairs geometrically."""
    with quiet_colmap():
        if kind == "exhaustive":
            pycolmap.match_exhaustive(db, device=pycolmap.Device.cpu)
        else:
            pairing = pycolmap.SequentialPairingOptions()
            pairing.overlap = SEQUENTIAL_OVERLAP
            pairing.quadratic_overlap = True
            pycolmap.match_sequential(db, pairing_options=pairing, device=pycolmap.Device.cpu)


def reconstruct(db: Path, image_dir: Path, out_dir: Path, n_images: int, photos_dir: Path,
                on_image: Callable[[int], None] | None = None, seed: int = 0) -> pycolmap.Reconstruction:
    """Incremental mapping; the model with the most registered images. A `SceneError` when none forms."""
    opts = pycolmap.IncrementalPipelineOptions()
    opts.random_seed = seed
    count = [0]

    def next_image():
        count[0] += 1
        if on_image is not None:
            on_image(count[0])

    out_dir.mkdir(parents=True, exist_ok=True)
    with quiet_colmap():
        models = pycolmap.incremental_mapping(db, image_dir, out_dir, options=opts, next_image_callback=next_image)
    if not models:
        raise SceneError(f"structure-from-motion could not register any of the {n_images} photos: they do not "
                         "overlap enough (or show too little texture)", photos_dir,
                         hint="take photos that overlap by more than half, moving around the scene, "
                              "with textured surfaces in view")
    return max(models.values(), key=lambda r: r.num_reg_images())


def undistort(model_dir: Path, image_dir: Path, out_dir: Path) -> Path:
    """Undistort the registered images to pinhole cameras (COLMAP's rule); returns the output scene folder."""
    with quiet_colmap():
        pycolmap.undistort_images(out_dir, model_dir, image_dir, output_type="COLMAP")
    return out_dir
