"""`normpos-grasp calibrate hand-eye`: camera pose from checkerboard images and the robot's flange poses.

calibrate hand-eye --mode eye-to-hand|eye-in-hand --images IMG... --poses POSES.csv --board 9x6 --square 0.025
    --camera camera.json --out camera.json [--cell CELL.yaml] [--touch X Y Z [--touch-image IMG]]
    [--verify-images IMG... --verify-poses VERIFY.csv]
calibrate hand-eye --mode MODE --record HOST --poses POSES.csv     (record the flange poses over RTDE)

Eye-to-hand writes the camera's `world_from_camera` (world = the robot base, or the cell's world through its
`robot.world_from_base` with --cell); eye-in-hand writes `flange_from_camera` into the camera JSON (and drops a
fixed `world_from_camera`, which a wrist camera does not have). Both write the residual report next to --out
(OUT.hand_eye.json). Every input is read and checked before anything is written; a failed verification (touch
point or verification images beyond tolerance) writes nothing and exits 1.
"""

from __future__ import annotations

import argparse
import json
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from normpos_grasp.errors import InputError


def _positive(hi: float, what: str) -> Callable[[str], float]:
    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number ({what}), got {text!r}") from None
        if not (math.isfinite(value) and 0 < value <= hi):
            raise argparse.ArgumentTypeError(f"expected {what} in (0, {hi:g}], got {text!r}")
        return value

    return parse


