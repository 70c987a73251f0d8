"""Camera calibration: intrinsics from checkerboard images (Zhang's method via OpenCV) and extrinsics from
surveyed control points (EPnP, then Levenberg-Marquardt refinement of the reprojection error).

Control-point CSV (one point per row, header required; x, y, z in metres in the world frame, u, v in pixels):

    name,x,y,z,u,v
    P1,0.0,0.0,0.0,312.4,402.1
"""

from __future__ import annotations

import csv
import itertools
import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from normpos_grasp.camera.model import MAX_CAMERA_DISTANCE_M, Camera, check_rotation
from normpos_grasp.errors import CalibrationError, InputError
from normpos_grasp.geometry.transforms import invert_pose, transform_points
from normpos_grasp.typing import ArrayLike, FloatArray, UInt8Array
from normpos_grasp.validation import as_float_array

logger = logging.getLogger(__name__)


# -------------------------------------------------------------------------------------------------
# intrinsics
# -------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class IntrinsicsOptions:
    """Settings of `calibrate_intrinsics`.

    Attributes:
        board: inner corners (columns, rows), for example (9, 6).
        square_m: edge of one square in metres.
        n_distortion: 5 (k1, k2, p1, p2, k3), 4 (k3 fixed at 0) or 0 (no distortion estimated).
        min_images: fewest images with a detected board.
        subpix_window: half-size in pixels of the corner refinement window.
    """

    board: tuple[int, int] = (9, 6)
    square_m: float = 0.025
    n_distortion: int = 5
    min_images: int = 3
    subpix_window: int = 5

    def __post_init__(self) -> None:
        if len(self.board) != 2 or min(self.board) < 2:
            raise InputError(f"board must give inner corners (cols, rows), each >= 2, got {self.board}")
        if not self.square_m > 0:
            raise InputError(f"square_m must be > 0 metres, got {self.square_m}")
        if self.n_distortion not in (0, 4, 5):
            raise InputError(f"n_distortion must be 0, 4 or 5, got {self.n_distortion}")
        if self.min_images < 1:
            raise InputError(f"min_images must be >= 1, got {self.min_images}")


@dataclass(frozen=True, eq=False)
class IntrinsicsResult:
    """camera (no extrinsics); rms_px over all corners; per_image_rms_px (M,) for `used` image indices;
    `rejected` image indices where no board was found."""

    camera: Camera
    rms_px: float
    per_image_rms_px: FloatArray
    used: tuple[int, ...]
    rejected: tuple[int, ...]


def find_checkerboard(image: ArrayLike, board: tuple[int, int], subpix_window: int = 5) -> FloatArray:
    """(cols*rows, 2) sub-pixel inner-corner pixels of a checkerboard in an 8-bit gray or RGB image.

    Raises CalibrationError when the board is not found.
    """
    import cv2

    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] in (3, 4):
        gray = cv2.cvtColor(np.ascontiguousarray(img[:, :, :3]), cv2.COLOR_RGB2GRAY)
    elif img.ndim == 2:
        gray = img
    else:
        raise InputError(f"image must be (H, W) gray or (H, W, 3) RGB, got {img.shape}")
    if gray.dtype != np.uint8:
        raise InputError(f"image must be 8-bit, got {gray.dtype}")
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    found, corners = cv2.findChessboardCorners(gray, tuple(board), flags=flags)
    if not found:
        raise CalibrationError(f"no {board[0]}x{board[1]} checkerboard (inner corners) found in the image")
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-4)
    w = int(subpix_window)
    corners = cv2.cornerSubPix(gray, corners, (w, w), (-1, -1), criteria)
    return np.asarray(corners, dtype=np.float64).reshape(-1, 2)


def board_points(board: tuple[int, int], square_m: float) -> FloatArray:
    """(cols*rows, 3) inner-corner positions in the board frame (z = 0), OpenCV's row-major order; metres."""
    cols, rows = board
    gx, gy = np.meshgrid(np.arange(cols), np.arange(rows))
    return np.column_stack([gx.ravel() * square_m, gy.ravel() * square_m, np.zeros(cols * rows)])


