"""COLMAP sparse models (binary or text) read with pycolmap, images from `images/` (or `images_N/`).

Poses are converted from COLMAP's world-to-camera OpenCV convention to OpenGL camera-to-world once,
here; images of non-pinhole camera models are undistorted; the sparse points and their colours
become `scene.points`. Registered images sorted by name; every 8th is test.
"""
from __future__ import annotations

import math
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np

from repaint_nerf.core.colmap import pycolmap
from repaint_nerf.core.errors import SceneError
from repaint_nerf.core.scene.cameras import Cameras, opencv_to_opengl
from repaint_nerf.core.scene.loaders.common import (TEST_EVERY, check_pose, every_eighth_split, holdout_note,
                                                    load_split, wanted)
from repaint_nerf.core.scene.loaders.images import list_images, read_image
from repaint_nerf.core.scene.loaders.undistort import undistort_image, undistorted_camera
from repaint_nerf.core.scene.scene import Scene

MODEL_FILES = ("cameras.bin", "cameras.txt")


def has_model(folder: Path) -> bool:
    """Whether `folder` directly holds a COLMAP model (cameras, images and points files)."""
    return any((folder / f).is_file() for f in MODEL_FILES)


def find_model(root: Path) -> Path | None:
    """The model folder of a COLMAP scene: `sparse/0`, `sparse/`, or `root` itself; None when absent."""
    for cand in (root / "sparse" / "0", root / "sparse", root):
        if has_model(cand):
            return cand
    sparse = root / "sparse"
    if sparse.is_dir():
        subs = sorted(p for p in sparse.iterdir() if p.is_dir() and has_model(p))
        if subs:
            return subs[0]
    return None


PROBE_TIMEOUT_S = 20.0  # seconds of CPU time, plus 1 s per 10 MB of .bin files
PROBE_WALL_FACTOR = 30  # the wall-clock backstop, in probe time limits: a busy machine slows the probe, not its CPU
_PROBE = """
import sys
try:
    import resource
except ImportError:
    resource = None
mem, cpu = int(sys.argv[2]), int(sys.argv[3])
for name, soft, hard in (("RLIMIT_AS", mem, mem), ("RLIMIT_CPU", cpu, cpu + 1)):  # SIGXCPU at soft, SIGKILL at hard
    try:  # each on its own: a system that refuses the memory limit (macOS) still gets the CPU-time one
        resource.setrlimit(getattr(resource, name), (soft, hard))
    except (AttributeError, ValueError, OSError):
        pass
import pycolmap
pycolmap.Reconstruction().read(sys.argv[1])
"""


def probe_binary_model(model: Path) -> None:
    """Read a binary model once in a child process (memory- and CPU-time-limited) before reading it here: on some
    corrupt .bin files (a count or track length turned huge) pycolmap loops forever or aborts the process. The limit
    is CPU time, not wall time: on a busy machine a sound model took over 20 s of wall time to read and was called
    corrupt."""
    size = sum(f.stat().st_size for f in model.glob("*.bin"))
    if size == 0:
        return
    cpu = int(math.ceil(PROBE_TIMEOUT_S + size / 10e6))
    limit = 4 * 1024 ** 3 + 50 * size
    wall = cpu * (PROBE_WALL_FACTOR if _cpu_limits() else 1)
    hint = "re-export the model (colmap model_converter) or run structure-from-motion again"
    try:
        r = subprocess.run([sys.executable, "-c", _PROBE, str(model), str(limit), str(cpu)], capture_output=True,
                           timeout=wall)
    except subprocess.TimeoutExpired:
        raise SceneError(f"reading the COLMAP model did not finish in {wall} s: a .bin file is corrupt", model,
                         hint=hint) from None
    xcpu = getattr(signal, "SIGXCPU", None)
    if xcpu is not None and r.returncode == -xcpu:  # the CPU-time limit
        raise SceneError(f"reading the COLMAP model did not finish in {cpu} s of CPU time: a .bin file is corrupt",
                         model, hint=hint)
    if r.returncode != 0:
        lines = [ln for ln in r.stderr.decode(errors="replace").splitlines() if ln.strip()]
        why = lines[-1].strip()[:200] if lines else f"exit status {r.returncode}"
        raise SceneError(f"cannot read the COLMAP model: a .bin file is corrupt ({why})", model, hint=hint)


def _cpu_limits() -> bool:
    """Whether a child process's CPU time can be limited here (POSIX `resource`)."""
    try:
        import resource  # noqa: F401
    except ImportError:
        return False
    return True


def photos_beside(model: Path) -> Path | None:
    """A folder of photos beside a model folder (`images/`, or `input/` where 3D Gaussian Splatting's convert.py
    keeps the photos as taken), from which structure-from-motion can recover the poses; None when there is none."""
    from repaint_nerf.core.scene.loaders.images import list_images

    root = model.parent.parent if model.parent.name == "sparse" else model.parent
    for cand in (root / "images", root / "input"):
        if list_images(cand):
            return cand
    return None


def read_model(model: Path) -> pycolmap.Reconstruction:
    """Read a model folder with pycolmap; a partial or corrupt model is a `SceneError`."""
    for stem in ("cameras", "images", "points3D"):
        if not ((model / f"{stem}.bin").is_file() or (model / f"{stem}.txt").is_file()):
            photos = photos_beside(model)
            again = (f"or recover the poses from the photos: open {photos} (structure-from-motion runs once and is "
                     "cached beside them)" if photos is not None else "or run structure-from-motion again")
            raise SceneError(f"the COLMAP model is incomplete: {stem}.bin / {stem}.txt is missing", model,
                             hint=f"re-export the model (colmap model_converter) {again}")
    probe_binary_model(model)
    try:
        rec = pycolmap.Reconstruction()
        rec.read(str(model))
    except Exception as exc:  # noqa: BLE001 - pycolmap raises plain RuntimeError/ValueError on bad files
        raise SceneError(f"cannot read the COLMAP model ({exc})", model) from exc
    return rec


