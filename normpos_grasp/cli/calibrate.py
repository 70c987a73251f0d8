"""`normpos-grasp calibrate intrinsics|extrinsics|check`: camera calibration and the static-reference drift check.

calibrate intrinsics IMAGES... --board 9x6 --square 0.025 --out camera.json
calibrate extrinsics --camera camera.json --points points.csv --out camera.json [--image calib.png] [--floor-z Z]
calibrate check --camera camera.json --reference camera.reference.json --image now.png

Every input is read and checked before anything is written; a refused input leaves no output file.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from normpos_grasp.cli.calibrate_hand_eye import add_hand_eye_parser
from normpos_grasp.errors import InputError


def _bounded(lo: float, hi: float, what: str, lo_open: bool = True) -> Callable[[str], float]:
    """argparse type: a finite float in (lo, hi] (or [lo, hi] when not `lo_open`)."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number ({what}), got {text!r}") from None
        low_ok = value > lo if lo_open else value >= lo
        if not (math.isfinite(value) and low_ok and value <= hi):
            bracket = "(" if lo_open else "["
            raise argparse.ArgumentTypeError(f"expected {what} in {bracket}{lo:g}, {hi:g}], got {text!r}")
        return value

    return parse


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "calibrate",
        help="calibrate a camera (intrinsics from checkerboards, extrinsics from control points) or check drift",
        description="Camera calibration: Zhang's method for intrinsics, EPnP + refinement for extrinsics.",
    )
    sub = p.add_subparsers(dest="calibrate_command", metavar="STEP", required=True)

    pi = sub.add_parser("intrinsics", help="K and distortion from checkerboard images")
    pi.add_argument("images", nargs="+", type=Path, help="checkerboard images (8-bit)")
    pi.add_argument("--board", default="9x6", help="inner corners COLSxROWS (default 9x6)")
    pi.add_argument(
        "--square", type=_bounded(0.0, 1.0, "metres"), default=0.025, help="square edge in metres (default 0.025)"
    )
    pi.add_argument("--distortion", type=int, choices=(0, 4, 5), default=5, help="distortion terms (default 5)")
    pi.add_argument(
        "--depth-scale",
        type=_bounded(0.0, 1.0, "metres per raw depth unit"),
        default=0.001,
        help="metres per raw depth unit (default 0.001)",
    )
    pi.add_argument("--out", type=Path, required=True, help="camera JSON to write")
    pi.set_defaults(handler=run)

    pe = sub.add_parser("extrinsics", help="world_from_camera from >= 4 surveyed control points")
    pe.add_argument("--camera", type=Path, required=True, help="camera JSON with intrinsics")
    pe.add_argument("--points", type=Path, required=True, help="CSV with columns name,x,y,z,u,v (metres, pixels)")
    pe.add_argument("--out", type=Path, required=True, help="camera JSON to write (may equal --camera)")
    pe.add_argument("--image", type=Path, default=None, help="calibration image: also save a static reference")
    pe.add_argument("--reference", type=Path, default=None, help="static reference JSON (default OUT.reference.json)")
    pe.add_argument(
        "--max-rms",
        type=_bounded(0.0, 50.0, "pixels"),
        default=2.0,
        help="reject solutions above this reprojection RMS in px (default 2)",
    )
    pe.add_argument(
        "--floor-z",
        type=_bounded(-20.0, 20.0, "metres", lo_open=False),
        default=None,
        help="world height of the floor (z up, m): a solved camera below it is refused "
        "(default: the lowest control point)",
    )
    pe.set_defaults(handler=run)

    pc = sub.add_parser("check", help="static-reference check: has the camera moved since calibration?")
    pc.add_argument("--camera", type=Path, required=True, help="calibrated camera JSON")
    pc.add_argument("--reference", type=Path, required=True, help="static reference JSON from `extrinsics --image`")
    pc.add_argument("--image", type=Path, default=None, help="current image (reference points found by matching)")
    pc.add_argument("--observed", type=Path, default=None, help="CSV name,u,v of the points as seen now")
    pc.add_argument(
        "--max-mm", type=_bounded(0.0, 1000.0, "mm"), default=2.0, help="tolerated camera move, mm (default 2)"
    )
    pc.add_argument(
        "--max-deg",
        type=_bounded(0.0, 90.0, "degrees"),
        default=0.1,
        help="tolerated camera rotation, degrees (default 0.1)",
    )
    pc.set_defaults(handler=run)

    add_hand_eye_parser(sub)  # calibrate hand-eye: normpos_grasp/cli/calibrate_hand_eye.py


def run(args: argparse.Namespace) -> int:
    step = args.calibrate_command
    if step == "intrinsics":
        return _intrinsics(args)
    if step == "extrinsics":
        return _extrinsics(args)
    return _check(args)


def _read_image(path: Path) -> np.ndarray:
    import cv2

    if not path.is_file():
        raise InputError(f"cannot read image {path}: no such file")
    try:
        img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    except cv2.error as exc:
        raise InputError(f"cannot decode image {path}: {' '.join(str(exc).split())}") from exc
    if img is None:
        raise InputError(f"cannot decode image {path} (not an image OpenCV reads)")
    return np.ascontiguousarray(img[:, :, ::-1])


