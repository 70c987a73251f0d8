"""Hand-eye benchmark: rendered checkerboards with known truth, both modes, several seeds.

Set-ups (normpos_grasp.camera.hand_eye_synthetic): eye-to-hand, a 640x480 camera (f = 615 px) 1 m above the
table looking down at the work area and a 9x6 board (25 mm squares) 2 cm out from the flange; eye-in-hand, the
same camera 7 cm off the flange axis and the board on the table. Per seed, `--poses` views: the camera 0.5-0.9 m
(eye-in-hand 0.4-0.65 m) from the board, tilted up to ~35 degrees and rolled up to 30 degrees about its optical
axis. Each view is rendered (camera.checkerboard.render_checkerboard, 3x supersampled), its corners detected
(OpenCV, sub-pixel), then Gaussian noise of `--noise` px is added to every corner coordinate. The flange poses
go in as UR pose vectors, optionally with noise (`--robot-noise-mm`, `--robot-noise-deg`).

Errors: distance between the true and calibrated camera positions (mm; base_from_camera for eye-to-hand,
flange_from_camera for eye-in-hand) and the angle between their orientations (deg). Touch: the calibrated
position of a board corner in the base frame (eye-in-hand: the board as it lay; eye-to-hand: the board laid on the
table and photographed by the fixed camera) against the truth, the error a perfect touch would report.

    .venv/bin/python benchmarks/bench_hand_eye.py [--seeds 10] [--poses 15] [--noise 0.3]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from normpos_grasp.camera import Camera
from normpos_grasp.camera.calibration import board_points, find_checkerboard
from normpos_grasp.camera.checkerboard import random_board_pose, render_checkerboard
from normpos_grasp.camera.hand_eye import (
    EYE_IN_HAND,
    EYE_TO_HAND,
    HandEyeOptions,
    HandEyeResult,
    board_view,
    calibrate_hand_eye_from_corners,
    touch_check,
)
from normpos_grasp.camera.hand_eye_synthetic import HandEyeScene, hand_eye_scene
from normpos_grasp.errors import CalibrationError
from normpos_grasp.geometry import invert_pose, make_pose, pose_to_ur, rotation_from_rotvec, transform_points
from normpos_grasp.geometry.transforms import rotation_angle

K = np.array([[615.0, 0, 320.5], [0, 612.0, 238.7], [0, 0, 1]])
CAMERA = Camera(K, 640, 480)
BOARD = (9, 6)
SQUARE = 0.025


def detected_corners(camera_from_board: np.ndarray, rng: np.random.Generator, noise_px: float) -> np.ndarray | None:
    """Corners found in the rendered view plus Gaussian noise; None where the board is not found."""
    image = render_checkerboard(CAMERA, camera_from_board, BOARD, SQUARE)
    try:
        corners = find_checkerboard(image, BOARD)
    except CalibrationError:
        return None
    return corners + rng.normal(0.0, noise_px, corners.shape)


def flange_vectors(scene: HandEyeScene, rng: np.random.Generator, noise_mm: float, noise_deg: float) -> np.ndarray:
    out = []
    for pose in scene.base_from_flange:
        if noise_mm > 0 or noise_deg > 0:
            rot = rotation_from_rotvec(rng.normal(0.0, np.radians(noise_deg), 3))
            pose = pose @ make_pose(rot, rng.normal(0.0, noise_mm / 1000.0, 3))
        out.append(pose_to_ur(pose))
    return np.array(out)


def touch_error_mm(result: HandEyeResult, scene: HandEyeScene, rng: np.random.Generator, noise_px: float) -> float:
    """Calibrated minus true base position of the board corner farthest from corner 0 (a perfect touch), mm."""
    obj = board_points(BOARD, SQUARE)
    corner = len(obj) - 1
    if scene.mode == EYE_IN_HAND:
        truth = transform_points(scene.board_pose, obj[corner : corner + 1])[0]
        return touch_check(result, truth, corner).distance_mm
    # eye-to-hand: the board taken off the flange and laid where the camera sees it
    base_from_camera = scene.camera_pose
    while True:
        cfb = random_board_pose(rng, BOARD, SQUARE, (0.7, 0.8))
        corners = detected_corners(cfb, rng, noise_px)
        if corners is not None:
            break
    truth = transform_points(base_from_camera @ cfb, obj[corner : corner + 1])[0]
    seen = board_view(CAMERA, corners, HandEyeOptions(board=BOARD, square_m=SQUARE)).camera_from_board
    return touch_check(result, truth, corner, seen).distance_mm


def run_mode(mode: str, args: argparse.Namespace) -> None:
    pos_mm, rot_deg, touch_mm, std_mm, rms_px, times = [], [], [], [], [], []
    start_mm, start_deg = [], []
    example: HandEyeResult | None = None
    for seed in range(args.seeds):
        rng = np.random.default_rng(1000 * seed + (0 if mode == EYE_TO_HAND else 1))
        scene = hand_eye_scene(rng, mode, args.poses, BOARD, SQUARE)
        corners = [detected_corners(c, rng, args.noise) for c in scene.camera_from_board]
        flange = flange_vectors(scene, rng, args.robot_noise_mm, args.robot_noise_deg)
        t = time.perf_counter()
        result = calibrate_hand_eye_from_corners(
            CAMERA, corners, flange, mode, HandEyeOptions(board=BOARD, square_m=SQUARE)
        )
        times.append(time.perf_counter() - t)
        err = invert_pose(scene.camera_pose) @ result.camera_pose
        pos_mm.append(float(np.linalg.norm(result.camera_pose[:3, 3] - scene.camera_pose[:3, 3]) * 1000.0))
        rot_deg.append(float(np.degrees(rotation_angle(err[:3, :3]))))
        start = invert_pose(scene.camera_pose) @ result.start_camera_pose
        start_mm.append(float(np.linalg.norm(result.start_camera_pose[:3, 3] - scene.camera_pose[:3, 3]) * 1000.0))
        start_deg.append(float(np.degrees(rotation_angle(start[:3, :3]))))
        touch_mm.append(touch_error_mm(result, scene, rng, args.noise))
        std_mm.append(float(np.linalg.norm(result.std_position_mm)))
        rms_px.append(result.rms_px)
        print(
            f"  seed {seed}: {pos_mm[-1]:.3f} mm, {rot_deg[-1]:.4f} deg (1-sigma {std_mm[-1]:.3f} mm), touch "
            f"{touch_mm[-1]:.3f} mm, RMS {rms_px[-1]:.3f} px, {len(result.used)}/{args.poses} boards, start "
            f"{result.method} ({start_mm[-1]:.3f} mm, {start_deg[-1]:.4f} deg), {times[-1] * 1000:.0f} ms"
        )
        if example is None:
            example = result
    ok = max(pos_mm) <= 1.0 and max(rot_deg) <= 0.1
    print(
        f"  {mode}: camera pose error median {np.median(pos_mm):.3f} mm / {np.median(rot_deg):.4f} deg, "
        f"max {max(pos_mm):.3f} mm / {max(rot_deg):.4f} deg over {args.seeds} seeds "
        f"(target 1 mm / 0.1 deg: {'met' if ok else 'NOT met'}); touch-point error median {np.median(touch_mm):.3f} "
        f"mm, max {max(touch_mm):.3f} mm; median calibration time {np.median(times) * 1000:.0f} ms"
    )
    print(
        f"  {mode}: the best closed-form start alone: median {np.median(start_mm):.3f} mm / "
        f"{np.median(start_deg):.4f} deg, max {max(start_mm):.3f} mm / {max(start_deg):.4f} deg"
    )
    if example is not None and args.report:
        print(f"  per-pose residual report, {mode}, seed 0:")
        for line in example.report_lines():
            print("    " + line)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--poses", type=int, default=15)
    parser.add_argument("--noise", type=float, default=0.3, help="corner noise, px (Gaussian sigma per coordinate)")
    parser.add_argument("--robot-noise-mm", type=float, default=0.0, help="flange position noise, mm (sigma per axis)")
    parser.add_argument(
        "--robot-noise-deg", type=float, default=0.0, help="flange rotation noise, deg (sigma per axis)"
    )
    parser.add_argument("--no-report", dest="report", action="store_false", help="skip the per-pose residual report")
    parser.add_argument("--mode", choices=(EYE_TO_HAND, EYE_IN_HAND, "both"), default="both")
    args = parser.parse_args()
    print(
        f"hand-eye on rendered 9x6 boards: {args.poses} poses, {args.noise} px corner noise, robot noise "
        f"{args.robot_noise_mm} mm / {args.robot_noise_deg} deg, {args.seeds} seeds"
    )
    for mode in (EYE_TO_HAND, EYE_IN_HAND) if args.mode == "both" else (args.mode,):
        print(f"{mode}:")
        run_mode(mode, args)


if __name__ == "__main__":
    main()