def check_camera(cam: pycolmap.Camera, model: Path) -> pycolmap.Camera:
    """A camera with a positive size, finite parameters and positive focal lengths, else a `SceneError`."""
    params = np.asarray(cam.params, dtype=np.float64)
    if cam.width < 1 or cam.height < 1 or not np.all(np.isfinite(params)) or \
            min(cam.focal_length_x, cam.focal_length_y) <= 0:
        raise SceneError(f"camera {cam.camera_id} is invalid ({cam.model_name} {cam.width}x{cam.height}, "
                         f"params {params.tolist()}): the model is corrupt", model,
                         hint="re-export the model or run structure-from-motion again")
    return cam


def _registered(im) -> bool:
    flag = getattr(im, "has_pose", None)
    return bool(flag if flag is not None else getattr(im, "registered", True))


def _image_dir(root: Path, downscale: float) -> Path:
    if float(downscale).is_integer() and downscale > 1 and (root / f"images_{int(downscale)}").is_dir():
        return root / f"images_{int(downscale)}"
    return root / "images"


def load_colmap(root: Path, downscale: float = 1.0, splits=None, max_size: int = 0,
                holdout_every: int = TEST_EVERY) -> Scene:
    """Load a COLMAP scene folder (with `sparse/0` or `sparse/` and `images/`); `max_size` as in load_split;
    every `holdout_every`-th image (by name) is the test split."""
    root = Path(root)
    model = find_model(root)
    if model is None:
        raise SceneError("no COLMAP model found (expected cameras/images/points3D .bin or .txt in sparse/0 or "
                         "sparse/)", root / "sparse" if (root / "sparse").exists() else root,
                         hint="run structure-from-motion (`repaint-nerf sfm`) or point to the model folder")
    rec = read_model(model)
    images = sorted((im for im in rec.images.values() if _registered(im)), key=lambda im: im.name)
    if not images:
        raise SceneError("the COLMAP model has no registered images", model)
    img_dir = _image_dir(root, downscale)
    if not img_dir.is_dir() and model == root:
        img_dir = root  # a bare model folder with the images beside it
    paths, poses, cams = [], [], []
    for im in images:
        p = img_dir / im.name
        if Path(im.name).is_absolute() or not p.resolve().is_relative_to(img_dir.resolve()):
            raise SceneError(f"image name '{im.name}' points outside the image folder", model,
                             hint="COLMAP image names are paths relative to the images/ folder")
        if not p.is_file():
            raise SceneError(f"image '{im.name}' of the COLMAP model not found in {img_dir}", p,
                             hint="put the images the model was built from in images/")
        w2c = np.eye(4)
        cfw = im.cam_from_world  # a method in pycolmap 4, a property in 3.x
        w2c[:3, :4] = (cfw() if callable(cfw) else cfw).matrix()
        if not np.all(np.isfinite(w2c)):
            raise SceneError(f"image '{im.name}': the pose contains NaN or infinite values", model)
        c2w = check_pose(opencv_to_opengl(np.linalg.inv(w2c)), model, f"image '{im.name}'")
        paths.append(p)
        poses.append(c2w)
        cams.append(check_camera(rec.cameras[im.camera_id], model))
    pins = np.asarray([undistorted_camera(c) for c in cams], dtype=np.float64)
    cameras = Cameras.create(np.stack(poses), pins[:, 0], pins[:, 1], pins[:, 2], pins[:, 3], pins[:, 4], pins[:, 5])

    def reader(i: int, p: Path) -> np.ndarray:
        img = read_image(p)
        cam = cams[i]
        if (img.shape[1], img.shape[0]) != (cam.width, cam.height):
            if (img.shape[0], img.shape[1]) == (cam.width, cam.height) or \
                    abs(img.shape[1] / img.shape[0] - cam.width / cam.height) > 0.01 * cam.width / cam.height:
                img = read_image(p, orient=False)  # COLMAP saw the stored pixels, not the EXIF-rotated ones
            cam = pycolmap.Camera(cam.todict())
            cam.rescale(int(img.shape[1]), int(img.shape[0]))
        return undistort_image(img, cam)[0]

    tr, te = every_eighth_split(len(images), holdout_every)
    out = {}
    for name, idx in (("train", tr), ("test", te)):
        if idx and wanted(name, splits):
            out[name] = load_split(cameras[idx], [paths[i] for i in idx], [images[i].name for i in idx], downscale,
                                   reader=lambda k, p, idx=idx: reader(idx[k], p), max_size=max_size)
    pts = rec.points3D
    points = np.asarray([pt.xyz for pt in pts.values()], dtype=np.float64).reshape(-1, 3)
    colors = np.asarray([pt.color for pt in pts.values()], dtype=np.uint8).reshape(-1, 3)
    models = sorted({c.model_name for c in cams})
    return Scene(root=root, format="colmap", splits=out, points=points if len(points) else None,
                 point_colors=colors if len(points) else None,
                 extra={"model_dir": str(model), "camera_models": models,
                        "holdout": holdout_note(holdout_every, "image names sorted")})
