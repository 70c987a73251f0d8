"""Static-reference check (the paper's resolution method 1): fixed control points anchor the world frame and
reveal a camera that was bumped since its extrinsics were calibrated.

At calibration time a `StaticReference` stores the surveyed points, the pixels they were seen at, the
calibrated `world_from_camera` and (optionally) a small image patch around each point. For a new frame the
points are found again (by the caller, or by normalised cross-correlation of the stored patches), the
camera pose is re-solved from them (EPnP + refinement) and compared with the calibrated one. The report
gives the camera's drift in millimetres and degrees, each point's pixel shift and the world error that the
shift would cause at the point's distance; with a depth image also each point's depth disagreement.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from normpos_grasp.camera.calibration import ControlPoints, ExtrinsicsOptions, calibrate_extrinsics
from normpos_grasp.camera.model import Camera, RGBDFrame, check_world_from_camera
from normpos_grasp.errors import CalibrationError, CameraMoved, InputError
from normpos_grasp.geometry.transforms import rotation_angle, transform_points
from normpos_grasp.typing import ArrayLike, FloatArray, UInt8Array
from normpos_grasp.validation import as_float_array

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class DriftOptions:
    """Tolerances of the check.

    Attributes:
        max_translation_mm: largest accepted move of the camera centre, millimetres.
        max_rotation_deg: largest accepted rotation of the camera, degrees.
        raise_on_drift: raise CameraMoved when a tolerance is exceeded (else only report).
        patch_radius_px: half-size of the stored patches (the patch is (2r+1)^2 pixels).
        search_radius_px: how far from its calibrated pixel a point is searched for, pixels.
        min_match_score: lowest normalised cross-correlation accepted as a match (0..1).
        pixel_tolerance_px: points that moved more than this are named in the error.
        min_peak_margin: a match is ambiguous (skipped) when a second correlation peak, more than 3 px away,
            comes within this margin of the best (repetitive texture such as a checkerboard).
    """

    max_translation_mm: float = 2.0
    max_rotation_deg: float = 0.1
    raise_on_drift: bool = True
    patch_radius_px: int = 12
    search_radius_px: int = 40
    min_match_score: float = 0.8
    pixel_tolerance_px: float = 1.0
    min_peak_margin: float = 0.05


@dataclass(frozen=True, eq=False)
class StaticReference:
    """Calibrated anchor of the world frame: names (N,), world (N, 3) metres, pixels (N, 2) at calibration,
    world_from_camera (4, 4) as calibrated, patches (N, 2r+1, 2r+1) uint8 gray around each pixel or None."""

    names: tuple[str, ...]
    world: FloatArray
    pixels: FloatArray
    world_from_camera: FloatArray
    patches: UInt8Array | None = None

    def __post_init__(self) -> None:
        w = as_float_array(self.world, "world", (None, 3))
        p = as_float_array(self.pixels, "pixels", (len(w), 2))
        if len(self.names) != len(w) or len(w) < 4:
            raise InputError(f"need >= 4 points with one name each, got {len(w)} points, {len(self.names)} names")
        object.__setattr__(self, "world", w)
        object.__setattr__(self, "pixels", p)
        object.__setattr__(self, "world_from_camera", check_world_from_camera(self.world_from_camera))
        if self.patches is not None and (self.patches.ndim != 3 or len(self.patches) != len(w)):
            raise InputError(f"patches must be (N, 2r+1, 2r+1) for N = {len(w)}, got {self.patches.shape}")

    @classmethod
    def from_calibration(
        cls, camera: Camera, points: ControlPoints, image: ArrayLike | None = None, patch_radius_px: int = 12
    ) -> StaticReference:
        """Reference from a calibrated camera, its control points and (optionally) the calibration image."""
        wfc = camera.require_world_from_camera()
        patches = None
        if image is not None:
            gray = _gray(image)
            patches = np.stack([_patch(gray, uv, patch_radius_px) for uv in points.pixels])
        return cls(points.names, points.world, points.pixels, wfc, patches)

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "names": list(self.names),
            "world_m": self.world.tolist(),
            "pixels": self.pixels.tolist(),
            "world_from_camera": self.world_from_camera.tolist(),
        }
        if self.patches is not None:
            out["patches"] = self.patches.tolist()
        return out

    @classmethod
    def from_dict(cls, data: Any) -> StaticReference:
        """Inverse of `to_dict`; raises InputError naming a missing or malformed key."""
        if not isinstance(data, dict):
            raise InputError(f"a static reference must be a JSON object, got {type(data).__name__}")
        missing = [k for k in ("names", "world_m", "pixels", "world_from_camera") if k not in data]
        if missing:
            raise InputError(f"static reference lacks the key {missing[0]!r}")
        names = data["names"]
        if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
            raise InputError(f"static reference names must be a list of text, got {type(names).__name__}")
        patches = data.get("patches")
        if patches is not None:
            arr = as_float_array(patches, "patches", (None, None, None))
            if np.any((arr < 0) | (arr > 255) | (arr != np.round(arr))):
                raise InputError("static reference patches must hold 8-bit gray values 0..255")
            patches = arr.astype(np.uint8)
        return cls(
            tuple(names),
            as_float_array(data["world_m"], "world_m", (None, 3)),
            as_float_array(data["pixels"], "pixels", (None, 2)),
            as_float_array(data["world_from_camera"], "world_from_camera", (4, 4)),
            patches,
        )

    def save_json(self, path: str | Path) -> None:
        target = Path(path)
        tmp = target.with_name(target.name + ".tmp")
        tmp.write_text(json.dumps(self.to_dict()))
        tmp.replace(target)

    @classmethod
    def load_json(cls, path: str | Path) -> StaticReference:
        try:
            data = json.loads(Path(path).read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:
            raise InputError(f"cannot read static reference {path}: {exc}") from exc
        try:
            return cls.from_dict(data)
        except InputError as exc:
            raise InputError(f"static reference {path}: {exc}") from exc


@dataclass(frozen=True, eq=False)
class DriftReport:
    """Result of a check.

    Attributes:
        translation_mm: distance between the calibrated and the re-solved camera centres, millimetres.
        rotation_deg: angle between the calibrated and the re-solved camera orientations, degrees.
        pixel_shift_px: (N,) distance of each observed pixel from its calibrated projection (NaN = not found).
        world_error_mm: (N,) distance of each surveyed point from its observed pixel's ray under the
            calibrated pose, millimetres: the error measuring through the old calibration would make there.
        depth_error_mm: (N,) measured minus expected depth at each point (NaN without valid depth).
        world_from_camera_now: (4, 4) re-solved pose.
        moved: True when a tolerance is exceeded.
    """

    translation_mm: float
    rotation_deg: float
    pixel_shift_px: FloatArray
    world_error_mm: FloatArray
    depth_error_mm: FloatArray
    world_from_camera_now: FloatArray
    moved: bool

    def summary(self) -> str:
        return (
            f"camera drift {self.translation_mm:.2f} mm, {self.rotation_deg:.3f} deg; "
            f"max point shift {np.nanmax(self.pixel_shift_px):.2f} px"
        )


def check_drift(
    camera: Camera,
    reference: StaticReference,
    observed_pixels: ArrayLike,
    options: DriftOptions | None = None,
    depth_m: ArrayLike | None = None,
) -> DriftReport:
    """Compare the pose re-solved from `observed_pixels` (N, 2; NaN rows = not seen) with the calibration.

    Raises CameraMoved (carrying the report) when a tolerance is exceeded and `raise_on_drift` is set;
    CalibrationError when fewer than 4 points were seen.
    """
    opts = DriftOptions() if options is None else options
    obs = np.asarray(observed_pixels, dtype=np.float64).reshape(-1, 2)
    if obs.shape[0] != len(reference.names):
        raise InputError(f"expected {len(reference.names)} observed pixels, got {obs.shape[0]}")
    seen = np.all(np.isfinite(obs), axis=1)
    if seen.sum() < 4:
        missing = tuple(int(i) for i in np.nonzero(~seen)[0])
        raise CalibrationError(
            f"only {int(seen.sum())} reference points found in the frame, need 4; missing {list(missing)} "
            f"({[reference.names[i] for i in missing]}): is the view blocked or the camera badly moved?",
            missing,
        )
    cal = camera.with_extrinsics(reference.world_from_camera)
    idx = np.nonzero(seen)[0]
    now = calibrate_extrinsics(cal, reference.world[idx], obs[idx], ExtrinsicsOptions(max_rms_px=1e9))
    wfc_now = now.world_from_camera
    wfc = reference.world_from_camera
    translation_mm = float(np.linalg.norm(wfc_now[:3, 3] - wfc[:3, 3]) * 1000.0)
    rotation_deg = float(np.degrees(rotation_angle(wfc[:3, :3].T @ wfc_now[:3, :3])))
    expected = cal.project(transform_points(cal.camera_from_world, reference.world))
    shift = np.full(len(obs), np.nan)
    shift[idx] = np.linalg.norm(obs[idx] - expected[idx], axis=1)
    world_err = np.full(len(obs), np.nan)
    pts_cam = transform_points(cal.camera_from_world, reference.world)
    xy = cal.normalized_coordinates(obs[idx])
    rays = np.column_stack([xy, np.ones(len(xy))])
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    along = np.einsum("ij,ij->i", pts_cam[idx], rays)
    world_err[idx] = np.linalg.norm(pts_cam[idx] - along[:, None] * rays, axis=1) * 1000.0
    depth_err = np.full(len(obs), np.nan)
    if depth_m is not None:
        d = np.asarray(depth_m, dtype=np.float64)
        for i in idx:
            u, v = int(round(obs[i, 0])), int(round(obs[i, 1]))
            if 0 <= v < d.shape[0] and 0 <= u < d.shape[1] and np.isfinite(d[v, u]) and d[v, u] > 0:
                depth_err[i] = (d[v, u] - pts_cam[i, 2]) * 1000.0
    moved = translation_mm > opts.max_translation_mm or rotation_deg > opts.max_rotation_deg
    report = DriftReport(translation_mm, rotation_deg, shift, world_err, depth_err, wfc_now, moved)
    logger.info("static reference: %s", report.summary())
    if moved and opts.raise_on_drift:
        worst = tuple(int(i) for i in np.nonzero(np.nan_to_num(shift) > opts.pixel_tolerance_px)[0])
        raise CameraMoved(
            f"camera moved since calibration: {translation_mm:.2f} mm (limit {opts.max_translation_mm}), "
            f"{rotation_deg:.3f} deg (limit {opts.max_rotation_deg}); points shifted by more than "
            f"{opts.pixel_tolerance_px} px: {[reference.names[i] for i in worst]}. Re-calibrate the extrinsics "
            "before moving the robot",
            worst,
            report,
        )
    return report


def locate_reference_points(
    reference: StaticReference, image: ArrayLike, options: DriftOptions | None = None
) -> FloatArray:
    """(N, 2) pixels of the reference points in `image` by normalised cross-correlation of the stored
    patches near their calibrated pixels, with sub-pixel peak interpolation; NaN rows where not found."""
    import cv2

    opts = DriftOptions() if options is None else options
    if reference.patches is None:
        raise InputError("the static reference holds no image patches; build it with the calibration image")
    gray = _gray(image)
    h, w = gray.shape
    r = reference.patches.shape[1] // 2
    out = np.full((len(reference.names), 2), np.nan)
    for i, (patch, uv) in enumerate(zip(reference.patches, reference.pixels, strict=True)):
        if float(patch.std()) < 2.0:
            logger.warning("reference point %s has a textureless patch; it cannot be tracked", reference.names[i])
            continue
        cu, cv_ = int(round(uv[0])), int(round(uv[1]))
        s = opts.search_radius_px + r
        x0, x1 = max(cu - s, 0), min(cu + s + 1, w)
        y0, y1 = max(cv_ - s, 0), min(cv_ + s + 1, h)
        if x1 - x0 <= 2 * r + 2 or y1 - y0 <= 2 * r + 2:
            continue
        res = np.asarray(cv2.matchTemplate(gray[y0:y1, x0:x1], patch, cv2.TM_CCOEFF_NORMED), np.float64)
        _, score, _, (mx, my) = cv2.minMaxLoc(res)
        if score < opts.min_match_score:
            continue
        others = res.copy()
        others[max(my - 3, 0) : my + 4, max(mx - 3, 0) : mx + 4] = -1.0
        if float(others.max(initial=-1.0)) > score - opts.min_peak_margin:
            logger.warning("reference point %s matches ambiguously (repetitive texture); skipped", reference.names[i])
            continue
        dx = _parabola(res, my, mx, axis=1)
        dy = _parabola(res, my, mx, axis=0)
        # patch centre = calibrated pixel rounded; keep the sub-pixel part of the calibrated pixel
        out[i] = [x0 + mx + dx + r + (uv[0] - cu), y0 + my + dy + r + (uv[1] - cv_)]
    return out


def check_frame(
    camera: Camera, reference: StaticReference, frame: RGBDFrame, options: DriftOptions | None = None
) -> DriftReport:
    """Locate the reference points in `frame.rgb` and run `check_drift` (with the frame's depth)."""
    pixels = locate_reference_points(reference, frame.rgb, options)
    return check_drift(camera, reference, pixels, options, depth_m=frame.depth_m)


def _gray(image: ArrayLike) -> UInt8Array:
    import cv2

    img = np.asarray(image)
    if img.dtype != np.uint8:
        raise InputError(f"image must be 8-bit, got {img.dtype}")
    if img.ndim == 3:
        return np.asarray(cv2.cvtColor(np.ascontiguousarray(img[:, :, :3]), cv2.COLOR_RGB2GRAY), np.uint8)
    if img.ndim != 2:
        raise InputError(f"image must be (H, W) or (H, W, 3), got {img.shape}")
    return img


def _patch(gray: UInt8Array, uv: FloatArray, r: int) -> UInt8Array:
    u, v = int(round(uv[0])), int(round(uv[1]))
    h, w = gray.shape
    if not (r <= u < w - r and r <= v < h - r):
        raise CalibrationError(f"reference pixel {uv.tolist()} lies within {r} px of the image border")
    return np.ascontiguousarray(gray[v - r : v + r + 1, u - r : u + r + 1])


def _parabola(res: FloatArray, y: int, x: int, axis: int) -> float:
    """Sub-pixel offset of a correlation peak along one axis (three-point parabola), in [-0.5, 0.5]."""
    if axis == 1:
        if x <= 0 or x >= res.shape[1] - 1:
            return 0.0
        a, b, c = res[y, x - 1], res[y, x], res[y, x + 1]
    else:
        if y <= 0 or y >= res.shape[0] - 1:
            return 0.0
        a, b, c = res[y - 1, x], res[y, x], res[y + 1, x]
    den = a - 2 * b + c
    if abs(den) < 1e-12:
        return 0.0
    return float(np.clip(0.5 * (a - c) / den, -0.5, 0.5))