def calibrate_intrinsics(images: Sequence[UInt8Array], options: IntrinsicsOptions | None = None) -> IntrinsicsResult:
    """Zhang's calibration from checkerboard images of one camera (all the same size)."""
    import cv2

    opts = IntrinsicsOptions() if options is None else options
    if len(images) == 0:
        raise CalibrationError("calibrate_intrinsics needs checkerboard images, got none")
    size = np.asarray(images[0]).shape[:2]
    obj, img_pts, used, rejected = [], [], [], []
    template = board_points(opts.board, opts.square_m).astype(np.float32)
    for i, image in enumerate(images):
        if np.asarray(image).shape[:2] != size:
            raise CalibrationError(
                f"image {i} is {np.asarray(image).shape[:2]} but image 0 is {size}; all images must share a size",
                (i,),
            )
        try:
            corners = find_checkerboard(image, opts.board, opts.subpix_window)
        except CalibrationError:
            rejected.append(i)
            continue
        obj.append(template)
        img_pts.append(corners.astype(np.float32).reshape(-1, 1, 2))
        used.append(i)
    if len(used) < opts.min_images:
        raise CalibrationError(
            f"board found in {len(used)} of {len(images)} images, need {opts.min_images}; "
            f"check --board (inner corners) and lighting. Images without a board: {rejected}",
            tuple(rejected),
        )
    flags = 0
    if opts.n_distortion == 4:
        flags |= cv2.CALIB_FIX_K3
    elif opts.n_distortion == 0:
        flags |= cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST
    h, w = int(size[0]), int(size[1])
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 200, 1e-12)
    rms, k, dist, rvecs, tvecs = cv2.calibrateCamera(obj, img_pts, (w, h), None, None, flags=flags, criteria=criteria)
    per_image = []
    for o, p, r, t in zip(obj, img_pts, rvecs, tvecs, strict=True):
        proj, _ = cv2.projectPoints(o, r, t, k, dist)
        per_image.append(float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - p.reshape(-1, 2)) ** 2, axis=1)))))
    d = np.asarray(dist, dtype=np.float64).reshape(-1)[:5]
    camera = Camera(np.asarray(k, dtype=np.float64), w, h, d)
    logger.info("intrinsics from %d images: rms %.3f px", len(used), rms)
    return IntrinsicsResult(camera, float(rms), np.array(per_image), tuple(used), tuple(rejected))