def _metres(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a coordinate in metres, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite coordinate in metres, got {text!r}")
    return value


def add_hand_eye_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Add `hand-eye` to the `calibrate` step parsers; returns the new parser."""
    from normpos_grasp.camera.hand_eye import MODES

    p = subparsers.add_parser(
        "hand-eye",
        help="camera pose from checkerboard images and flange poses (eye-to-hand or eye-in-hand)",
        description="Hand-eye calibration: OpenCV's hand-eye solvers (where exposed) and two closed-form solvers "
        "start a joint refinement of the corner reprojection error over all images.",
    )
    p.add_argument(
        "--mode",
        choices=MODES,
        required=True,
        help="eye-to-hand: fixed camera, board on the flange; "
        "eye-in-hand: camera on the wrist, board fixed in the cell",
    )
    p.add_argument(
        "--images", nargs="+", type=Path, default=None, metavar="IMG", help="checkerboard images, one per pose"
    )
    p.add_argument(
        "--poses",
        type=Path,
        required=True,
        metavar="POSES.csv",
        help="CSV x,y,z,rx,ry,rz: base_from_flange per image (m, UR rotation vector), zero TCP; written by --record",
    )
    p.add_argument("--board", default="9x6", help="inner corners COLSxROWS (default 9x6)")
    p.add_argument("--square", type=_positive(1.0, "metres"), default=0.025, help="square edge, m (default 0.025)")
    p.add_argument("--camera", type=Path, default=None, metavar="JSON", help="camera JSON with the intrinsics")
    p.add_argument("--out", type=Path, default=None, metavar="JSON", help="camera JSON to write (may equal --camera)")
    p.add_argument(
        "--record",
        metavar="HOST",
        default=None,
        help="record POSES.csv over RTDE instead: the flange pose of the controller at HOST each time Enter is "
        "pressed (TCP set to zero); nothing is calibrated",
    )
    p.add_argument("--report", type=Path, default=None, help="residual report JSON (default OUT.hand_eye.json)")
    p.add_argument(
        "--cell",
        type=Path,
        default=None,
        help="cell YAML: eye-to-hand extrinsics in its world (robot.world_from_base) and checked against it",
    )
    p.add_argument(
        "--max-rms",
        type=_positive(50.0, "pixels"),
        default=2.0,
        help="refuse a calibration above this reprojection RMS, px (default 2)",
    )
    p.add_argument(
        "--touch",
        nargs=3,
        type=_metres,
        metavar=("X", "Y", "Z"),
        default=None,
        help="TCP position touching a board corner, base frame, m (the pointer's TCP set)",
    )
    p.add_argument(
        "--touch-corner",
        type=int,
        default=None,
        help="index of the touched corner (row * cols + col; default: the nearest corner)",
    )
    p.add_argument(
        "--touch-image",
        type=Path,
        default=None,
        help="eye-to-hand: image of the board laid in the cell, taken for the touch check",
    )
    p.add_argument(
        "--max-touch-mm",
        type=_positive(1000.0, "mm"),
        default=3.0,
        help="tolerated touch-point distance, mm (default 3: the calibration, one image's board pose and the touch)",
    )
    p.add_argument(
        "--verify-images",
        nargs="+",
        type=Path,
        default=None,
        metavar="IMG",
        help="images at poses not used to calibrate",
    )
    p.add_argument("--verify-poses", type=Path, default=None, help="CSV x,y,z,rx,ry,rz of the verification images")
    p.add_argument(
        "--max-verify-px",
        type=_positive(100.0, "pixels"),
        default=2.0,
        help="tolerated corner reprojection RMS of a verification image, px (default 2)",
    )
    p.set_defaults(handler=run_hand_eye)
    return p


def _read_gray(path: Path) -> np.ndarray:
    import cv2

    if not path.is_file():
        raise InputError(f"cannot read image {path}: no such file")
    try:
        img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    except cv2.error as exc:
        raise InputError(f"cannot decode image {path}: {' '.join(str(exc).split())}") from exc
    if img is None:
        raise InputError(f"cannot decode image {path} (not an image OpenCV reads)")
    return np.asarray(img)


def _check_out(path: Path, flag: str) -> None:
    if path.is_dir():
        raise InputError(f"{flag} {path} is a folder; give a file name")
    if not path.parent.is_dir():
        raise InputError(f"the folder of {flag} {path} does not exist; create it first")


def _board(text: str) -> tuple[int, int]:
    try:
        cols, rows = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise InputError(f"--board must look like 9x6 (inner corners), got {text!r}") from None
    return cols, rows


def run_hand_eye(args: argparse.Namespace) -> int:
    """Handler of `calibrate hand-eye`; returns the exit code (0 written, 1 verification failed)."""
    from normpos_grasp.atomic import atomic_write_text
    from normpos_grasp.camera.hand_eye import (
        EYE_TO_HAND,
        HandEyeOptions,
        calibrate_hand_eye,
        check_excitation,
        detect_board,
        touch_check,
        verify_image,
    )
    from normpos_grasp.camera.hand_eye_io import read_poses_csv
    from normpos_grasp.camera.model import Camera

    opts = HandEyeOptions(board=_board(args.board), square_m=args.square, max_rms_px=args.max_rms)
    if args.record is not None:
        record_poses(args.record, args.poses, args.mode, opts)
        return 0
    missing = [
        flag
        for flag, value in (("--images", args.images), ("--camera", args.camera), ("--out", args.out))
        if value is None
    ]
    if missing:
        raise InputError(f"calibrate hand-eye needs {', '.join(missing)} (or --record HOST to record the poses)")
    report_path = args.report or args.out.with_name(args.out.stem + ".hand_eye.json")
    _check_out(args.out, "--out")
    _check_out(report_path, "--report")
    if (args.verify_images is None) != (args.verify_poses is None):
        raise InputError("give --verify-images and --verify-poses together")
    if args.touch_image is not None and args.touch is None:
        raise InputError("--touch-image needs --touch X Y Z (the TCP position on the corner)")
    if args.touch is not None and args.mode == EYE_TO_HAND and args.touch_image is None:
        raise InputError("eye-to-hand --touch needs --touch-image: lay the board in the cell and photograph it")
    camera = Camera.load_json(args.camera)
    world_from_base = np.eye(4)
    cell = None
    if args.cell is not None:
        from normpos_grasp.cell.config import resolve_cell

        cell = resolve_cell(args.cell)
        world_from_base = cell.world_from_base
    poses = read_poses_csv(args.poses)
    if len(poses) != len(args.images):
        raise InputError(
            f"{args.poses} holds {len(poses)} poses but {len(args.images)} images were given; one row per "
            "image, in the same order"
        )
    excitation = check_excitation(poses, args.mode, opts)
    if excitation.degenerate:
        raise InputError(f"{args.poses}: the pose set cannot determine a hand-eye calibration: {excitation.message}")
    verify_poses = None
    if args.verify_poses is not None:
        verify_poses = read_poses_csv(args.verify_poses)
        if len(verify_poses) != len(args.verify_images):
            raise InputError(
                f"{args.verify_poses} holds {len(verify_poses)} poses but {len(args.verify_images)} "
                "verification images were given"
            )
    images = [_read_gray(p) for p in args.images]
    verify_imgs = [_read_gray(p) for p in args.verify_images] if args.verify_images else []
    touch_img = None if args.touch_image is None else _read_gray(args.touch_image)

    result = calibrate_hand_eye(camera, images, poses, args.mode, opts)
    for line in result.report_lines():
        print(line)
    for i in result.rejected:
        print(f"  (pose {i} is {args.images[i]})")

    failed = []
    checks: dict[str, Any] = {}
    if args.touch is not None:
        cfb = None if touch_img is None else detect_board(touch_img, camera, opts).camera_from_board
        touch = touch_check(result, args.touch, args.touch_corner, cfb)
        print(
            f"touch check: corner {touch.corner} predicted at {np.round(touch.predicted_base_m, 5).tolist()} m, "
            f"touched {np.round(touch.touched_base_m, 5).tolist()} m: {touch.distance_mm:.2f} mm apart"
        )
        checks["touch"] = {
            "corner": touch.corner,
            "predicted_base_m": touch.predicted_base_m.tolist(),
            "touched_base_m": touch.touched_base_m.tolist(),
            "distance_mm": touch.distance_mm,
        }
        if touch.distance_mm > args.max_touch_mm:
            failed.append(
                f"the touched corner is {touch.distance_mm:.2f} mm from the prediction (tolerance "
                f"{args.max_touch_mm:g} mm)"
            )
    if verify_poses is not None:
        checks["verify"] = []
        for path, img, pose in zip(args.verify_images, verify_imgs, verify_poses, strict=True):
            check = verify_image(result, camera, img, pose)
            print(f"verification {path}: corners reprojected RMS {check.rms_px:.3f} px, max {check.max_px:.3f} px")
            checks["verify"].append({"image": str(path), "rms_px": check.rms_px, "max_px": check.max_px})
            if check.rms_px > args.max_verify_px:
                failed.append(
                    f"verification image {path} reprojects at {check.rms_px:.2f} px RMS (tolerance "
                    f"{args.max_verify_px:g} px)"
                )
    if failed:
        print("VERIFICATION FAILED, nothing written: " + "; ".join(failed))
        print("re-check the TCP of the touch, the pose order in the CSV and that the board did not move")
        return 1

    if args.mode == EYE_TO_HAND:
        wfc = world_from_base @ result.camera_pose
        if cell is not None:
            wfc = cell.check_camera(wfc, "hand-eye world_from_camera")
        data = camera.with_extrinsics(wfc).to_dict()
        frame = "the cell's world" if cell is not None else "the robot base frame (world = base)"
        print(f"camera position {np.round(wfc[:3, 3], 4).tolist()} m in {frame}")
    else:
        data = camera.with_extrinsics(None).to_dict()
        if camera.world_from_camera is not None:
            print("note: the fixed world_from_camera of the input camera was dropped (a wrist camera moves)")
        data["flange_from_camera"] = result.camera_pose.tolist()
    record = result.to_dict()
    record["camera"] = str(args.out)
    record["images"] = [str(p) for p in args.images]
    record["checks"] = checks
    try:
        atomic_write_text(args.out, json.dumps(data, indent=2) + "\n")
        atomic_write_text(report_path, json.dumps(record, indent=2) + "\n")
    except OSError as exc:
        raise InputError(f"cannot write {args.out}: {exc.strerror or exc}") from exc
    print(f"wrote {args.out} and {report_path}")
    return 0


def record_poses(
    host: str,
    path: Path,
    mode: str,
    options: Any = None,
    prompt: Callable[[str], str] = input,
    max_poses: int = 100,
) -> np.ndarray:
    """Record POSES.csv interactively: each Enter reads `getActualTCPPose` of the controller at `host` over RTDE
    (ur_rtde's RTDEReceiveInterface) while the arm stands still; 'q' or end of input finishes. The file is
    rewritten (atomically) after every pose, so an interruption keeps what was recorded; an existing file is
    refused. Prints the rotation spread once 3 poses are in. Returns the (N, 6) poses."""
    from normpos_grasp.camera.hand_eye import HandEyeOptions, check_excitation, check_flange_poses
    from normpos_grasp.camera.hand_eye_io import write_poses_csv
    from normpos_grasp.errors import ConnectionLost, MissingDependency

    opts = options if options is not None else HandEyeOptions()
    if path.exists():
        raise InputError(f"--poses {path} already exists; move it away or give a new name to record into")
    _check_out(path, "--poses")
    try:
        import rtde_receive
    except ImportError as exc:
        raise MissingDependency("ur-rtde==1.6.5", "core", "calibrate hand-eye --record") from exc
    try:
        receiver = rtde_receive.RTDEReceiveInterface(host)
    except RuntimeError as exc:
        raise ConnectionLost(f"cannot open RTDE on {host}: {' '.join(str(exc).split())}") from exc
    poses: list[list[float]] = []
    try:
        print(f"recording flange poses from {host} into {path} (TCP must be set to zero on the pendant)")
        while len(poses) < max_poses:
            try:
                answer = prompt(f"pose {len(poses)}: move the arm, take image {len(poses)}, press Enter (q: done) ")
            except EOFError:
                break
            if answer.strip().lower() in ("q", "quit", "done"):
                break
            speed = np.asarray(receiver.getActualTCPSpeed(), dtype=np.float64)
            qd = np.asarray(receiver.getActualQd(), dtype=np.float64)
            if np.linalg.norm(speed[:3]) > 1e-3 or np.linalg.norm(speed[3:]) > 1e-2 or np.abs(qd).max() > 2e-3:
                print("the arm is moving: wait until it stands still, then press Enter again")
                continue
            pose = np.asarray(receiver.getActualTCPPose(), dtype=np.float64)
            check_flange_poses(pose[None])
            poses.append(pose.tolist())
            write_poses_csv(path, np.array(poses))
            print(f"  pose {len(poses) - 1}: {np.round(pose, 5).tolist()}")
            if len(poses) >= 3:
                report = check_excitation(np.array(poses), mode, opts)
                spread = ", ".join(f"{v:.1f}" for v in report.spread_deg)
                print(f"  rotation spread {spread} deg" + (f": {report.message}" if report.degenerate else ""))
                for warning in report.warnings:
                    print(f"  {warning}")
    finally:
        receiver.disconnect()
    print(f"recorded {len(poses)} poses in {path}" if poses else "no pose recorded")
    return np.array(poses)
