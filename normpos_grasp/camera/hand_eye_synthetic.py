"""Synthetic hand-eye set-ups with known truth, for tests and benchmarks.

A set-up fixes the two unknowns of a mode (see `camera.hand_eye`) and draws views of the board: the camera looks
at the board centre from 0.4-0.9 m, tilted up to ~35 degrees (`checkerboard.random_board_pose`) and rolled about
its optical axis; the flange pose of each view follows from the truth. Render each `camera_from_board` with
`checkerboard.render_checkerboard` to get the image.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from normpos_grasp.camera.checkerboard import random_board_pose
from normpos_grasp.camera.hand_eye import EYE_IN_HAND, EYE_TO_HAND, check_mode
from normpos_grasp.geometry.transforms import invert_pose, look_at, make_pose, rotation_from_rotvec
from normpos_grasp.typing import FloatArray


@dataclass(frozen=True, eq=False)
class HandEyeScene:
    """Truth and views: camera_pose (4, 4) base_from_camera or flange_from_camera, board_pose (4, 4)
    flange_from_board or base_from_board, base_from_flange (N, 4, 4), camera_from_board (N, 4, 4)."""

    mode: str
    camera_pose: FloatArray
    board_pose: FloatArray
    base_from_flange: FloatArray
    camera_from_board: FloatArray


def hand_eye_scene(
    rng: np.random.Generator,
    mode: str,
    n_views: int = 15,
    board: tuple[int, int] = (9, 6),
    square_m: float = 0.025,
    roll_deg: float = 30.0,
) -> HandEyeScene:
    """A UR-cell-like set-up: eye-to-hand, a camera 1.0 m above the table looking down at the robot's work area
    and the board 2 cm out from the flange; eye-in-hand, a wrist camera 7 cm off the flange axis and the board on
    the table 0.5 m in front of the base. Views are `n_views` random board poses seen by the camera (0.5-0.9 m
    eye-to-hand, 0.4-0.65 m eye-in-hand) rolled up to `roll_deg` about the optical axis."""
    check_mode(mode)
    cols, rows = board
    centre = np.array([(cols - 1) * square_m / 2, (rows - 1) * square_m / 2, 0.0])
    face = np.diag([1.0, -1.0, -1.0])  # board z (into the board) against the frame's z
    if mode == EYE_TO_HAND:
        camera_pose = look_at([0.55, 0.25, 1.0], [0.45, 0.0, 0.25], up=(1.0, 0.0, 0.0))
        tweak = make_pose(rotation_from_rotvec([0.03, -0.02, 0.4]))
        board_pose = make_pose(face, [0.0, 0.0, 0.02]) @ tweak @ make_pose(translation=-centre)
        distance = (0.5, 0.9)
    else:
        camera_pose = make_pose(rotation_from_rotvec([0.05, -0.03, 1.5]), [0.0, -0.07, 0.045])
        board_pose = make_pose(face @ rotation_from_rotvec([0.0, 0.0, 0.3]), [0.5, 0.1, 0.0])
        distance = (0.4, 0.65)
    flanges, views = [], []
    for _ in range(n_views):
        cfb = random_board_pose(rng, board, square_m, distance)
        roll = make_pose(rotation_from_rotvec([0.0, 0.0, np.radians(rng.uniform(-roll_deg, roll_deg))]))
        cfb = roll @ cfb
        if mode == EYE_IN_HAND:  # B X C = W
            bff = board_pose @ invert_pose(cfb) @ invert_pose(camera_pose)
        else:  # B W = X C
            bff = camera_pose @ cfb @ invert_pose(board_pose)
        flanges.append(bff)
        views.append(cfb)
    return HandEyeScene(mode, camera_pose, board_pose, np.stack(flanges), np.stack(views))


__all__ = ["EYE_IN_HAND", "EYE_TO_HAND", "HandEyeScene", "hand_eye_scene"]