# -------------------------------------------------------------------------------------------------
# extrinsics
# -------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ExtrinsicsOptions:
    """Settings of `calibrate_extrinsics`.

    Attributes:
        refine: run Levenberg-Marquardt on the reprojection error after EPnP.
        min_separation_m: world points closer than this are duplicates (metres).
        min_pixel_separation_px: pixels closer than this are duplicates.
        collinear_tol: relative singular-value threshold for collinear / coplanar-degenerate sets.
        max_rms_px: a solution whose reprojection RMS exceeds this (pixels) is rejected, naming the worst points.
            Surveyed points clicked to a pixel give well under 1 px; 2 px leaves room for a survey error of a
            few millimetres at 1 m, while a u/v mix-up or a mis-numbered point gives more.
        floor_z_m: world height (z up, metres) the camera must be above; None: the lowest control point (a
            camera below every control point looks up at them: u and v swapped or a world frame with z down).
        max_distance_m: control points spanning more than this, or a camera farther than this from them, are
            refused as millimetres given for metres.
    """

    refine: bool = True
    min_separation_m: float = 1e-4
    min_pixel_separation_px: float = 0.5
    collinear_tol: float = 1e-3
    max_rms_px: float = 2.0
    floor_z_m: float | None = None
    max_distance_m: float = MAX_CAMERA_DISTANCE_M

    def __post_init__(self) -> None:
        for name in ("min_separation_m", "min_pixel_separation_px", "collinear_tol", "max_rms_px", "max_distance_m"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise InputError(f"ExtrinsicsOptions.{name} must be finite and > 0, got {value}")
        if self.floor_z_m is not None and not np.isfinite(self.floor_z_m):
            raise InputError(f"ExtrinsicsOptions.floor_z_m must be finite (metres) or None, got {self.floor_z_m}")


@dataclass(frozen=True, eq=False)
class ExtrinsicsResult:
    """camera (with world_from_camera); residuals_px (N,) reprojection error per point; residuals_m (N,)
    distance of each world point from its pixel's viewing ray (metres); rms_px; method used."""

    camera: Camera
    world_from_camera: FloatArray
    residuals_px: FloatArray
    residuals_m: FloatArray
    rms_px: float
    method: str


@dataclass(frozen=True, eq=False)
class ControlPoints:
    """Surveyed control points: names (N,), world (N, 3) metres, pixels (N, 2)."""

    names: tuple[str, ...]
    world: FloatArray
    pixels: FloatArray


def read_control_points(path: str | Path) -> ControlPoints:
    """Read a control-point CSV with columns x, y, z, u, v (metres, pixels) and an optional name column."""
    p = Path(path)
    try:
        with p.open(newline="", encoding="utf-8") as fh:
            rows = list(csv.DictReader(fh))
    except OSError as exc:
        raise InputError(f"cannot read control points {p}: {exc}") from exc
    except (UnicodeDecodeError, csv.Error) as exc:
        raise InputError(f"{p} is not a UTF-8 CSV file: {exc}") from exc
    if not rows:
        raise CalibrationError(f"{p} holds no control points (expected a header name,x,y,z,u,v and rows)")
    needed = {"x", "y", "z", "u", "v"}
    header = {k.strip().lower() for k in rows[0] if k is not None}
    if not needed <= header:
        raise InputError(f"{p}: columns x, y, z, u, v are required, got {sorted(header)}")
    names, world, pixels = [], [], []
    for i, row in enumerate(rows):
        r = {k.strip().lower(): (v or "").strip() for k, v in row.items() if k is not None}
        try:
            world.append([float(r["x"]), float(r["y"]), float(r["z"])])
            pixels.append([float(r["u"]), float(r["v"])])
        except ValueError as exc:
            raise CalibrationError(f"{p} row {i + 2}: not a number ({exc})", (i,)) from exc
        names.append(r.get("name") or r.get("id") or f"P{i}")
    return ControlPoints(tuple(names), np.array(world), np.array(pixels))


def write_control_points(path: str | Path, points: ControlPoints) -> None:
    """Write control points as CSV (name,x,y,z,u,v)."""
    with Path(path).open("w", newline="") as fh:
        out = csv.writer(fh)
        out.writerow(["name", "x", "y", "z", "u", "v"])
        for n, xyz, uv in zip(points.names, points.world, points.pixels, strict=True):
            out.writerow([n, *(f"{v:.6f}" for v in xyz), *(f"{v:.4f}" for v in uv)])


def check_control_points(world: ArrayLike, pixels: ArrayLike, options: ExtrinsicsOptions | None = None) -> None:
    """Raise CalibrationError (naming the point indices) for sets that cannot define a camera pose."""
    opts = ExtrinsicsOptions() if options is None else options
    try:
        w = as_float_array(world, "world points", (None, 3))
        px = as_float_array(pixels, "pixels", (None, 2))
    except InputError as exc:
        raise CalibrationError(f"control points: {exc}") from exc
    n = len(w)
    if len(px) != n:
        raise CalibrationError(f"got {n} world points but {len(px)} pixels")
    if n < 4:
        raise CalibrationError(f"extrinsics need at least 4 control points, got {n}", tuple(range(n)))
    dw = np.linalg.norm(w[:, None] - w[None], axis=2)
    dp = np.linalg.norm(px[:, None] - px[None], axis=2)
    iu = np.triu_indices(n, 1)
    span = float(dw.max())
    if span > opts.max_distance_m:
        far = tuple(sorted(int(v) for v in np.unravel_index(int(np.argmax(dw)), dw.shape)))
        raise CalibrationError(
            f"control points span {span:.4g} m (points {far[0]} and {far[1]}; more than {opts.max_distance_m:g} m "
            "across a cell): looks like millimetres; give x, y, z in metres",
            far,
        )
    dup = [(int(i), int(j)) for i, j in zip(*iu, strict=True) if dw[i, j] < opts.min_separation_m]
    if dup:
        raise CalibrationError(
            f"duplicate world points (closer than {opts.min_separation_m} m): pairs {dup}",
            tuple(sorted({*sum(dup, ())})),
        )
    dupp = [(int(i), int(j)) for i, j in zip(*iu, strict=True) if dp[i, j] < opts.min_pixel_separation_px]
    if dupp:
        raise CalibrationError(
            f"two control points share a pixel (closer than {opts.min_pixel_separation_px} px): pairs {dupp}",
            tuple(sorted({*sum(dupp, ())})),
        )
    all_idx = tuple(range(n))
    if _rank(w, opts.collinear_tol) < 2:
        raise CalibrationError(
            f"control points {list(all_idx)} are collinear in the world; add off-line points", all_idx
        )
    if _rank(np.column_stack([px, np.zeros(n)]), opts.collinear_tol) < 2:
        raise CalibrationError(f"control points {list(all_idx)} are collinear in the image", all_idx)
    if _rank(w, opts.collinear_tol) == 2:
        # coplanar: need 4 points in general position (no point set where all but one are collinear)
        for i in range(n):
            rest = np.delete(w, i, axis=0)
            if _rank(rest, opts.collinear_tol) < 2:
                others = tuple(j for j in range(n) if j != i)
                raise CalibrationError(
                    f"coplanar control points with {list(others)} on one line: degenerate; add points off that line",
                    others,
                )
        if n == 4:
            for trio in itertools.combinations(range(4), 3):
                if _rank(w[list(trio)], opts.collinear_tol) < 2:
                    raise CalibrationError(f"control points {list(trio)} are collinear (4 coplanar points)", trio)


def calibrate_extrinsics(
    camera: Camera, world: ArrayLike, pixels: ArrayLike, options: ExtrinsicsOptions | None = None
) -> ExtrinsicsResult:
    """`world_from_camera` from >= 4 control points: EPnP, then LM refinement; per-point residuals.

    Pixels are raw image coordinates; the camera's distortion is applied by OpenCV.
    """
    import cv2

    opts = ExtrinsicsOptions() if options is None else options
    check_control_points(world, pixels, opts)
    w = np.asarray(world, dtype=np.float64).reshape(-1, 3)
    px = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    k, dist = camera.K, camera.distortion
    candidates: list[tuple[float, str, FloatArray, FloatArray]] = []
    behind: tuple[float, tuple[int, ...]] | None = None
    methods = [("epnp", cv2.SOLVEPNP_EPNP), ("sqpnp", cv2.SOLVEPNP_SQPNP)]
    if _rank(w, opts.collinear_tol) == 2:
        methods.append(("ippe", cv2.SOLVEPNP_IPPE))
    for name, flag in methods:
        try:
            ok, rvec, tvec = cv2.solvePnP(w, px, k, dist, flags=flag)
        except cv2.error as exc:
            logger.debug("solvePnP %s failed: %s", name, exc)
            continue
        if not ok or not np.all(np.isfinite(rvec)) or not np.all(np.isfinite(tvec)):
            continue
        if opts.refine:
            rvec, tvec = cv2.solvePnPRefineLM(w, px, k, dist, rvec, tvec)
            name += "+lm"
        proj, _ = cv2.projectPoints(w, rvec, tvec, k, dist)
        rms = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - px) ** 2, axis=1))))
        cam_pts = transform_points(_pose(rvec, tvec), w)
        if np.all(cam_pts[:, 2] > 0):
            candidates.append((rms, name, np.asarray(rvec, dtype=np.float64), np.asarray(tvec, dtype=np.float64)))
        else:
            idx = tuple(int(i) for i in np.nonzero(cam_pts[:, 2] <= 0)[0])
            if behind is None or rms < behind[0]:
                behind = (rms, idx)
    if not candidates:
        idx = behind[1] if behind is not None else tuple(range(len(w)))
        raise CalibrationError(
            f"control points {list(idx)} lie behind the camera in the best pose; check their pixel/world "
            "correspondences (order, units in metres) and the intrinsics",
            idx,
        )
    rms, method, rvec, tvec = min(candidates, key=lambda c: c[0])
    camera_from_world = _pose(rvec, tvec)
    wfc = invert_pose(camera_from_world)
    wfc[:3, :3] = check_rotation(wfc[:3, :3], "solved camera rotation")
    _check_plausible(wfc, w, opts)
    cam = camera.with_extrinsics(wfc)
    proj, _ = cv2.projectPoints(w, rvec, tvec, k, dist)
    res_px = np.linalg.norm(proj.reshape(-1, 2) - px, axis=1)
    res_m = _ray_distances(cam, w, px)
    if rms > opts.max_rms_px:
        worst = tuple(int(i) for i in np.argsort(-res_px)[: max(1, len(w) // 4)])
        raise CalibrationError(
            f"extrinsics reprojection RMS {rms:.2f} px exceeds {opts.max_rms_px} px; worst points {list(worst)} "
            f"({[round(float(res_px[i]), 2) for i in worst]} px): re-survey or re-click them, and check that the "
            "u, v columns are not swapped",
            worst,
        )
    logger.info("extrinsics (%s) from %d points: rms %.3f px", method, len(w), rms)
    return ExtrinsicsResult(cam, wfc, res_px, res_m, rms, method)


def _check_plausible(world_from_camera: FloatArray, world: FloatArray, opts: ExtrinsicsOptions) -> None:
    """Refuse a solved camera that cannot be real: under the floor (world z up) or implausibly far from its points."""
    centre = world_from_camera[:3, 3]
    dist = np.linalg.norm(world - centre, axis=1)
    if float(dist.max()) > opts.max_distance_m:
        raise CalibrationError(
            f"the solved camera is {float(dist.max()):.4g} m from control point {int(np.argmax(dist))} (more than "
            f"{opts.max_distance_m:g} m): looks like millimetres; give x, y, z in metres",
            (int(np.argmax(dist)),),
        )
    lowest = int(np.argmin(world[:, 2]))
    floor = float(world[lowest, 2]) if opts.floor_z_m is None else float(opts.floor_z_m)
    if centre[2] < floor:
        where = f"control point {lowest} (z = {floor:.3f} m)" if opts.floor_z_m is None else f"z = {floor:.3f} m"
        raise CalibrationError(
            f"the solved camera is at z = {centre[2]:.3f} m, below the floor at {where} (world z up): a camera "
            "cannot look up at the parts; check that the u, v columns are not swapped and that the world z axis "
            "points up (give floor_z_m / --floor-z for a camera that really sits below its points)",
            tuple(range(len(world))),
        )


def _ray_distances(camera: Camera, world: FloatArray, pixels: FloatArray) -> FloatArray:
    """(N,) distance in metres of each world point from the viewing ray of its pixel."""
    pts_cam = transform_points(camera.camera_from_world, world)
    xy = camera.normalized_coordinates(pixels)
    rays = np.column_stack([xy, np.ones(len(xy))])
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    along = np.einsum("ij,ij->i", pts_cam, rays)
    return np.asarray(np.linalg.norm(pts_cam - along[:, None] * rays, axis=1))


def _pose(rvec: ArrayLike, tvec: ArrayLike) -> FloatArray:
    import cv2

    rot, _ = cv2.Rodrigues(np.asarray(rvec, dtype=np.float64).reshape(3, 1))
    pose = np.eye(4)
    pose[:3, :3] = rot
    pose[:3, 3] = np.asarray(tvec, dtype=np.float64).reshape(3)
    return pose


def _rank(points: FloatArray, tol: float) -> int:
    """Affine rank (0 point, 1 line, 2 plane, 3 volume) with a tolerance relative to the largest spread."""
    c = points - points.mean(axis=0)
    s = np.linalg.svd(c, compute_uv=False)
    if s[0] <= 1e-12:
        return 0
    return int(np.sum(s > tol * s[0]))
