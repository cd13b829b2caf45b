"""Undistortion of images from non-pinhole camera models (COLMAP models, nerfstudio k1.. / p1..).

The undistorted pinhole camera is chosen by pycolmap (`undistort_camera`, COLMAP's own rule); the
pixels are resampled with cv2.remap through pycolmap's exact projection of the distorted model, so
every COLMAP model works and RGBA images keep their alpha.
"""
from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np

from repaint_nerf.core.colmap import pycolmap

PINHOLE_MODELS = ("SIMPLE_PINHOLE", "PINHOLE")


def make_camera(model: str, params, width: int, height: int) -> pycolmap.Camera:
    """A pycolmap camera of `model` (e.g. 'OPENCV') with its parameter list in COLMAP order."""
    cam = pycolmap.Camera.create_from_model_name(1, model, 1.0, int(width), int(height))
    cam.params = np.asarray(params, dtype=np.float64)
    return cam


def needs_undistortion(cam: pycolmap.Camera) -> bool:
    """True unless the model is a pinhole or all its distortion parameters are zero."""
    if cam.model_name in PINHOLE_MODELS:
        return False
    extra = np.asarray(cam.params)[list(cam.extra_params_idxs())]
    return bool(np.any(extra != 0.0)) or "FISHEYE" in cam.model_name


def pinhole_of(cam: pycolmap.Camera) -> tuple[float, float, float, float, int, int]:
    """(fx, fy, cx, cy, width, height) of a camera, ignoring any distortion."""
    return (float(cam.focal_length_x), float(cam.focal_length_y), float(cam.principal_point_x),
            float(cam.principal_point_y), int(cam.width), int(cam.height))


def _key(cam: pycolmap.Camera) -> tuple:
    return cam.model_name, tuple(float(p) for p in cam.params), int(cam.width), int(cam.height)


@lru_cache(maxsize=16)
def _maps(key: tuple):
    model, params, width, height = key
    cam = make_camera(model, params, width, height)
    new = pycolmap.undistort_camera(pycolmap.UndistortCameraOptions(), cam)
    w, h = int(new.width), int(new.height)
    vv, uu = np.meshgrid(np.arange(h, dtype=np.float64) + 0.5, np.arange(w, dtype=np.float64) + 0.5, indexing="ij")
    xy = new.cam_from_img(np.stack([uu.ravel(), vv.ravel()], axis=1))
    src = cam.img_from_cam(np.hstack([xy, np.ones((xy.shape[0], 1))]), check_cheirality=False)
    # cv2 samples with pixel centres at integers; COLMAP puts them at +0.5.
    map_x = (src[:, 0] - 0.5).reshape(h, w).astype(np.float32)
    map_y = (src[:, 1] - 0.5).reshape(h, w).astype(np.float32)
    return map_x, map_y, pinhole_of(new)


def undistorted_camera(cam: pycolmap.Camera) -> tuple[float, float, float, float, int, int]:
    """The pinhole (fx, fy, cx, cy, width, height) that `undistort_image` produces for `cam`."""
    if not needs_undistortion(cam):
        return pinhole_of(cam)
    return _maps(_key(cam))[2]


def undistort_image(img: np.ndarray, cam: pycolmap.Camera) -> tuple[np.ndarray, tuple]:
    """Resample an image of camera `cam` (its size must match) to its undistorted pinhole camera.

    Returns (image, (fx, fy, cx, cy, width, height)); pixels that fall outside the source are black.
    """
    if not needs_undistortion(cam):
        return img, pinhole_of(cam)
    map_x, map_y, pin = _maps(_key(cam))
    out = cv2.remap(img, map_x, map_y, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                    borderValue=0)
    return out, pin
