"""POSES.csv: the flange pose of every hand-eye image, and the hand-eye field of a camera JSON.

POSES.csv (UTF-8, a header, one row per image in the order the images are given; metres and a UR rotation
vector in radians, as `getActualTCPPose` reports with a zero TCP):

    x,y,z,rx,ry,rz
    0.412300,-0.120500,0.351000,2.221400,-2.221400,0.000000

Blank lines are skipped; every other problem is an InputError of one line naming the file, the line and the
column. An eye-in-hand calibration adds `flange_from_camera` (4x4, metres) to the camera JSON; the camera
loader ignores it, `read_flange_from_camera` reads it.
"""

from __future__ import annotations

import csv
import io
import json
import math
from pathlib import Path

import numpy as np

from normpos_grasp.atomic import atomic_write_text
from normpos_grasp.camera.hand_eye import MAX_FLANGE_DISTANCE_M, MAX_ROTVEC_RAD, check_flange_poses
from normpos_grasp.errors import InputError
from normpos_grasp.geometry.transforms import pose_to_ur
from normpos_grasp.typing import ArrayLike, FloatArray
from normpos_grasp.validation import check_pose

POSE_COLUMNS = ("x", "y", "z", "rx", "ry", "rz")


def read_poses_csv(path: str | Path) -> FloatArray:
    """(N, 6) UR pose vectors [x, y, z, rx, ry, rz] (metres, radians) from a POSES.csv file."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8-sig")
    except OSError as exc:
        raise InputError(f"cannot read poses {p}: {exc.strerror or exc}") from exc
    except UnicodeDecodeError as exc:
        raise InputError(f"{p} is not UTF-8 text ({exc.reason} at byte {exc.start})") from exc
    try:
        rows = [(n, row) for n, row in enumerate(csv.reader(io.StringIO(text)), start=1) if any(c.strip() for c in row)]
    except csv.Error as exc:
        raise InputError(f"{p}: not a CSV file ({exc})") from exc
    if not rows:
        raise InputError(f"{p} is empty; expected a header {','.join(POSE_COLUMNS)} and one row per image")
    header = tuple(c.strip().lower() for c in rows[0][1])
    if header != POSE_COLUMNS:
        raise InputError(f"{p} line {rows[0][0]}: the header must be {','.join(POSE_COLUMNS)}, got {','.join(header)}")
    out = []
    for line, row in rows[1:]:
        if len(row) != len(POSE_COLUMNS):
            raise InputError(
                f"{p} line {line}: expected {len(POSE_COLUMNS)} values {','.join(POSE_COLUMNS)}, got {len(row)}"
            )
        values = []
        for name, cell in zip(POSE_COLUMNS, row, strict=True):
            try:
                v = float(cell.strip())
            except ValueError:
                raise InputError(f"{p} line {line}: {name} = {cell.strip()!r} is not a number") from None
            if not math.isfinite(v):
                raise InputError(f"{p} line {line}: {name} = {cell.strip()} is not finite")
            values.append(v)
        xyz, rot = np.array(values[:3]), np.array(values[3:])
        if np.linalg.norm(xyz) > MAX_FLANGE_DISTANCE_M:
            raise InputError(
                f"{p} line {line}: the flange is {np.linalg.norm(xyz):.4g} m from the base (more than "
                f"{MAX_FLANGE_DISTANCE_M:g} m): looks like millimetres; x, y, z are metres"
            )
        if np.linalg.norm(rot) > MAX_ROTVEC_RAD:
            raise InputError(
                f"{p} line {line}: the rotation vector is {np.linalg.norm(rot):.4g} long (more than 2 pi): looks "
                "like degrees; rx, ry, rz are a UR rotation vector in radians"
            )
        out.append(values)
    if not out:
        raise InputError(f"{p} holds a header but no poses")
    return np.array(out)


def write_poses_csv(path: str | Path, poses: ArrayLike) -> None:
    """Write (N, 6) UR pose vectors or (N, 4, 4) poses as POSES.csv, atomically (temporary file, os.replace)."""
    mats = check_flange_poses(poses)
    buf = io.StringIO()
    out = csv.writer(buf, lineterminator="\n")
    out.writerow(POSE_COLUMNS)
    for m in mats:
        out.writerow([f"{v:.9f}" for v in pose_to_ur(m)])
    atomic_write_text(path, buf.getvalue())


def read_flange_from_camera(path: str | Path) -> FloatArray:
    """The (4, 4) `flange_from_camera` (metres) an eye-in-hand calibration wrote into a camera JSON."""
    p = Path(path)
    try:
        data = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise InputError(f"cannot read camera file {p}: {exc}") from exc
    if not isinstance(data, dict) or "flange_from_camera" not in data:
        raise InputError(f"camera file {p} has no flange_from_camera (run `calibrate hand-eye --mode eye-in-hand`)")
    pose = check_pose(data["flange_from_camera"], f"{p}: flange_from_camera")
    if np.linalg.norm(pose[:3, 3]) > 1.0:
        raise InputError(f"{p}: flange_from_camera puts the camera {np.linalg.norm(pose[:3, 3]):.4g} m from the flange")
    return pose
