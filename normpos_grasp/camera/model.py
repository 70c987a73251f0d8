"""Pinhole camera with OpenCV distortion: projection and back-projection (the paper's Eq. 1-5).

Camera frame is OpenCV's (x right, y down, z forward); `world_from_camera` maps camera to world (z up).
Depth images are metric (metres, float) inside the library; `depth_scale_m` converts raw sensor units.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from normpos_grasp.atomic import atomic_write_text
from normpos_grasp.errors import ExtrinsicsError, InputError
from normpos_grasp.geometry.transforms import invert_pose, transform_points
from normpos_grasp.typing import ArrayLike, FloatArray, UInt8Array
from normpos_grasp.validation import as_float_array

# Largest accepted max |R^T R - I| of a camera rotation. Files store rounded floats (BOP: about 1e-7); 1e-3 is a
# rotation error below 0.06 deg, which is projected onto the nearest rotation. Anything larger is not a rotation
# (an all-zero block: 1.0; a block scaled by 1000: 1e6) and is refused instead of being re-orthonormalised.
ROTATION_TOL = 1e-3
# A pick cell camera is within a few metres of the world origin and of what it looks at; 20 m is far beyond any
# cell and far below what millimetres read as metres give (a camera 0.8 m away reads as 800 m).
MAX_CAMERA_DISTANCE_M = 20.0
MAX_IMAGE_SIDE_PX = 16384  # larger than any RGB-D sensor; an image header claiming more is corrupt
MAX_DEPTH_SCALE_M = 1.0  # metres per raw depth unit: 1.0 is depth stored in metres


def check_rotation(value: ArrayLike, name: str = "rotation", tol: float = ROTATION_TOL) -> FloatArray:
    """A (3, 3) rotation from `value`, projected onto SO(3) when max |R^T R - I| <= `tol`.

    Raises ExtrinsicsError naming `name` with the measured deviation (not orthonormal) or the determinant (a
    reflection); a matrix that is not a rotation is never silently re-orthonormalised."""
    rot = as_float_array(value, name, (3, 3))
    deviation = float(np.abs(rot.T @ rot - np.eye(3)).max())
    if deviation > tol:
        raise ExtrinsicsError(
            f"{name} is not a rotation: max |R^T R - I| = {deviation:.3g} (tolerance {tol:g}); an all-zero, "
            "scaled or hand-typed block cannot be used: write the calibrated rotation",
            deviation,
        )
    det = float(np.linalg.det(rot))
    if det < 0:
        raise ExtrinsicsError(
            f"{name} has determinant {det:.3f}: a reflection, not a rotation (a left-handed frame or two axes "
            "swapped); check the axis order of the calibration",
            det,
        )
    u, _, vt = np.linalg.svd(rot)
    return np.asarray(u @ vt)


def check_world_from_camera(
    value: ArrayLike,
    name: str = "world_from_camera",
    floor_z_m: float | None = None,
    max_distance_m: float = MAX_CAMERA_DISTANCE_M,
) -> FloatArray:
    """A validated (4, 4) `world_from_camera` (metres, world z up): the one check every camera loader uses.

    Refuses (ExtrinsicsError, naming `name` and the measured value) a last row other than [0, 0, 0, 1], a rotation
    block that is not orthonormal within `ROTATION_TOL` or is a reflection (see `check_rotation`), a camera more
    than `max_distance_m` from the world origin (units: millimetres read as metres) and, when `floor_z_m` is
    given, a camera below the floor. Returns a new array with the rotation projected onto SO(3)."""
    pose = as_float_array(value, name, (4, 4))
    if not np.allclose(pose[3], [0.0, 0.0, 0.0, 1.0], atol=1e-9):
        raise ExtrinsicsError(f"{name}: last row must be [0, 0, 0, 1], got {pose[3].tolist()}")
    out = np.eye(4)
    out[:3, :3] = check_rotation(pose[:3, :3], f"{name} rotation")
    out[:3, 3] = pose[:3, 3]
    dist = float(np.linalg.norm(out[:3, 3]))
    if dist > max_distance_m:
        raise ExtrinsicsError(
            f"{name}: camera {dist:.4g} m from the world origin (more than {max_distance_m:g} m): looks like "
            "millimetres; the translation is in metres",
            dist,
        )
    if floor_z_m is not None and out[2, 3] < floor_z_m:
        raise ExtrinsicsError(
            f"{name}: camera at z = {out[2, 3]:.3f} m, under the floor at z = {floor_z_m:.3f} m (world z up); "
            "check the sign of z, the axis order and the calibration's u/v columns",
            float(out[2, 3]),
        )
    return out


@dataclass(frozen=True, eq=False)
class Camera:
    """Intrinsics, distortion, image size, depth scale and optional world extrinsics.

    Attributes:
        K: (3, 3) intrinsic matrix in pixels.
        width, height: image size in pixels.
        distortion: OpenCV coefficients (k1, k2, p1, p2[, k3[, k4, k5, k6]]); zeros when undistorted.
        depth_scale_m: metres per raw depth unit (a D435 or BOP depth_scale 1.0 image: 0.001).
        world_from_camera: (4, 4) pose of the camera in the world, or None when only the camera frame is known.
    """

    K: FloatArray
    width: int
    height: int
    distortion: FloatArray = field(default_factory=lambda: np.zeros(5))
    depth_scale_m: float = 0.001
    world_from_camera: FloatArray | None = None

    def __post_init__(self) -> None:
        k = as_float_array(self.K, "K", (3, 3))
        if k[0, 0] <= 0 or k[1, 1] <= 0 or not np.allclose(k[2], [0, 0, 1]) or k[1, 0] != 0 or k[0, 1] != 0:
            raise InputError(f"K must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0, got {k.tolist()}")
        size_ok = all(
            isinstance(v, int | float | np.integer | np.floating)
            and not isinstance(v, bool)
            and float(v).is_integer()
            and 0 < v <= MAX_IMAGE_SIDE_PX
            for v in (self.width, self.height)
        )
        if not size_ok:
            raise InputError(
                f"image size must be whole numbers of pixels in 1..{MAX_IMAGE_SIDE_PX}, got {self.width}x{self.height}"
            )
        dist = as_float_array(self.distortion, "distortion", (None,))
        if dist.size not in (4, 5, 8, 12):
            raise InputError(f"distortion must have 4, 5, 8 or 12 coefficients (no tilt model), got {dist.size}")
        scale = self.depth_scale_m
        if isinstance(scale, bool) or not isinstance(scale, int | float | np.floating | np.integer):
            raise InputError(f"depth_scale_m must be a number (metres per unit), got {scale!r}")
        if not (np.isfinite(scale) and 0 < scale <= MAX_DEPTH_SCALE_M):
            raise InputError(
                f"depth_scale_m must be finite, positive and at most {MAX_DEPTH_SCALE_M} (metres per raw unit; "
                f"0.001 for millimetre depth), got {scale}"
            )
        object.__setattr__(self, "K", k)
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))
        object.__setattr__(self, "distortion", dist)
        object.__setattr__(self, "depth_scale_m", float(self.depth_scale_m))
        if self.world_from_camera is not None:
            object.__setattr__(self, "world_from_camera", check_world_from_camera(self.world_from_camera))
        for arr in (self.K, self.distortion, self.world_from_camera):
            if arr is not None:
                arr.setflags(write=False)

    # -- convenience -------------------------------------------------------------------------
    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) in pixels."""
        return (self.width, self.height)

    @property
    def has_distortion(self) -> bool:
        return bool(np.any(self.distortion != 0))

    @property
    def camera_from_world(self) -> FloatArray:
        """Inverse of `world_from_camera`; raises InputError when the extrinsics are unknown."""
        return invert_pose(self.require_world_from_camera())

    def require_world_from_camera(self) -> FloatArray:
        if self.world_from_camera is None:
            raise InputError("this camera has no world_from_camera; calibrate extrinsics first")
        return self.world_from_camera

    def with_extrinsics(self, world_from_camera: ArrayLike | None) -> Camera:
        """A copy with other extrinsics."""
        wfc = None if world_from_camera is None else check_world_from_camera(world_from_camera)
        return Camera(self.K, self.width, self.height, self.distortion, self.depth_scale_m, wfc)

    def scaled(self, factor: float) -> Camera:
        """A copy for an image resized by `factor` (pixel-centre convention)."""
        k = self.K.copy()
        k[0, 0] *= factor
        k[1, 1] *= factor
        k[0, 2] = (k[0, 2] + 0.5) * factor - 0.5
        k[1, 2] = (k[1, 2] + 0.5) * factor - 0.5
        return Camera(
            k,
            round(self.width * factor),
            round(self.height * factor),
            self.distortion,
            self.depth_scale_m,
            self.world_from_camera,
        )

    # -- projection --------------------------------------------------------------------------
    def project(self, points_camera: ArrayLike) -> FloatArray:
        """Project (N, 3) camera-frame points (z > 0) to (N, 2) pixel coordinates (u, v), with distortion."""
        pts = np.asarray(points_camera, dtype=np.float64).reshape(-1, 3)
        z = pts[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            x = pts[:, 0] / z
            y = pts[:, 1] / z
        if self.has_distortion:
            x, y = _distort(x, y, self.distortion)
        return np.column_stack([self.fx * x + self.cx, self.fy * y + self.cy])

    def normalized_coordinates(self, pixels: ArrayLike) -> FloatArray:
        """(N, 2) pixels -> (N, 2) undistorted normalised coordinates (x/z, y/z)."""
        px = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
        if not self.has_distortion:
            return np.column_stack([(px[:, 0] - self.cx) / self.fx, (px[:, 1] - self.cy) / self.fy])
        xd = (px[:, 0] - self.cx) / self.fx
        yd = (px[:, 1] - self.cy) / self.fy
        return _undistort(xd, yd, self.distortion)

    def backproject(self, pixels: ArrayLike, depth_m: ArrayLike) -> FloatArray:
        """Eq. 1-4: (N, 2) pixels with (N,) z-depths in metres -> (N, 3) camera-frame points."""
        xy = self.normalized_coordinates(pixels)
        z = np.asarray(depth_m, dtype=np.float64).reshape(-1)
        if z.shape[0] != xy.shape[0]:
            raise InputError(f"got {xy.shape[0]} pixels but {z.shape[0]} depths")
        return np.column_stack([xy * z[:, None], z])

    def backproject_to_world(self, pixels: ArrayLike, depth_m: ArrayLike) -> FloatArray:
        """Eq. 5: (N, 2) pixels with depths -> (N, 3) world points; needs `world_from_camera`."""
        return transform_points(self.require_world_from_camera(), self.backproject(pixels, depth_m))

    def pixel_grid_rays(self) -> FloatArray:
        """(H, W, 2) undistorted normalised coordinates of every pixel centre, for whole-image back-projection."""
        v, u = np.mgrid[0 : self.height, 0 : self.width]
        xy = self.normalized_coordinates(np.column_stack([u.ravel(), v.ravel()]))
        return xy.reshape(self.height, self.width, 2)

    # -- serialisation -----------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict (SI units)."""
        out: dict[str, Any] = {
            "K": self.K.tolist(),
            "width": self.width,
            "height": self.height,
            "distortion": self.distortion.tolist(),
            "depth_scale_m": self.depth_scale_m,
        }
        if self.world_from_camera is not None:
            out["world_from_camera"] = self.world_from_camera.tolist()
        return out

    @classmethod
    def from_dict(cls, data: Any) -> Camera:
        """Inverse of `to_dict`; raises InputError naming a missing or malformed key."""
        if not isinstance(data, dict):
            raise InputError(f"a camera description must be a JSON object, got {type(data).__name__}")
        missing = [k for k in ("K", "width", "height") if k not in data]
        if missing:
            raise InputError(f"camera description lacks the key {missing[0]!r}")
        wfc = data.get("world_from_camera")
        return cls(
            K=as_float_array(data["K"], "K", (3, 3)),
            width=_whole(data["width"], "width"),
            height=_whole(data["height"], "height"),
            distortion=as_float_array(data.get("distortion", np.zeros(5)), "distortion", (None,)),
            depth_scale_m=_number(data.get("depth_scale_m", 0.001), "depth_scale_m"),
            world_from_camera=None if wfc is None else as_float_array(wfc, "world_from_camera", (4, 4)),
        )

    def save_json(self, path: str | Path) -> None:
        """Write the camera as JSON atomically (a temporary file renamed into place)."""
        atomic_write_text(path, json.dumps(self.to_dict(), indent=2))

    @classmethod
    def load_json(cls, path: str | Path) -> Camera:
        """Read a camera JSON written by `save_json` (or by hand); every problem is an InputError naming the file."""
        try:
            data = json.loads(Path(path).read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:
            raise InputError(f"cannot read camera file {path}: {exc}") from exc
        try:
            return cls.from_dict(data)
        except InputError as exc:
            raise type(exc)(f"camera file {path}: {exc}") from exc

    @classmethod
    def from_bop(cls, entry: Any, width: int, height: int) -> Camera:
        """From one BOP `scene_camera.json` entry: cam_K, depth_scale (mm/unit), optional cam_R_w2c, cam_t_w2c (mm).

        The rotation must be orthonormal within `ROTATION_TOL` (rounding is corrected, garbage refused); a
        missing `depth_scale` means 1.0 mm per unit (BOP's default)."""
        if not isinstance(entry, dict):
            raise InputError(f"a BOP camera entry must be an object, got {type(entry).__name__}")
        if "cam_K" not in entry:
            raise InputError("BOP camera entry lacks cam_K")
        k = as_float_array(entry["cam_K"], "cam_K", (9,)).reshape(3, 3)
        wfc = None
        if ("cam_R_w2c" in entry) != ("cam_t_w2c" in entry):
            raise InputError("BOP camera entry has only one of cam_R_w2c and cam_t_w2c; give both or neither")
        if "cam_R_w2c" in entry:
            cfw = np.eye(4)
            cfw[:3, :3] = check_rotation(
                as_float_array(entry["cam_R_w2c"], "cam_R_w2c", (9,)).reshape(3, 3), "cam_R_w2c"
            )
            cfw[:3, 3] = as_float_array(entry["cam_t_w2c"], "cam_t_w2c", (3,)) / 1000.0
            wfc = invert_pose(cfw)
        scale_mm = _number(entry.get("depth_scale", 1.0), "depth_scale")
        return cls(k, width, height, np.zeros(5), scale_mm / 1000.0, wfc)

    def to_bop(self) -> dict[str, Any]:
        """One BOP `scene_camera.json` entry (mm); BOP has no distortion field, so undistort first."""
        out: dict[str, Any] = {
            "cam_K": self.K.reshape(-1).tolist(),
            "depth_scale": self.depth_scale_m * 1000.0,
        }
        if self.world_from_camera is not None:
            cfw = self.camera_from_world
            out["cam_R_w2c"] = cfw[:3, :3].reshape(-1).tolist()
            out["cam_t_w2c"] = (cfw[:3, 3] * 1000.0).tolist()
        return out


@dataclass(frozen=True, eq=False)
class RGBDFrame:
    """One RGB-D frame: rgb (H, W, 3) uint8, depth_m (H, W) float metres (0 or NaN = invalid), its camera."""

    rgb: UInt8Array
    depth_m: FloatArray
    camera: Camera
    stamp: float = 0.0
    scene_id: int = 0
    im_id: int = 0

    def __post_init__(self) -> None:
        h, w = self.camera.height, self.camera.width
        if self.depth_m.shape != (h, w):
            raise InputError(f"depth must be (H, W) = ({h}, {w}) to match the camera, got {self.depth_m.shape}")
        if self.rgb.shape != (h, w, 3):
            raise InputError(f"rgb must be (H, W, 3) = ({h}, {w}, 3), got {self.rgb.shape}")

    @property
    def frame_name(self) -> str:
        """'world' when the camera has extrinsics, else 'camera'."""
        return "camera" if self.camera.world_from_camera is None else "world"


def _whole(value: Any, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int | float) or not float(value).is_integer():
        raise InputError(f"{name} must be a whole number of pixels, got {value!r}")
    return int(value)


def _number(value: Any, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise InputError(f"{name} must be a number, got {value!r}")
    return float(value)


def _distort(x: FloatArray, y: FloatArray, d: FloatArray) -> tuple[FloatArray, FloatArray]:
    """OpenCV's distortion model (radial k1..k6, tangential p1, p2, thin prism s1..s4)."""
    c = np.zeros(12)
    c[: d.size] = d
    k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4 = c
    r2 = x * x + y * y
    radial = (1 + k1 * r2 + k2 * r2**2 + k3 * r2**3) / (1 + k4 * r2 + k5 * r2**2 + k6 * r2**3)
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) + s1 * r2 + s2 * r2**2
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y + s3 * r2 + s4 * r2**2
    return xd, yd


def _undistort(xd: FloatArray, yd: FloatArray, d: FloatArray, iterations: int = 20) -> FloatArray:
    """Invert `_distort` by Gauss-Newton on each point (2x2 Jacobian by central differences); (N, 2)."""
    x, y = xd.copy(), yd.copy()
    eps = 1e-7
    for _ in range(iterations):
        fx, fy = _distort(x, y, d)
        rx, ry = fx - xd, fy - yd
        if max(np.abs(rx).max(initial=0.0), np.abs(ry).max(initial=0.0)) < 1e-14:
            break
        ax, ay = _distort(x + eps, y, d)
        bx, by = _distort(x - eps, y, d)
        cx, cy = _distort(x, y + eps, d)
        ex, ey = _distort(x, y - eps, d)
        j11, j21 = (ax - bx) / (2 * eps), (ay - by) / (2 * eps)
        j12, j22 = (cx - ex) / (2 * eps), (cy - ey) / (2 * eps)
        det = j11 * j22 - j12 * j21
        det = np.where(np.abs(det) < 1e-12, 1e-12, det)
        x = x - (j22 * rx - j12 * ry) / det
        y = y - (-j21 * rx + j11 * ry) / det
    return np.column_stack([x, y])
