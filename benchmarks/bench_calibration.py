"""Calibration benchmark: intrinsics from rendered checkerboards (known K) and extrinsics from noisy control points.

Intrinsics: boards (9x6 inner corners, 25 mm squares) rendered with cv2.warpPerspective at a known K
(normpos_grasp.camera.checkerboard, 3x supersampled), 0.5-0.9 m away, tilted up to ~35 degrees;
normpos_grasp.camera.calibration.calibrate_intrinsics with 5 distortion terms.

Extrinsics: a 640x480 camera (f = 615 px) 1.5 m from the world origin, looking at it from a random direction
above the table; N control points seen at pixels spread over the image (40 px margin, >= 20 px apart) at depths of
1.5 m +- spread (the spread says how far the points are from one plane); pixels get 0.5 px Gaussian noise;
calibrate_extrinsics (EPnP, SQPnP [, IPPE] candidates, Levenberg-Marquardt refinement, lowest RMS).
Errors: distance between true and estimated camera centres (mm), angle between orientations (degrees).

    .venv/bin/python benchmarks/bench_calibration.py [--trials 300] [--boards 12] [--seed 0]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from normpos_grasp.camera import Camera
from normpos_grasp.camera.calibration import (
    ExtrinsicsOptions,
    IntrinsicsOptions,
    calibrate_extrinsics,
    calibrate_intrinsics,
    check_control_points,
)
from normpos_grasp.camera.checkerboard import random_board_pose, render_checkerboard
from normpos_grasp.errors import CalibrationError
from normpos_grasp.geometry import invert_pose, transform_points
from normpos_grasp.geometry.transforms import look_at, rotation_angle


def intrinsics(boards: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    rows = []
    for trial in range(3):
        k = np.array([[rng.uniform(580, 650), 0, rng.uniform(300, 340)], [0, 0, rng.uniform(220, 260)], [0, 0, 1]])
        k[1, 1] = k[0, 0] * rng.uniform(0.98, 1.02)
        cam = Camera(k, 640, 480)
        images = [render_checkerboard(cam, random_board_pose(rng, (9, 6), 0.025)) for _ in range(boards)]
        t = time.perf_counter()
        res = calibrate_intrinsics(images, IntrinsicsOptions(board=(9, 6), square_m=0.025))
        dt = time.perf_counter() - t
        est = np.array([res.camera.fx, res.camera.fy, res.camera.cx, res.camera.cy])
        true = np.array([cam.fx, cam.fy, cam.cx, cam.cy])
        rel = (est / true - 1.0) * 100.0
        rows.append(np.abs(rel))
        print(f"  trial {trial}: fx {rel[0]:+.3f} %  fy {rel[1]:+.3f} %  cx {rel[2]:+.3f} %  cy {rel[3]:+.3f} %  "
              f"RMS {res.rms_px:.3f} px, {len(res.used)}/{boards} boards, {dt * 1000:.0f} ms")  # fmt: skip
    worst = np.max(rows, axis=0)
    print(f"  worst |error| over trials: fx {worst[0]:.3f} %, fy {worst[1]:.3f} %, cx {worst[2]:.3f} %, "
          f"cy {worst[3]:.3f} %")  # fmt: skip


def extrinsics(trials: int, seed: int) -> None:
    k = np.array([[615.0, 0, 319.5], [0, 615.0, 239.5], [0, 0, 1]])
    cam = Camera(k, 640, 480)
    for spread in (0.3, 0.6):
        for n in (4, 5, 6, 8):
            rng = np.random.default_rng(seed + n)
            errs = []
            ts = []
            for _ in range(trials):
                d = rng.normal(size=3)
                d[2] = abs(d[2]) + 1.0
                wfc = look_at(d / np.linalg.norm(d) * 1.5, [0.0, 0.0, 0.0])
                while True:  # a surveyor would not pick near-coincident or collinear points: resample those
                    uv = np.column_stack([rng.uniform(40, 600, n), rng.uniform(40, 440, n)])
                    world = transform_points(wfc, cam.backproject(uv, rng.uniform(1.5 - spread, 1.5 + spread, n)))
                    try:
                        check_control_points(world, uv, ExtrinsicsOptions(min_pixel_separation_px=20.0))
                        break
                    except CalibrationError:
                        continue
                noisy = cam.project(transform_points(invert_pose(wfc), world)) + rng.normal(0, 0.5, (n, 2))
                t = time.perf_counter()
                res = calibrate_extrinsics(cam, world, noisy)
                ts.append(time.perf_counter() - t)
                est = res.world_from_camera
                errs.append(
                    (
                        np.linalg.norm(est[:3, 3] - wfc[:3, 3]) * 1000.0,
                        np.degrees(rotation_angle(wfc[:3, :3].T @ est[:3, :3])),
                    )
                )
            e = np.array(errs)
            print(f"  depth spread +-{spread:.1f} m, {n} points: position median {np.median(e[:, 0]):6.2f} mm "
                  f"(p95 {np.percentile(e[:, 0], 95):6.2f}), rotation median {np.median(e[:, 1]):.3f} deg "
                  f"(p95 {np.percentile(e[:, 1], 95):.3f}), {np.median(ts) * 1000:.2f} ms")  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--trials", type=int, default=300)
    parser.add_argument("--boards", type=int, default=12)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    print(f"Intrinsics from {args.boards} rendered 9x6 checkerboards at a known K (relative error)")
    intrinsics(args.boards, args.seed)
    print(f"Extrinsics from control points, 0.5 px pixel noise, camera at 1.5 m ({args.trials} trials each)")
    extrinsics(args.trials, args.seed)


if __name__ == "__main__":
    main()
