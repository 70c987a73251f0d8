"""Camera intrinsics presets matching the simulated sensors, and camera poses above the table with tilt.

Intrinsics are nominal values of each sensor's common stream (pinhole, no distortion); `camera_intrinsics`
rescales them to any resolution keeping the horizontal field of view and square pixels.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from normpos_grasp.camera.model import Camera
from normpos_grasp.errors import InputError
from normpos_grasp.geometry.transforms import look_at
from normpos_grasp.typing import ArrayLike, FloatArray


@dataclass(frozen=True)
class IntrinsicsPreset:
    """Nominal pinhole intrinsics at the sensor's native stream size (pixels)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float


#: Nominal intrinsics per sensor preset (depth-aligned stream).
INTRINSICS: dict[str, IntrinsicsPreset] = {
    "ideal": IntrinsicsPreset(640, 480, 615.0, 615.0, 319.5, 239.5),
    "d435": IntrinsicsPreset(640, 480, 615.0, 615.0, 319.5, 239.5),  # HFOV about 55 deg (colour/depth aligned)
    "d455": IntrinsicsPreset(640, 480, 390.0, 390.0, 319.5, 239.5),  # HFOV about 79 deg at 640x480
    "zed2": IntrinsicsPreset(1280, 720, 525.0, 525.0, 639.5, 359.5),  # HD720, HFOV about 101 deg
    "zivid": IntrinsicsPreset(1944, 1200, 1780.0, 1780.0, 971.5, 599.5),  # Zivid 2 class, HFOV about 57 deg
}


def parse_resolution(text: str) -> tuple[int, int]:
    """'640x480' -> (640, 480); raises InputError on anything else."""
    try:
        w, h = (int(p) for p in text.lower().split("x"))
    except ValueError as exc:
        raise InputError(f"resolution must look like 640x480, got {text!r}") from exc
    if w <= 0 or h <= 0:
        raise InputError(f"resolution must be positive, got {text!r}")
    return w, h


def camera_intrinsics(sensor: str, resolution: tuple[int, int] | None = None) -> Camera:
    """A `Camera` (no extrinsics) with `sensor`'s intrinsics at `resolution` (W, H); native size when None.

    Scaling keeps the horizontal field of view and square pixels; the principal point scales per axis.
    Depth raw units are 0.1 mm (`depth_scale_m` 1e-4), which BOP stores as depth_scale 0.1.
    """
    if sensor not in INTRINSICS:
        raise InputError(f"unknown sensor {sensor!r}; choose one of {sorted(INTRINSICS)}")
    p = INTRINSICS[sensor]
    w, h = resolution if resolution is not None else (p.width, p.height)
    sx, sy = w / p.width, h / p.height
    k = np.array(
        [[p.fx * sx, 0.0, (p.cx + 0.5) * sx - 0.5], [0.0, p.fy * sx, (p.cy + 0.5) * sy - 0.5], [0.0, 0.0, 1.0]]
    )
    return Camera(k, int(w), int(h), np.zeros(5), 1e-4)


@dataclass(frozen=True)
class CameraOptions:
    """Where cameras are placed (ranges are sampled uniformly with the frame's seed).

    sensor: intrinsics preset name; resolution: (W, H) pixels or None for the preset's native size.
    distance_m: (min, max) distance from the target point to the camera, metres.
    tilt_deg: (min, max) angle between the optical axis and straight down, degrees.
    azimuth_deg: (min, max) direction of the camera around the target, degrees (0 = from +x).
    target_jitter_m: the look-at point is drawn within this radius around the scene target, metres.
    roll_deg: (min, max) rotation of the image about the optical axis, degrees.
    """

    sensor: str = "d435"
    resolution: tuple[int, int] | None = (640, 480)
    distance_m: tuple[float, float] = (0.6, 0.85)
    tilt_deg: tuple[float, float] = (0.0, 30.0)
    azimuth_deg: tuple[float, float] = (0.0, 360.0)
    target_jitter_m: float = 0.03
    roll_deg: tuple[float, float] = (-10.0, 10.0)

    def __post_init__(self) -> None:
        if self.sensor not in INTRINSICS:
            raise InputError(f"unknown sensor {self.sensor!r}; choose one of {sorted(INTRINSICS)}")
        if not 0 < self.distance_m[0] <= self.distance_m[1]:
            raise InputError(f"distance_m must be (min, max) with 0 < min <= max, got {self.distance_m}")
        if not 0 <= self.tilt_deg[0] <= self.tilt_deg[1] < 90:
            raise InputError(f"tilt_deg must be (min, max) within [0, 90), got {self.tilt_deg}")


def camera_pose(
    target: ArrayLike, distance_m: float, tilt_deg: float, azimuth_deg: float, roll_deg: float = 0.0
) -> FloatArray:
    """`world_from_camera` (4, 4) of a camera `distance_m` from `target`, tilted `tilt_deg` from straight down.

    The camera sits on the side given by `azimuth_deg` and looks at `target`; the image's up direction points
    away from the camera across the table, rolled by `roll_deg` about the optical axis.
    """
    tgt = np.asarray(target, dtype=np.float64).reshape(3)
    tilt, az, roll = np.radians([tilt_deg, azimuth_deg, roll_deg])
    offset = np.array([np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), np.cos(tilt)])
    eye = tgt + distance_m * offset
    away = -np.array([np.cos(az), np.sin(az), 0.0])  # horizontal direction from the camera across the target
    pose = look_at(eye, tgt, up=away + np.array([0.0, 0.0, 1e-3]))
    if roll != 0.0:
        c, s = np.cos(roll), np.sin(roll)
        rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        pose[:3, :3] = pose[:3, :3] @ rz
    return pose


def sample_camera(options: CameraOptions, target: ArrayLike, rng: np.random.Generator) -> Camera:
    """A camera with the preset intrinsics and a pose drawn from `options` around `target` (metres)."""
    intr = camera_intrinsics(options.sensor, options.resolution)
    tgt = np.asarray(target, dtype=np.float64).reshape(3).copy()
    r = options.target_jitter_m * np.sqrt(rng.random())
    phi = 2 * np.pi * rng.random()
    tgt[:2] += r * np.array([np.cos(phi), np.sin(phi)])
    pose = camera_pose(
        tgt,
        float(rng.uniform(*options.distance_m)),
        float(rng.uniform(*options.tilt_deg)),
        float(rng.uniform(*options.azimuth_deg)),
        float(rng.uniform(*options.roll_deg)),
    )
    return intr.with_extrinsics(pose)
