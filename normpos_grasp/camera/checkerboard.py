"""Synthetic checkerboard images at a known camera (for testing and benchmarking intrinsic calibration).

The board texture is warped by the exact plane homography K [r1 r2 t] with `cv2.warpPerspective`, rendered
at `supersample` times the resolution and area-averaged down, so edges are anti-aliased like a real lens.
Pixel centres sit at integer coordinates, as in OpenCV. Distortion is not rendered.
"""

from __future__ import annotations

import numpy as np

from normpos_grasp.camera.model import Camera
from normpos_grasp.errors import InputError
from normpos_grasp.geometry.transforms import look_at, make_pose, rotation_from_rotvec
from normpos_grasp.typing import FloatArray, UInt8Array
from normpos_grasp.validation import check_pose


def render_checkerboard(
    camera: Camera,
    camera_from_board: FloatArray,
    board: tuple[int, int] = (9, 6),
    square_m: float = 0.025,
    *,
    supersample: int = 3,
    px_per_square: int = 64,
) -> UInt8Array:
    """(H, W) uint8 gray image of a board with `board` inner corners; the board frame has its origin at the
    first inner corner, x along columns, y along rows, z into the board (OpenCV's convention)."""
    import cv2

    pose = check_pose(camera_from_board, "camera_from_board")
    if camera.has_distortion:
        raise InputError("render_checkerboard renders pinhole images only; pass a camera without distortion")
    cols, rows = board
    if min(cols, rows) < 2 or not square_m > 0:
        raise InputError(f"board needs >= 2x2 inner corners and square_m > 0, got {board}, {square_m}")
    margin = 1  # squares of white border
    n_x, n_y = cols + 1 + 2 * margin, rows + 1 + 2 * margin
    tex = np.full((n_y * px_per_square, n_x * px_per_square), 255, np.uint8)
    for j in range(rows + 1):
        for i in range(cols + 1):
            if (i + j) % 2 == 0:
                y0, x0 = (j + margin) * px_per_square, (i + margin) * px_per_square
                tex[y0 : y0 + px_per_square, x0 : x0 + px_per_square] = 0
    # texture pixel (tx, ty) -> board metres: X = (tx + 0.5) / pps * sq - (1 + margin) * sq
    s = square_m / px_per_square
    off = -(1 + margin) * square_m + 0.5 * s
    board_from_tex = np.array([[s, 0, off], [0, s, off], [0, 0, 1.0]])
    cam = camera.scaled(supersample)
    plane = np.column_stack([pose[:3, 0], pose[:3, 1], pose[:3, 3]])
    h_img = cam.K @ plane @ board_from_tex
    big = cv2.warpPerspective(
        tex,
        h_img,
        (cam.width, cam.height),
        flags=cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=128,
    )
    small = cv2.resize(big, (camera.width, camera.height), interpolation=cv2.INTER_AREA)
    return np.asarray(small, dtype=np.uint8)


def random_board_pose(
    rng: np.random.Generator, board: tuple[int, int], square_m: float, distance_m: tuple[float, float] = (0.5, 0.9)
) -> FloatArray:
    """A `camera_from_board` looking at the board centre from a random distance, tilted up to ~35 degrees."""
    cols, rows = board
    centre = np.array([(cols - 1) * square_m / 2, (rows - 1) * square_m / 2, 0.0])
    dist = rng.uniform(*distance_m)
    tilt = rotation_from_rotvec(rng.uniform(-0.6, 0.6, 3) * np.array([1.0, 1.0, 0.5]))
    eye = centre + tilt @ np.array([0.0, 0.0, -dist])
    board_from_camera = look_at(eye, centre, up=(0.0, -1.0, 0.0))
    shift = make_pose(translation=rng.uniform(-0.06, 0.06, 3) * np.array([1, 1, 0]))
    return np.asarray(np.linalg.inv(board_from_camera) @ shift)
