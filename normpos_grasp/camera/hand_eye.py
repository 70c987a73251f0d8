"""Hand-eye calibration of a UR cell from checkerboard images and flange poses: eye-to-hand and eye-in-hand.

Modes (poses named `a_from_b`, metres):
    eye-to-hand: the camera is fixed in the cell, the board is on the flange. Unknowns `base_from_camera` (X)
        and `flange_from_board` (W): base_from_flange_i @ W = X @ camera_from_board_i.
    eye-in-hand: the camera is on the wrist, the board is fixed in the cell. Unknowns `flange_from_camera` (X)
        and `base_from_board` (W): base_from_flange_i @ X @ camera_from_board_i = W.

Both read P_i @ X @ C_i = W with P_i = base_from_flange_i (eye-in-hand) or its inverse (eye-to-hand) and
C_i = camera_from_board_i. The board pose of every image comes from its corners (OpenCV's detector, IPPE +
Levenberg-Marquardt PnP with the camera's intrinsics). OpenCV's hand-eye solvers (`cv2.calibrateHandEye`, five
methods, and `cv2.calibrateRobotWorldHandEye`, two) give the starting points where the installed OpenCV exposes
them to Python (the 5.0.0 wheels do not: opencv/opencv#29565); two closed-form solvers of this module always run
as well (Park and Martin's pairwise AX = XB, and a linear AX = ZB solve over all poses at once). The candidate
with the lowest corner reprojection error wins, then X and W are refined jointly by minimising the reprojection
error of every corner in every image (scipy least_squares, soft-L1 loss).

Flange poses are UR pose vectors [x, y, z, rx, ry, rz] (metres, rotation vector in radians) as
`getActualTCPPose` reports them with a zero TCP. A constant non-zero TCP is absorbed into the result (W becomes
tcp_from_board for eye-to-hand; X becomes tcp_from_camera for eye-in-hand): use the same TCP when using it.

Board convention (that of `calibration.board_points`): inner corners in OpenCV's row-major order, the board
frame at corner 0, x along the `cols` side, y along the `rows` side, z into the board. For a board whose
`cols + rows` is odd (9x6) the two ends differ in colour and corner 0 is the one whose diagonal outer square is
black; boards with `cols + rows` even look the same turned by 180 degrees and are refused.
"""

from __future__ import annotations

import itertools
import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from normpos_grasp.camera.calibration import board_points, find_checkerboard
from normpos_grasp.camera.model import Camera
from normpos_grasp.errors import CalibrationError, InputError
from normpos_grasp.geometry.transforms import (
    invert_pose,
    make_pose,
    pose_from_ur,
    rotation_angle,
    rotation_from_rotvec,
    rotation_to_rotvec,
    transform_points,
)
from normpos_grasp.typing import ArrayLike, FloatArray, UInt8Array
from normpos_grasp.validation import as_float_array

logger = logging.getLogger(__name__)

EYE_TO_HAND = "eye-to-hand"
EYE_IN_HAND = "eye-in-hand"
MODES = (EYE_TO_HAND, EYE_IN_HAND)
#: a flange farther than this from the robot base (metres) is a pose given in millimetres; UR arms reach 1.75 m
MAX_FLANGE_DISTANCE_M = 5.0
#: a rotation vector longer than this (radians) is degrees; UR controllers report |r| <= pi
MAX_ROTVEC_RAD = 2.0 * np.pi


