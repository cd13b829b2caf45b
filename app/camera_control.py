"""The editor's viewpoint: orbit, pan, zoom, snap and field of view, in the one camera convention.

The state is a target point, a distance and two angles around a scene up axis; `c2w()` returns an
OpenGL camera-to-world pose (looks down -z, +y up) as `core.scene.cameras` defines, so the renderer
sees exactly what a training camera would.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from repaint_nerf.core.scene.cameras import Cameras, look_at


def fit_aspect(width: float, height: float, aspect: float | None) -> tuple[int, int, int, int]:
    """(x, y, w, h): the largest rectangle of `aspect` (width / height) centred in a width x height area, in whole
    pixels (the area itself for no aspect). The view shows a capture's photo frame this way: a portrait capture in a
    landscape window is neither stretched nor cropped, and the sides nobody photographed are not rendered."""
    width, height = max(int(width), 1), max(int(height), 1)
    if not aspect or not math.isfinite(aspect) or aspect <= 0:
        return 0, 0, width, height
    w, h = (width, max(round(width / aspect), 1)) if width / height < aspect else (max(round(height * aspect), 1), height)
    w, h = min(w, width), min(h, height)
    return (width - w) // 2, (height - h) // 2, w, h


def _unit(v: np.ndarray) -> np.ndarray:
    n = float(np.linalg.norm(v))
    return v / n if n > 1e-12 else v


@dataclass
class CameraControl:
    """An orbit camera around `target` at `distance`, with yaw/pitch about `up`, in field coordinates."""

    target: np.ndarray = field(default_factory=lambda: np.zeros(3))
    distance: float = 3.0
    yaw: float = 0.0  # radians around `up`
    pitch: float = 0.3  # radians above the horizontal plane
    fov_y: float = 50.0  # degrees
    up: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))
    orbit_speed: float = 0.01  # radians per pixel
    home: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.target = np.asarray(self.target, dtype=np.float64)
        self.up = _unit(np.asarray(self.up, dtype=np.float64))
        self.set_home()

    # --- basis around the up axis
    def _basis(self) -> tuple[np.ndarray, np.ndarray]:
        """Two unit vectors spanning the plane orthogonal to `up` (yaw 0 points along the first)."""
        ref = np.array([1.0, 0.0, 0.0]) if abs(self.up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        e1 = _unit(ref - self.up * float(ref @ self.up))
        e2 = np.cross(self.up, e1)
        return e1, e2

    def eye(self) -> np.ndarray:
        e1, e2 = self._basis()
        cp = math.cos(self.pitch)
        offset = (e1 * math.cos(self.yaw) * cp + e2 * math.sin(self.yaw) * cp + self.up * math.sin(self.pitch))
        return self.target + self.distance * offset

    def c2w(self) -> np.ndarray:
        """OpenGL camera-to-world pose (4x4 float64)."""
        return look_at(self.eye(), self.target, up=self.up)

    def cameras(self, width: int, height: int) -> Cameras:
        """A one-camera `Cameras` of the current view at width x height pixels."""
        fy = 0.5 * height / math.tan(math.radians(self.fov_y) * 0.5)
        return Cameras.create(self.c2w(), fy, fy, width * 0.5, height * 0.5, width, height)

    # --- interaction
    def orbit(self, dx: float, dy: float) -> None:
        """Rotate around the target by a mouse drag of (dx, dy) pixels (right/down positive)."""
        self.yaw -= dx * self.orbit_speed
        self.pitch = float(np.clip(self.pitch + dy * self.orbit_speed, -1.55, 1.55))

    def pan(self, dx: float, dy: float, viewport_height: int) -> None:
        """Move the target in the image plane so the scene follows a drag of (dx, dy) pixels."""
        m = self.c2w()
        per_px = 2.0 * self.distance * math.tan(math.radians(self.fov_y) * 0.5) / max(viewport_height, 1)
        self.target = self.target - m[:3, 0] * dx * per_px + m[:3, 1] * dy * per_px

    def zoom(self, steps: float) -> None:
        """Dolly towards (positive steps) or away from the target."""
        self.distance = float(np.clip(self.distance * (0.9 ** steps), 1e-3, 1e4))

    def set_fov(self, degrees: float) -> None:
        self.fov_y = float(np.clip(degrees, 10.0, 120.0))

    def snap_to(self, c2w: np.ndarray, fov_y: float | None = None) -> None:
        """Take the pose of a (training) camera: keep its eye and viewing direction exactly."""
        c2w = np.asarray(c2w, dtype=np.float64)
        eye, forward = c2w[:3, 3], -_unit(c2w[:3, 2])
        # Aim at the point along the view ray closest to the current target, so orbiting stays natural.
        depth = max(float((self.target - eye) @ forward), 1e-2)
        self.target = eye + forward * depth
        self.distance = depth
        back = -forward
        self.pitch = math.asin(float(np.clip(back @ self.up, -1.0, 1.0)))
        e1, e2 = self._basis()
        self.yaw = math.atan2(float(back @ e2), float(back @ e1))
        if fov_y is not None:
            self.fov_y = float(fov_y)

    def set_home(self) -> None:
        """Remember the current view as the one `reset()` returns to."""
        self.home = dict(target=self.target.copy(), distance=self.distance, yaw=self.yaw,
                         pitch=self.pitch, fov_y=self.fov_y)

    def reset(self) -> None:
        for k, v in self.home.items():
            setattr(self, k, v.copy() if isinstance(v, np.ndarray) else v)

    def state(self) -> tuple:
        """A hashable summary; equal states render the same image."""
        return (tuple(np.round(self.target, 9)), round(self.distance, 9), round(self.yaw, 9),
                round(self.pitch, 9), round(self.fov_y, 9))

    @staticmethod
    def framing(cameras: Cameras) -> "CameraControl":
        """A control that orbits the centre the given cameras look at, with their mean up vector."""
        c2w = cameras.c2w.detach().cpu().double().numpy()
        eyes, fwd = c2w[:, :3, 3], -c2w[:, :3, 2]
        up = _unit(c2w[:, :3, 1].mean(axis=0))
        # Least-squares point closest to all viewing rays.
        a = np.zeros((3, 3))
        b = np.zeros(3)
        for o, d in zip(eyes, fwd):
            d = _unit(d)
            p = np.eye(3) - np.outer(d, d)
            a += p
            b += p @ o
        target = np.linalg.lstsq(a, b, rcond=None)[0] if len(eyes) > 1 else eyes[0] + fwd[0]
        fov = float(np.degrees(2 * np.arctan(0.5 * float(cameras.height[0]) / float(cameras.fy[0]))))
        ctl = CameraControl(target=target, up=up, fov_y=fov)
        ctl.snap_to(c2w[0])
        ctl.set_home()
        return ctl