def _check_out(path: Path) -> None:
    """Refuse an output path that cannot be written, before any work is done."""
    if path.is_dir():
        raise InputError(f"--out {path} is a folder; give a file name such as {path / 'camera.json'}")
    if not path.parent.is_dir():
        raise InputError(f"the folder of {path} does not exist; create it first")


def _write(save: Callable[[Path], None], path: Path) -> None:
    try:
        save(path)
    except OSError as exc:
        raise InputError(f"cannot write {path}: {exc.strerror or exc}") from exc


def _intrinsics(args: argparse.Namespace) -> int:
    from normpos_grasp.camera.calibration import IntrinsicsOptions, calibrate_intrinsics

    try:
        cols, rows = (int(x) for x in args.board.lower().split("x"))
    except ValueError as exc:
        raise InputError(f"--board must look like 9x6 (inner corners), got {args.board!r}") from exc
    opts = IntrinsicsOptions(board=(cols, rows), square_m=args.square, n_distortion=args.distortion)
    _check_out(args.out)
    images = [_read_image(p) for p in args.images]
    result = calibrate_intrinsics(images, opts)
    cam = result.camera
    from normpos_grasp.camera.model import Camera

    cam = Camera(cam.K, cam.width, cam.height, cam.distortion, args.depth_scale)
    _write(cam.save_json, args.out)
    print(f"fx {cam.fx:.3f}  fy {cam.fy:.3f}  cx {cam.cx:.3f}  cy {cam.cy:.3f}  distortion {cam.distortion.round(5)}")
    print(f"RMS reprojection error {result.rms_px:.4f} px over {len(result.used)} images")
    for i, err in zip(result.used, result.per_image_rms_px, strict=True):
        print(f"  {args.images[i]}: {err:.4f} px")
    for i in result.rejected:
        print(f"  {args.images[i]}: no board found, skipped")
    print(f"wrote {args.out}")
    return 0


def _extrinsics(args: argparse.Namespace) -> int:
    from normpos_grasp.camera.calibration import ExtrinsicsOptions, calibrate_extrinsics, read_control_points
    from normpos_grasp.camera.model import Camera
    from normpos_grasp.camera.static_reference import StaticReference

    _check_out(args.out)
    ref_path = None
    if args.image is not None:
        ref_path = args.reference or args.out.with_suffix(".reference.json")
        _check_out(ref_path)
    cam = Camera.load_json(args.camera)
    points = read_control_points(args.points)
    image = None if args.image is None else _read_image(args.image)
    opts = ExtrinsicsOptions(max_rms_px=args.max_rms, floor_z_m=args.floor_z)
    result = calibrate_extrinsics(cam, points.world, points.pixels, opts)
    ref = None if image is None else StaticReference.from_calibration(result.camera, points, image)
    _write(result.camera.save_json, args.out)
    pos = result.world_from_camera[:3, 3]
    print(f"camera position in the world {pos.round(4).tolist()} m ({result.method}), RMS {result.rms_px:.3f} px")
    for name, rp, rm in zip(points.names, result.residuals_px, result.residuals_m, strict=True):
        print(f"  {name}: {rp:.3f} px, {rm * 1000:.2f} mm from its ray")
    print(f"wrote {args.out}")
    if ref is not None and ref_path is not None:
        _write(ref.save_json, ref_path)
        print(f"wrote static reference {ref_path}")
    return 0


def _check(args: argparse.Namespace) -> int:
    import csv

    from normpos_grasp.camera.model import Camera
    from normpos_grasp.camera.static_reference import (
        DriftOptions,
        StaticReference,
        check_drift,
        locate_reference_points,
    )

    cam = Camera.load_json(args.camera)
    ref = StaticReference.load_json(args.reference)
    opts = DriftOptions(max_translation_mm=args.max_mm, max_rotation_deg=args.max_deg, raise_on_drift=False)
    if args.observed is not None:
        try:
            with args.observed.open(newline="", encoding="utf-8") as fh:
                seen = {r["name"]: (float(r["u"]), float(r["v"])) for r in csv.DictReader(fh)}
        except (OSError, UnicodeDecodeError) as exc:
            raise InputError(f"cannot read {args.observed}: {exc}") from exc
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(f"{args.observed}: expected a CSV with columns name,u,v (pixels): {exc}") from exc
        pixels = np.array([seen.get(n, (np.nan, np.nan)) for n in ref.names], dtype=np.float64)
    elif args.image is not None:
        pixels = locate_reference_points(ref, _read_image(args.image), opts)
    else:
        raise InputError("give --image (points found by matching) or --observed (a CSV name,u,v)")
    report = check_drift(cam, ref, pixels, opts)
    print(report.summary())
    for name, px, mm in zip(ref.names, report.pixel_shift_px, report.world_error_mm, strict=True):
        print(f"  {name}: shift {px:.2f} px, {mm:.2f} mm at the point")
    if report.moved:
        print("CAMERA MOVED: re-calibrate the extrinsics before moving the robot")
        return 1
    print("camera within tolerance")
    return 0