@dataclass(frozen=True)
class HandEyeOptions:
    """Settings of `calibrate_hand_eye`.

    Attributes:
        board: inner corners (columns, rows); `cols + rows` must be odd (9x6) so corner 0 is unambiguous.
        square_m: square edge, metres.
        subpix_window: half-size of the corner refinement window, pixels.
        min_poses: fewest images with a detected board.
        loss, loss_scale_px: robust loss of the joint refinement (scipy least_squares) and its scale, pixels.
        max_rms_px: a calibration whose reprojection RMS exceeds this (pixels) is refused, naming the worst poses.
        min_rotation_deg: the largest rotation between two poses must reach this (degrees), else refused.
        min_axis_spread_deg: the RMS rotation about the second principal axis of the relative rotations must
            reach this (degrees), else the rotations are about one axis and the set is refused.
        warn_axis_spread_deg: below this RMS rotation (degrees) about any principal axis, a warning names the axis.
    """

    board: tuple[int, int] = (9, 6)
    square_m: float = 0.025
    subpix_window: int = 5
    min_poses: int = 3
    loss: str = "soft_l1"
    loss_scale_px: float = 1.0
    max_rms_px: float = 2.0
    min_rotation_deg: float = 5.0
    min_axis_spread_deg: float = 2.0
    warn_axis_spread_deg: float = 5.0

    def __post_init__(self) -> None:
        if len(self.board) != 2 or min(self.board) < 2:
            raise InputError(f"board must give inner corners (cols, rows), each >= 2, got {self.board}")
        if (self.board[0] + self.board[1]) % 2 == 0:
            raise InputError(
                f"a {self.board[0]}x{self.board[1]} board looks the same turned by 180 degrees, so its corner 0 is "
                "ambiguous; use a board with an odd and an even inner-corner count (9x6, 7x6, 11x8)"
            )
        if not (np.isfinite(self.square_m) and 0 < self.square_m <= 1.0):
            raise InputError(f"square_m must be in (0, 1] metres, got {self.square_m}")
        if self.min_poses < 3:
            raise InputError(f"min_poses must be >= 3 (hand-eye needs two independent motions), got {self.min_poses}")
        if self.loss not in ("linear", "soft_l1", "huber", "cauchy", "arctan"):
            raise InputError(f"loss must be a scipy least_squares loss, got {self.loss!r}")
        for name in ("loss_scale_px", "max_rms_px", "min_rotation_deg", "min_axis_spread_deg", "warn_axis_spread_deg"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise InputError(f"HandEyeOptions.{name} must be finite and > 0, got {value}")


@dataclass(frozen=True, eq=False)
class BoardView:
    """One detected board: corners_px (K, 2) in `board_points` order; camera_from_board (4, 4) from PnP;
    pnp_rms_px its reprojection RMS."""

    corners_px: FloatArray
    camera_from_board: FloatArray
    pnp_rms_px: float


@dataclass(frozen=True, eq=False)
class ExcitationReport:
    """How well a pose set excites the rotation axes.

    spread_deg (3,): RMS rotation about the principal axes of all pairwise relative rotations, largest first,
    degrees; axes (3, 3): those axes as columns, in `frame` ("base" for eye-to-hand, "flange" for eye-in-hand);
    max_rotation_deg: the largest rotation between two poses; degenerate: the set cannot determine the
    calibration (reason in `message`); warnings: weak but usable excitation, each saying what to add."""

    spread_deg: FloatArray
    axes: FloatArray
    max_rotation_deg: float
    frame: str
    degenerate: bool
    message: str
    warnings: tuple[str, ...]


@dataclass(frozen=True, eq=False)
class HandEyeResult:
    """A hand-eye calibration.

    camera_pose (4, 4): base_from_camera (eye-to-hand) or flange_from_camera (eye-in-hand); board_pose (4, 4):
    flange_from_board or base_from_board. Per used pose (arrays of length M, in `used` order): reprojection_rms_px,
    reprojection_max_px (corner reprojection through the calibration), consistency_mm / consistency_deg (the
    flange pose the image implies, base_from_flange from board pose and calibration, against the robot's; at the
    flange origin). rms_px over all corners; used / rejected image indices (rejected: no board found); method of
    the starting solution, with candidates {method: reprojection RMS px}; std_position_mm / std_rotation_deg: 1-sigma
    of the camera pose from the refinement's Jacobian (position per axis of the parent frame, rotation per camera
    axis); start_camera_pose (4, 4): the camera pose of the starting solution, before the joint refinement;
    excitation; warnings."""

    mode: str
    camera_pose: FloatArray
    board_pose: FloatArray
    reprojection_rms_px: FloatArray
    reprojection_max_px: FloatArray
    consistency_mm: FloatArray
    consistency_deg: FloatArray
    rms_px: float
    used: tuple[int, ...]
    rejected: tuple[int, ...]
    method: str
    candidates: dict[str, float]
    std_position_mm: FloatArray
    std_rotation_deg: FloatArray
    excitation: ExcitationReport
    start_camera_pose: FloatArray = field(default_factory=lambda: np.eye(4))
    warnings: tuple[str, ...] = ()
    board: tuple[int, int] = (9, 6)
    square_m: float = 0.025
    views: tuple[BoardView, ...] = field(default=(), repr=False)

    @property
    def camera_pose_name(self) -> str:
        return "base_from_camera" if self.mode == EYE_TO_HAND else "flange_from_camera"

    @property
    def board_pose_name(self) -> str:
        return "flange_from_board" if self.mode == EYE_TO_HAND else "base_from_board"

    def report_lines(self) -> list[str]:
        """Human-readable residual report: one line per used pose, then the summary."""
        lines = [
            f"{self.mode}: {self.camera_pose_name} position {np.round(self.camera_pose[:3, 3], 5).tolist()} m, "
            f"rotation vector {np.round(rotation_to_rotvec(self.camera_pose[:3, :3]), 5).tolist()} rad",
            f"start: {self.method} (candidates, RMS px: "
            + ", ".join(f"{k} {v:.3f}" for k, v in sorted(self.candidates.items(), key=lambda kv: kv[1]))
            + ")",
            f"  {'pose':>4}  {'reproj RMS px':>13}  {'max px':>7}  {'flange mm':>9}  {'flange deg':>10}",
        ]
        for k, i in enumerate(self.used):
            lines.append(
                f"  {i:>4}  {self.reprojection_rms_px[k]:>13.3f}  {self.reprojection_max_px[k]:>7.3f}  "
                f"{self.consistency_mm[k]:>9.3f}  {self.consistency_deg[k]:>10.4f}"
            )
        for i in self.rejected:
            lines.append(f"  {i:>4}  no board found: skipped")
        lines.append(
            f"RMS {self.rms_px:.3f} px over {len(self.used)} poses; camera pose 1-sigma "
            f"{float(np.linalg.norm(self.std_position_mm)):.3f} mm, {float(np.linalg.norm(self.std_rotation_deg)):.4f} "
            f"deg; rotation spread {np.round(self.excitation.spread_deg, 1).tolist()} deg about the principal axes"
        )
        lines.extend(f"warning: {w}" for w in self.warnings)
        return lines

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready record of the calibration and its residuals (metres, radians; residuals in px, mm, deg)."""
        return {
            "mode": self.mode,
            self.camera_pose_name: self.camera_pose.tolist(),
            self.board_pose_name: self.board_pose.tolist(),
            "board": list(self.board),
            "square_m": self.square_m,
            "rms_px": self.rms_px,
            "method": self.method,
            "candidates_rms_px": self.candidates,
            "std_position_mm": self.std_position_mm.tolist(),
            "std_rotation_deg": self.std_rotation_deg.tolist(),
            "poses": [
                {
                    "index": i,
                    "reprojection_rms_px": float(self.reprojection_rms_px[k]),
                    "reprojection_max_px": float(self.reprojection_max_px[k]),
                    "consistency_mm": float(self.consistency_mm[k]),
                    "consistency_deg": float(self.consistency_deg[k]),
                }
                for k, i in enumerate(self.used)
            ],
            "rejected": list(self.rejected),
            "excitation": {
                "frame": self.excitation.frame,
                "spread_deg": self.excitation.spread_deg.tolist(),
                "axes": self.excitation.axes.T.tolist(),
                "max_rotation_deg": self.excitation.max_rotation_deg,
            },
            "warnings": list(self.warnings),
        }


@dataclass(frozen=True, eq=False)
class TouchCheck:
    """A touch-point verification: the board corner `corner` (index in `board_points` order) predicted in the
    robot base frame by the calibration, the TCP position touched on it (metres) and their distance (mm)."""

    corner: int
    predicted_base_m: FloatArray
    touched_base_m: FloatArray
    distance_mm: float


@dataclass(frozen=True, eq=False)
class ImageCheck:
    """A verification image at a new flange pose: residuals_px (K,) between the detected corners and the
    corners the calibration predicts; rms_px, max_px."""

    residuals_px: FloatArray
    rms_px: float
    max_px: float


# -------------------------------------------------------------------------------------------------
# input checks
# -------------------------------------------------------------------------------------------------
def check_mode(mode: str) -> str:
    if mode not in MODES:
        raise InputError(f"mode must be {' or '.join(MODES)}, got {mode!r}")
    return mode


def check_flange_poses(poses: ArrayLike, name: str = "base_from_flange") -> FloatArray:
    """(N, 4, 4) flange poses from (N, 6) UR pose vectors [x, y, z, rx, ry, rz] or (N, 4, 4) matrices.

    Raises InputError for non-finite values, a flange farther than MAX_FLANGE_DISTANCE_M from the base
    (millimetres), a rotation vector longer than 2 pi (degrees) or a matrix that is not a rigid pose; the
    message names the pose index."""
    try:
        arr = np.array(poses, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name}: expected (N, 6) UR pose vectors or (N, 4, 4) poses") from exc
    if arr.ndim == 2 and arr.shape[1] == 6:
        vectors = arr
    elif arr.ndim == 3 and arr.shape[1:] == (4, 4):
        vectors = None
    else:
        raise InputError(f"{name}: expected (N, 6) UR pose vectors or (N, 4, 4) poses, got shape {arr.shape}")
    bad = np.nonzero(~np.all(np.isfinite(arr.reshape(len(arr), -1)), axis=1))[0]
    if bad.size:
        raise InputError(f"{name}: pose {int(bad[0])} holds NaN or inf values")
    if vectors is not None:
        rot_norm = np.linalg.norm(vectors[:, 3:], axis=1)
        if np.any(rot_norm > MAX_ROTVEC_RAD):
            i = int(np.argmax(rot_norm))
            raise InputError(
                f"{name}: pose {i} has a rotation vector of length {rot_norm[i]:.4g} (more than 2 pi): looks like "
                "degrees; rx, ry, rz are a UR rotation vector in radians"
            )
        mats = np.stack([pose_from_ur(v) for v in vectors]) if len(vectors) else np.zeros((0, 4, 4))
    else:
        mats = arr
        for i, m in enumerate(mats):
            rot = m[:3, :3]
            if (
                not np.allclose(m[3], [0, 0, 0, 1], atol=1e-9)
                or not np.allclose(rot.T @ rot, np.eye(3), atol=1e-6)
                or np.linalg.det(rot) < 0
            ):
                raise InputError(f"{name}: pose {i} is not a rigid transform (rotation block or last row)")
    dist = np.linalg.norm(mats[:, :3, 3], axis=1) if len(mats) else np.zeros(0)
    if np.any(dist > MAX_FLANGE_DISTANCE_M):
        i = int(np.argmax(dist))
        raise InputError(
            f"{name}: pose {i} puts the flange {dist[i]:.4g} m from the robot base (more than "
            f"{MAX_FLANGE_DISTANCE_M:g} m): looks like millimetres; x, y, z are metres, as getActualTCPPose reports"
        )
    return np.asarray(mats)


# -------------------------------------------------------------------------------------------------
# board views
# -------------------------------------------------------------------------------------------------
def detect_board(image: ArrayLike, camera: Camera, options: HandEyeOptions | None = None) -> BoardView:
    """Find the board in an 8-bit image and solve its pose (IPPE, then Levenberg-Marquardt) with the
    camera's intrinsics and distortion. Raises CalibrationError when no board is found."""
    opts = HandEyeOptions() if options is None else options
    corners = find_checkerboard(image, opts.board, opts.subpix_window)
    corners = _canonical_order(_gray(image), corners, opts.board, opts.square_m)
    return board_view(camera, corners, opts)


def board_view(camera: Camera, corners_px: ArrayLike, options: HandEyeOptions | None = None) -> BoardView:
    """Board pose from its (K, 2) corner pixels in `board_points` order (distorted pixels, as detected)."""
    import cv2

    opts = HandEyeOptions() if options is None else options
    obj = board_points(opts.board, opts.square_m)
    px = as_float_array(corners_px, "corners_px", (len(obj), 2))
    k, dist = camera.K, camera.distortion
    ok, rvec, tvec = cv2.solvePnP(obj, px, k, dist, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        raise CalibrationError("solvePnP found no board pose for these corners")
    rvec, tvec = cv2.solvePnPRefineLM(obj, px, k, dist, rvec, tvec)
    pose = make_pose(cv2.Rodrigues(rvec)[0], np.asarray(tvec, dtype=np.float64).reshape(3))
    if np.any(transform_points(pose, obj)[:, 2] <= 0):
        raise CalibrationError("the solved board pose puts corners behind the camera; check the intrinsics")
    res = camera.project(transform_points(pose, obj)) - px
    return BoardView(px, pose, float(np.sqrt(np.mean(np.sum(res**2, axis=1)))))


def _gray(image: ArrayLike) -> UInt8Array:
    import cv2

    img = np.asarray(image)
    if img.ndim == 3:
        return np.asarray(cv2.cvtColor(np.ascontiguousarray(img[:, :, :3]), cv2.COLOR_RGB2GRAY), dtype=np.uint8)
    return np.asarray(img, dtype=np.uint8)


def _canonical_order(gray: UInt8Array, corners: FloatArray, board: tuple[int, int], square_m: float) -> FloatArray:
    """Corners reversed when the detector started at the wrong end: corner 0's diagonal outer square is black."""
    import cv2

    obj = board_points(board, square_m)[:, :2]
    h, _ = cv2.findHomography(obj, corners, 0)
    if h is None:
        return corners
    cols, rows = board
    probes = np.array([[-0.5, -0.5], [cols - 0.5, rows - 0.5]]) * square_m
    px = cv2.perspectiveTransform(probes.reshape(-1, 1, 2), h).reshape(-1, 2)
    values = []
    for u, v in px:
        iu, iv = int(round(u)), int(round(v))
        if not (2 <= iu < gray.shape[1] - 2 and 2 <= iv < gray.shape[0] - 2):
            return corners  # a corner square outside the image: keep the detector's order
        values.append(float(gray[iv - 2 : iv + 3, iu - 2 : iu + 3].mean()))
    return corners[::-1].copy() if values[0] > values[1] else corners


# -------------------------------------------------------------------------------------------------
# excitation
# -------------------------------------------------------------------------------------------------
def check_excitation(base_from_flange: ArrayLike, mode: str, options: HandEyeOptions | None = None) -> ExcitationReport:
    """Spread of the relative rotations of a flange-pose set (see `ExcitationReport`); never raises for a weak set."""
    opts = HandEyeOptions() if options is None else options
    check_mode(mode)
    mats = check_flange_poses(base_from_flange)
    frame = "base" if mode == EYE_TO_HAND else "flange"
    rots = [m[:3, :3] for m in mats]
    vecs = []
    for i, j in itertools.combinations(range(len(rots)), 2):
        rel = rots[j] @ rots[i].T if mode == EYE_TO_HAND else rots[j].T @ rots[i]
        vecs.append(rotation_to_rotvec(rel))
    if not vecs:
        return ExcitationReport(np.zeros(3), np.eye(3), 0.0, frame, True, "fewer than 2 poses", ())
    r = np.asarray(vecs)
    scatter = r.T @ r / len(r)
    evals, evecs = np.linalg.eigh(scatter)
    order = np.argsort(evals)[::-1]
    spread = np.degrees(np.sqrt(np.clip(evals[order], 0.0, None)))
    axes = evecs[:, order]
    max_rot = float(np.degrees(np.max(np.linalg.norm(r, axis=1))))

    def ax(k: int) -> str:
        v = axes[:, k] * (1.0 if axes[np.argmax(np.abs(axes[:, k])), k] >= 0 else -1.0)
        return f"{frame} [{v[0]:.2f}, {v[1]:.2f}, {v[2]:.2f}]"

    degenerate, message, warnings = False, "", []
    if max_rot < opts.min_rotation_deg:
        degenerate = True
        message = (
            f"the flange rotates at most {max_rot:.1f} deg between poses (need {opts.min_rotation_deg:g}): add poses "
            "tilted 15-30 deg about two different axes"
        )
    elif spread[1] < opts.min_axis_spread_deg:
        degenerate = True
        message = (
            f"the flange rotations are nearly all about one axis ({ax(0)}; RMS spread {spread[0]:.1f} / "
            f"{spread[1]:.1f} / {spread[2]:.1f} deg about the principal axes): the offset along that axis cannot be "
            f"found; add poses tilted 15-30 deg about {ax(1)} and {ax(2)}"
        )
    else:
        for k in (1, 2):
            if spread[k] < opts.warn_axis_spread_deg:
                warnings.append(
                    f"little rotation about {ax(k)} (RMS {spread[k]:.1f} deg, less than "
                    f"{opts.warn_axis_spread_deg:g}): add poses tilted 15-30 deg about it"
                )
    return ExcitationReport(spread, axes, max_rot, frame, degenerate, message, tuple(warnings))


# -------------------------------------------------------------------------------------------------
# calibration
# -------------------------------------------------------------------------------------------------
def calibrate_hand_eye(
    camera: Camera,
    images: Sequence[ArrayLike],
    base_from_flange: ArrayLike,
    mode: str,
    options: HandEyeOptions | None = None,
) -> HandEyeResult:
    """Hand-eye calibration from checkerboard images and the flange pose of each (see the module docstring).

    images: 8-bit gray or RGB, one per pose; base_from_flange: (N, 6) UR pose vectors or (N, 4, 4). Images without
    a board are skipped (`rejected`). Raises InputError (mismatched counts, bad poses) or CalibrationError (too few
    boards, a degenerate pose set, a reprojection RMS over `max_rms_px`)."""
    opts = HandEyeOptions() if options is None else options
    check_mode(mode)
    mats = check_flange_poses(base_from_flange)
    if len(images) != len(mats):
        raise InputError(f"got {len(images)} images but {len(mats)} flange poses; give one pose per image")
    views: list[BoardView | None] = []
    for i, image in enumerate(images):
        try:
            views.append(detect_board(image, camera, opts))
        except CalibrationError as exc:
            logger.info("image %d: %s", i, exc)
            views.append(None)
    return _calibrate(camera, views, mats, mode, opts)


def calibrate_hand_eye_from_corners(
    camera: Camera,
    corners_px: Sequence[ArrayLike | None],
    base_from_flange: ArrayLike,
    mode: str,
    options: HandEyeOptions | None = None,
) -> HandEyeResult:
    """As `calibrate_hand_eye`, from detected corners per pose ((K, 2) in `board_points` order, None: no board)."""
    opts = HandEyeOptions() if options is None else options
    check_mode(mode)
    mats = check_flange_poses(base_from_flange)
    if len(corners_px) != len(mats):
        raise InputError(f"got corners for {len(corners_px)} images but {len(mats)} flange poses")
    views = [None if c is None else board_view(camera, c, opts) for c in corners_px]
    return _calibrate(camera, views, mats, mode, opts)


def _calibrate(
    camera: Camera, views: list[BoardView | None], mats: FloatArray, mode: str, opts: HandEyeOptions
) -> HandEyeResult:
    used = tuple(i for i, v in enumerate(views) if v is not None)
    rejected = tuple(i for i, v in enumerate(views) if v is None)
    if len(used) < opts.min_poses:
        raise CalibrationError(
            f"board found in {len(used)} of {len(views)} images, need {opts.min_poses}; check --board (inner "
            f"corners), focus and lighting. Images without a board: {list(rejected)}",
            rejected,
        )
    good = [v for v in views if v is not None]
    flange = mats[list(used)]
    excitation = check_excitation(flange, mode, opts)
    if excitation.degenerate:
        raise CalibrationError(f"the pose set cannot determine a hand-eye calibration: {excitation.message}", used)
    p = flange if mode == EYE_IN_HAND else np.stack([invert_pose(m) for m in flange])
    c = np.stack([v.camera_from_board for v in good])
    obj = board_points(opts.board, opts.square_m)
    observed = np.stack([v.corners_px for v in good])
    p_inv = np.stack([invert_pose(m) for m in p])

    candidates: dict[str, float] = {}
    best: tuple[float, str, FloatArray, FloatArray] | None = None
    for name, x, w in _initial_solutions(p, c):
        if not (np.all(np.isfinite(x)) and np.all(np.isfinite(w))):
            continue
        res = _residuals(camera, obj, observed, p_inv, x, w)
        rms = float(np.sqrt(np.mean(res**2) * 2.0))
        candidates[name] = rms
        if best is None or rms < best[0]:
            best = (rms, name, x, w)
    if best is None:
        raise CalibrationError("no hand-eye solver found a finite solution; check the poses and images", used)
    _, method, x0, w0 = best
    x, w, std_pos_m, std_rot = _refine(camera, obj, observed, p_inv, x0, w0, opts)

    res = _residuals(camera, obj, observed, p_inv, x, w).reshape(len(used), -1, 2)
    per_norm = np.linalg.norm(res, axis=2)
    rms_each = np.sqrt(np.mean(per_norm**2, axis=1))
    rms = float(np.sqrt(np.mean(per_norm**2)))
    cons_mm, cons_deg = [], []
    for k in range(len(used)):
        implied = _implied_flange(mode, x, w, c[k])
        cons_mm.append(float(np.linalg.norm(implied[:3, 3] - flange[k][:3, 3]) * 1000.0))
        cons_deg.append(float(np.degrees(rotation_angle(implied[:3, :3].T @ flange[k][:3, :3]))))
    if rms > opts.max_rms_px:
        worst = tuple(used[int(k)] for k in np.argsort(-rms_each)[: max(1, len(used) // 4)])
        raise CalibrationError(
            f"hand-eye reprojection RMS {rms:.2f} px exceeds {opts.max_rms_px} px; worst poses {list(worst)} "
            f"({[round(float(rms_each[used.index(i)]), 2) for i in worst]} px): check that the pose rows match the "
            f"images in order, that the mode ({mode}) is right and that the robot held still for each image",
            worst,
        )
    warnings = list(excitation.warnings)
    if rejected:
        warnings.append(f"no board found in images {list(rejected)}: they were skipped")
    for msg in warnings:
        logger.warning("hand-eye: %s", msg)
    logger.info("hand-eye %s from %d poses (%s start): rms %.3f px", mode, len(used), method, rms)
    return HandEyeResult(
        mode=mode,
        camera_pose=x,
        board_pose=w,
        reprojection_rms_px=rms_each,
        reprojection_max_px=per_norm.max(axis=1),
        consistency_mm=np.array(cons_mm),
        consistency_deg=np.array(cons_deg),
        rms_px=rms,
        used=used,
        rejected=rejected,
        method=method,
        candidates=candidates,
        std_position_mm=std_pos_m * 1000.0,
        std_rotation_deg=np.degrees(std_rot),
        excitation=excitation,
        start_camera_pose=x0,
        warnings=tuple(warnings),
        board=opts.board,
        square_m=opts.square_m,
        views=tuple(good),
    )


def _implied_flange(mode: str, x: FloatArray, w: FloatArray, camera_from_board: FloatArray) -> FloatArray:
    """base_from_flange that one board pose implies through the calibration."""
    if mode == EYE_IN_HAND:  # B X C = W  ->  B = W C^-1 X^-1
        return np.asarray(w @ invert_pose(camera_from_board) @ invert_pose(x))
    return np.asarray(x @ camera_from_board @ invert_pose(w))  # B W = X C  ->  B = X C W^-1


def _residuals(
    camera: Camera, obj: FloatArray, observed: FloatArray, p_inv: FloatArray, x: FloatArray, w: FloatArray
) -> FloatArray:
    """Flat reprojection residuals (pixels) of every corner of every image: camera_from_board_i = X^-1 P_i^-1 W
    (`p_inv` (M, 4, 4) holds the P_i^-1); a corner behind the camera counts 1000 px."""
    cfb = invert_pose(x) @ p_inv @ w  # (M, 4, 4)
    pts = np.einsum("mij,kj->mki", cfb[:, :3, :3], obj) + cfb[:, None, :3, 3]  # (M, K, 3)
    behind = pts[..., 2] <= 1e-6
    pts[..., 2] = np.where(behind, 1.0, pts[..., 2])
    out = camera.project(pts.reshape(-1, 3)).reshape(observed.shape) - observed
    out[behind] = 1e3
    return np.asarray(out.reshape(-1))


def _refine(
    camera: Camera,
    obj: FloatArray,
    observed: FloatArray,
    p_inv: FloatArray,
    x0: FloatArray,
    w0: FloatArray,
    opts: HandEyeOptions,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Joint refinement of X and W (right perturbations) on the corner reprojection error; returns X, W and the
    1-sigma of the camera position (metres, per axis of X's parent frame) and rotation (radians, per axis)."""
    from scipy.optimize import least_squares

    def unpack(d: FloatArray) -> tuple[FloatArray, FloatArray]:
        x = x0 @ make_pose(rotation_from_rotvec(d[0:3]), d[3:6])
        w = w0 @ make_pose(rotation_from_rotvec(d[6:9]), d[9:12])
        return x, w

    def fun(d: FloatArray) -> FloatArray:
        x, w = unpack(d)
        return _residuals(camera, obj, observed, p_inv, x, w)

    sol = least_squares(
        fun,
        np.zeros(12),
        method="trf",
        loss=opts.loss,
        f_scale=opts.loss_scale_px,
        x_scale="jac",
        max_nfev=200,
        tr_solver="lsmr",
    )
    x, w = unpack(sol.x)
    # 1-sigma from the Gauss-Newton normal matrix at the solution, scaled by the residual variance
    jac = np.asarray(sol.jac)
    dof = max(len(sol.fun) - 12, 1)
    sigma2 = float(np.sum(sol.fun**2) / dof)
    try:
        cov = np.linalg.inv(jac.T @ jac) * sigma2
    except np.linalg.LinAlgError:
        cov = np.full((12, 12), np.inf)
    rot = x[:3, :3]
    cov_pos = rot @ cov[3:6, 3:6] @ rot.T  # translation perturbation is in X's own axes
    std_pos = np.sqrt(np.clip(np.diag(cov_pos), 0.0, None))
    std_rot = np.sqrt(np.clip(np.diag(cov[0:3, 0:3]), 0.0, None))
    return x, w, std_pos, std_rot


# -------------------------------------------------------------------------------------------------
# starting solutions
# -------------------------------------------------------------------------------------------------
def _initial_solutions(p: FloatArray, c: FloatArray) -> list[tuple[str, FloatArray, FloatArray]]:
    """Candidate (name, X, W) for P_i X C_i = W: OpenCV's solvers where exposed, then this module's two."""
    out: list[tuple[str, FloatArray, FloatArray]] = []
    out.extend(_opencv_solutions(p, c))
    for name, solver in (("park-martin", _park_martin), ("linear-axzb", _linear_axzb)):
        try:
            x = solver(p, c)
        except (np.linalg.LinAlgError, ValueError) as exc:
            logger.debug("hand-eye solver %s failed: %s", name, exc)
            continue
        if isinstance(x, tuple):
            out.append((name, x[0], x[1]))
        else:
            out.append((name, x, _mean_w(p, c, x)))
    return out


def _opencv_solutions(p: FloatArray, c: FloatArray) -> list[tuple[str, FloatArray, FloatArray]]:
    import cv2

    out: list[tuple[str, FloatArray, FloatArray]] = []
    r_p = [m[:3, :3] for m in p]
    t_p = [m[:3, 3].reshape(3, 1) for m in p]
    r_c = [m[:3, :3] for m in c]
    t_c = [m[:3, 3].reshape(3, 1) for m in c]
    hand_eye = getattr(cv2, "calibrateHandEye", None)
    if hand_eye is not None:
        for name in ("TSAI", "PARK", "HORAUD", "ANDREFF", "DANIILIDIS"):
            try:  # gripper2base = P_i, target2cam = C_i -> cam2gripper = X
                r, t = hand_eye(r_p, t_p, r_c, t_c, method=getattr(cv2, f"CALIB_HAND_EYE_{name}"))
            except cv2.error as exc:
                logger.debug("cv2.calibrateHandEye %s failed: %s", name, exc)
                continue
            x = make_pose(_nearest_rotation(np.asarray(r)), np.asarray(t, dtype=np.float64).reshape(3))
            out.append((f"opencv-{name.lower()}", x, _mean_w(p, c, x)))
    robot_world = getattr(cv2, "calibrateRobotWorldHandEye", None)
    if robot_world is not None:
        c_inv = [invert_pose(m) for m in c]
        r_ci = [m[:3, :3] for m in c_inv]
        t_ci = [m[:3, 3].reshape(3, 1) for m in c_inv]
        for name in ("SHAH", "LI"):
            try:  # cTw = C_i^-1, gTb = P_i -> wTb = X^-1, cTg = W^-1 (C_i^-1 X^-1 = W^-1 P_i)
                r_bw, t_bw, r_gc, t_gc = robot_world(
                    r_ci, t_ci, r_p, t_p, method=getattr(cv2, f"CALIB_ROBOT_WORLD_HAND_EYE_{name}")
                )
            except cv2.error as exc:
                logger.debug("cv2.calibrateRobotWorldHandEye %s failed: %s", name, exc)
                continue
            x_inv = make_pose(_nearest_rotation(np.asarray(r_bw)), np.asarray(t_bw, dtype=np.float64).reshape(3))
            w_inv = make_pose(_nearest_rotation(np.asarray(r_gc)), np.asarray(t_gc, dtype=np.float64).reshape(3))
            out.append((f"opencv-{name.lower()}", invert_pose(x_inv), invert_pose(w_inv)))
    return out


def _nearest_rotation(m: FloatArray) -> FloatArray:
    u, _, vt = np.linalg.svd(np.asarray(m, dtype=np.float64).reshape(3, 3))
    d = np.sign(np.linalg.det(u @ vt)) or 1.0
    return np.asarray(u @ np.diag([1.0, 1.0, d]) @ vt)


def _mean_w(p: FloatArray, c: FloatArray, x: FloatArray) -> FloatArray:
    """W = P_i X C_i averaged over the poses (chordal mean rotation, mean translation)."""
    ws = np.stack([p[i] @ x @ c[i] for i in range(len(p))])
    return make_pose(_nearest_rotation(ws[:, :3, :3].sum(axis=0)), ws[:, :3, 3].mean(axis=0))


def _park_martin(p: FloatArray, c: FloatArray) -> FloatArray:
    """X of A X = X B over all pose pairs (A = P_j^-1 P_i, B = C_j C_i^-1): rotation by aligning the rotation
    vectors (alpha = R_X beta, Park and Martin 1994, solved reflection-safe by SVD), translation by least squares
    on (R_A - I) t_X = R_X t_B - t_A."""
    alphas, betas, rows, rhs_parts = [], [], [], []
    pairs = list(itertools.combinations(range(len(p)), 2))
    for i, j in pairs:
        a = invert_pose(p[j]) @ p[i]
        b = c[j] @ invert_pose(c[i])
        alphas.append(rotation_to_rotvec(a[:3, :3]))
        betas.append(rotation_to_rotvec(b[:3, :3]))
    alpha, beta = np.asarray(alphas), np.asarray(betas)
    h = beta.T @ alpha  # sum beta alpha^T
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    rot = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    for i, j in pairs:
        a = invert_pose(p[j]) @ p[i]
        b = c[j] @ invert_pose(c[i])
        rows.append(a[:3, :3] - np.eye(3))
        rhs_parts.append(rot @ b[:3, 3] - a[:3, 3])
    t, *_ = np.linalg.lstsq(np.vstack(rows), np.concatenate(rhs_parts), rcond=None)
    return make_pose(rot, t)


def _linear_axzb(p: FloatArray, c: FloatArray) -> tuple[FloatArray, FloatArray]:
    """X and W of P_i X C_i = W at once: the rotations from the null vector of the stacked linear system
    R_Pi R_X - R_W R_Ci^T = 0 (column-major vec: (I kron R_Pi) vec R_X - (R_Ci kron I) vec R_W = 0), each
    projected onto SO(3); then the translations by least squares on R_Pi t_X - t_W = R_W t(C_i^-1) - t_Pi."""
    eye = np.eye(3)
    blocks = [np.hstack([np.kron(eye, m[:3, :3]), -np.kron(ci[:3, :3], eye)]) for m, ci in zip(p, c, strict=True)]
    _, _, vt = np.linalg.svd(np.vstack(blocks))
    v = vt[-1]
    rx = v[:9].reshape(3, 3, order="F")
    rw = v[9:].reshape(3, 3, order="F")
    if np.linalg.det(rx) < 0:
        rx, rw = -rx, -rw
    rx, rw = _nearest_rotation(rx), _nearest_rotation(rw)
    rows, rhs = [], []
    for m, ci in zip(p, c, strict=True):
        ci_inv = invert_pose(ci)
        rows.append(np.hstack([m[:3, :3], -eye]))
        rhs.append(rw @ ci_inv[:3, 3] - m[:3, 3])
    sol, *_ = np.linalg.lstsq(np.vstack(rows), np.concatenate(rhs), rcond=None)
    return make_pose(rx, sol[:3]), make_pose(rw, sol[3:])


# -------------------------------------------------------------------------------------------------
# verification
# -------------------------------------------------------------------------------------------------
def predict_corners(result: HandEyeResult, camera: Camera, base_from_flange: ArrayLike) -> FloatArray:
    """(K, 2) pixels where the calibration puts the board corners at the flange pose `base_from_flange`
    ((6,) UR pose vector or (4, 4))."""
    flange = check_flange_poses(np.asarray(base_from_flange, dtype=np.float64)[None])[0]
    p = flange if result.mode == EYE_IN_HAND else invert_pose(flange)
    cfb = invert_pose(result.camera_pose) @ invert_pose(p) @ result.board_pose
    pts = transform_points(cfb, board_points(result.board, result.square_m))
    if np.any(pts[:, 2] <= 0):
        raise CalibrationError("at this flange pose the calibration puts the board behind the camera")
    return camera.project(pts)


def verify_image(result: HandEyeResult, camera: Camera, image: ArrayLike, base_from_flange: ArrayLike) -> ImageCheck:
    """Detect the board in a verification image taken at a new flange pose and compare its corners with the
    calibration's prediction (pixels)."""
    opts = HandEyeOptions(board=result.board, square_m=result.square_m)
    corners = find_checkerboard(image, opts.board, opts.subpix_window)
    corners = _canonical_order(_gray(image), corners, opts.board, opts.square_m)
    res = np.linalg.norm(predict_corners(result, camera, base_from_flange) - corners, axis=1)
    return ImageCheck(res, float(np.sqrt(np.mean(res**2))), float(res.max()))


def board_corners_in_base(result: HandEyeResult, camera_from_board: ArrayLike | None = None) -> FloatArray:
    """(K, 3) board corners in the robot base frame, metres.

    Eye-in-hand: the board where it lay during calibration (`camera_from_board` is ignored). Eye-to-hand: the
    board taken off the flange and laid in the cell, seen by the fixed camera as `camera_from_board` (required)."""
    obj = board_points(result.board, result.square_m)
    if result.mode == EYE_IN_HAND:
        return transform_points(result.board_pose, obj)
    if camera_from_board is None:
        raise InputError(
            "eye-to-hand touch check: lay the board in the cell, take an image with the fixed camera and pass its "
            "board pose (camera_from_board / --touch-image)"
        )
    return transform_points(result.camera_pose @ np.asarray(camera_from_board, dtype=np.float64), obj)


def touch_check(
    result: HandEyeResult,
    touched_base_m: ArrayLike,
    corner: int | None = None,
    camera_from_board: ArrayLike | None = None,
) -> TouchCheck:
    """Distance (mm) between a board corner touched with the TCP (its position in the base frame, metres, as
    getActualTCPPose reports with the pointer's TCP) and the corner the calibration predicts.

    corner: index in `board_points` order; None: the corner nearest the touched point. See
    `board_corners_in_base` for `camera_from_board`."""
    touched = as_float_array(touched_base_m, "touched point", (3,))
    if float(np.linalg.norm(touched)) > MAX_FLANGE_DISTANCE_M:
        raise InputError(
            f"touched point {touched.tolist()} is {np.linalg.norm(touched):.4g} m from the base: looks like "
            "millimetres; give metres"
        )
    corners = board_corners_in_base(result, camera_from_board)
    if corner is None:
        k = int(np.argmin(np.linalg.norm(corners - touched, axis=1)))
    else:
        if not 0 <= int(corner) < len(corners):
            raise InputError(f"corner must be in 0..{len(corners) - 1}, got {corner}")
        k = int(corner)
    dist = float(np.linalg.norm(corners[k] - touched) * 1000.0)
    return TouchCheck(k, corners[k], touched, dist)
