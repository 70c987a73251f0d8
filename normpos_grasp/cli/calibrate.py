"""`normpos-grasp calibrate intrinsics|extrinsics|check`: camera calibration and the static-reference drift check.

calibrate intrinsics IMAGES... --board 9x6 --square 0.025 --out camera.json
calibrate extrinsics --camera camera.json --points points.csv --out camera.json [--image calib.png]
calibrate check --camera camera.json --reference camera.reference.json --image now.png
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import numpy as np

from normpos_grasp.errors import InputError


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
    pi.add_argument("--square", type=float, default=0.025, help="square edge in metres (default 0.025)")
    pi.add_argument("--distortion", type=int, choices=(0, 4, 5), default=5, help="distortion terms (default 5)")
    pi.add_argument("--depth-scale", type=float, default=0.001, help="metres per raw depth unit (default 0.001)")
    pi.add_argument("--out", type=Path, required=True, help="camera JSON to write")
    pi.set_defaults(handler=run)

    pe = sub.add_parser("extrinsics", help="world_from_camera from >= 4 surveyed control points")
    pe.add_argument("--camera", type=Path, required=True, help="camera JSON with intrinsics")
    pe.add_argument("--points", type=Path, required=True, help="CSV with columns name,x,y,z,u,v (metres, pixels)")
    pe.add_argument("--out", type=Path, required=True, help="camera JSON to write (may equal --camera)")
    pe.add_argument("--image", type=Path, default=None, help="calibration image: also save a static reference")
    pe.add_argument("--reference", type=Path, default=None, help="static reference JSON (default OUT.reference.json)")
    pe.add_argument("--max-rms", type=float, default=10.0, help="reject solutions above this RMS in px (default 10)")
    pe.set_defaults(handler=run)

    pc = sub.add_parser("check", help="static-reference check: has the camera moved since calibration?")
    pc.add_argument("--camera", type=Path, required=True, help="calibrated camera JSON")
    pc.add_argument("--reference", type=Path, required=True, help="static reference JSON from `extrinsics --image`")
    pc.add_argument("--image", type=Path, default=None, help="current image (reference points found by matching)")
    pc.add_argument("--observed", type=Path, default=None, help="CSV name,u,v of the points as seen now")
    pc.add_argument("--max-mm", type=float, default=2.0, help="tolerated camera move, mm (default 2)")
    pc.add_argument("--max-deg", type=float, default=0.1, help="tolerated camera rotation, degrees (default 0.1)")
    pc.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    step = args.calibrate_command
    if step == "intrinsics":
        return _intrinsics(args)
    if step == "extrinsics":
        return _extrinsics(args)
    return _check(args)


def _read_image(path: Path) -> np.ndarray:
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise InputError(f"cannot read image {path}")
    return np.ascontiguousarray(img[:, :, ::-1])


def _intrinsics(args: argparse.Namespace) -> int:
    from normpos_grasp.camera.calibration import IntrinsicsOptions, calibrate_intrinsics

    try:
        cols, rows = (int(x) for x in args.board.lower().split("x"))
    except ValueError as exc:
        raise InputError(f"--board must look like 9x6 (inner corners), got {args.board!r}") from exc
    opts = IntrinsicsOptions(board=(cols, rows), square_m=args.square, n_distortion=args.distortion)
    images = [_read_image(p) for p in args.images]
    result = calibrate_intrinsics(images, opts)
    cam = result.camera
    from normpos_grasp.camera.model import Camera

    cam = Camera(cam.K, cam.width, cam.height, cam.distortion, args.depth_scale)
    cam.save_json(args.out)
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

    cam = Camera.load_json(args.camera)
    points = read_control_points(args.points)
    result = calibrate_extrinsics(cam, points.world, points.pixels, ExtrinsicsOptions(max_rms_px=args.max_rms))
    result.camera.save_json(args.out)
    pos = result.world_from_camera[:3, 3]
    print(f"camera position in the world {pos.round(4).tolist()} m ({result.method}), RMS {result.rms_px:.3f} px")
    for name, rp, rm in zip(points.names, result.residuals_px, result.residuals_m, strict=True):
        print(f"  {name}: {rp:.3f} px, {rm * 1000:.2f} mm from its ray")
    print(f"wrote {args.out}")
    if args.image is not None:
        ref_path = args.reference or args.out.with_suffix(".reference.json")
        ref = StaticReference.from_calibration(result.camera, points, _read_image(args.image))
        ref.save_json(ref_path)
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
        with args.observed.open(newline="") as fh:
            seen = {r["name"]: (float(r["u"]), float(r["v"])) for r in csv.DictReader(fh)}
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
