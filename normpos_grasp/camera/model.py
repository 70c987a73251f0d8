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

from normpos_grasp.errors import InputError
from normpos_grasp.geometry.transforms import invert_pose, transform_points
from normpos_grasp.typing import ArrayLike, FloatArray, UInt8Array
from normpos_grasp.validation import as_float_array, check_pose


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
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise InputError(f"image size must be positive, got {self.width}x{self.height}")
        dist = as_float_array(self.distortion, "distortion", (None,))
        if dist.size not in (4, 5, 8, 12):
            raise InputError(f"distortion must have 4, 5, 8 or 12 coefficients (no tilt model), got {dist.size}")
        if not self.depth_scale_m > 0:
            raise InputError(f"depth_scale_m must be positive (metres per unit), got {self.depth_scale_m}")
        object.__setattr__(self, "K", k)
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))
        object.__setattr__(self, "distortion", dist)
        object.__setattr__(self, "depth_scale_m", float(self.depth_scale_m))
        if self.world_from_camera is not None:
            object.__setattr__(self, "world_from_camera", check_pose(self.world_from_camera, "world_from_camera"))
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
        wfc = None if world_from_camera is None else check_pose(world_from_camera, "world_from_camera")
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
    def from_dict(cls, data: dict[str, Any]) -> Camera:
        """Inverse of `to_dict`; raises InputError naming a missing key."""
        try:
            return cls(
                K=np.asarray(data["K"], dtype=np.float64),
                width=int(data["width"]),
                height=int(data["height"]),
                distortion=np.asarray(data.get("distortion", np.zeros(5)), dtype=np.float64),
                depth_scale_m=float(data.get("depth_scale_m", 0.001)),
                world_from_camera=None
                if data.get("world_from_camera") is None
                else np.asarray(data["world_from_camera"], dtype=np.float64),
            )
        except KeyError as exc:
            raise InputError(f"camera description lacks the key {exc.args[0]!r}") from exc

    def save_json(self, path: str | Path) -> None:
        """Write the camera as JSON atomically (a temporary file renamed into place)."""
        target = Path(path)
        tmp = target.with_name(target.name + ".tmp")
        tmp.write_text(json.dumps(self.to_dict(), indent=2))
        tmp.replace(target)

    @classmethod
    def load_json(cls, path: str | Path) -> Camera:
        try:
            data = json.loads(Path(path).read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise InputError(f"cannot read camera file {path}: {exc}") from exc
        return cls.from_dict(data)

    @classmethod
    def from_bop(cls, entry: dict[str, Any], width: int, height: int) -> Camera:
        """From one BOP `scene_camera.json` entry: cam_K, depth_scale (mm/unit), optional cam_R_w2c, cam_t_w2c (mm)."""
        try:
            k = np.asarray(entry["cam_K"], dtype=np.float64).reshape(3, 3)
        except KeyError as exc:
            raise InputError("BOP camera entry lacks cam_K") from exc
        wfc = None
        if "cam_R_w2c" in entry and "cam_t_w2c" in entry:
            cfw = np.eye(4)
            cfw[:3, :3] = np.asarray(entry["cam_R_w2c"], dtype=np.float64).reshape(3, 3)
            cfw[:3, 3] = np.asarray(entry["cam_t_w2c"], dtype=np.float64).reshape(3) / 1000.0
            wfc = invert_pose(cfw)
            # re-orthonormalise: BOP files store rounded floats
            u, _, vt = np.linalg.svd(wfc[:3, :3])
            wfc[:3, :3] = u @ vt
        return cls(k, width, height, np.zeros(5), float(entry.get("depth_scale", 1.0)) / 1000.0, wfc)

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
