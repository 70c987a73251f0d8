"""Homogeneous transforms named `a_from_b`: `a_from_c = a_from_b @ b_from_c`. Metres and radians."""

from __future__ import annotations

import numpy as np

from normpos_grasp.typing import ArrayLike, FloatArray
from normpos_grasp.validation import as_float_array


def make_pose(rotation: ArrayLike | None = None, translation: ArrayLike | None = None) -> FloatArray:
    """Build a (4, 4) pose from a (3, 3) rotation and a (3,) translation in metres."""
    pose = np.eye(4)
    if rotation is not None:
        pose[:3, :3] = as_float_array(rotation, "rotation", (3, 3))
    if translation is not None:
        pose[:3, 3] = as_float_array(translation, "translation", (3,))
    return pose


def invert_pose(a_from_b: ArrayLike) -> FloatArray:
    """Return `b_from_a` for a rigid (4, 4) `a_from_b`, exactly (R^T, -R^T t)."""
    pose = as_float_array(a_from_b, "a_from_b", (4, 4))
    inv = np.eye(4)
    inv[:3, :3] = pose[:3, :3].T
    inv[:3, 3] = -pose[:3, :3].T @ pose[:3, 3]
    return inv


def transform_points(a_from_b: ArrayLike, points_b: ArrayLike) -> FloatArray:
    """Map (N, 3) points from frame b to frame a; returns a new (N, 3) array."""
    pose = np.asarray(a_from_b, dtype=np.float64)
    pts = np.asarray(points_b, dtype=np.float64).reshape(-1, 3)
    return pts @ pose[:3, :3].T + pose[:3, 3]


def rotation_angle(rotation: ArrayLike) -> float:
    """Angle in radians of a (3, 3) rotation, in [0, pi]; numerically safe near 0 and pi."""
    rot = np.asarray(rotation, dtype=np.float64)
    cos = np.clip((np.trace(rot) - 1.0) / 2.0, -1.0, 1.0)
    sin = 0.5 * np.linalg.norm([rot[2, 1] - rot[1, 2], rot[0, 2] - rot[2, 0], rot[1, 0] - rot[0, 1]])
    return float(np.arctan2(sin, cos))


def rotation_from_rotvec(rotvec: ArrayLike) -> FloatArray:
    """(3, 3) rotation from an axis-angle vector (radians), Rodrigues' formula."""
    vec = as_float_array(rotvec, "rotvec", (3,))
    theta = float(np.linalg.norm(vec))
    if theta < 1e-12:
        skew = _skew(vec)
        return np.eye(3) + skew
    k = _skew(vec / theta)
    return np.eye(3) + np.sin(theta) * k + (1.0 - np.cos(theta)) * (k @ k)


def rotation_to_rotvec(rotation: ArrayLike) -> FloatArray:
    """Axis-angle vector (3,) of a (3, 3) rotation; angle in [0, pi], stable near pi."""
    rot = as_float_array(rotation, "rotation", (3, 3))
    theta = rotation_angle(rot)
    if theta < 1e-9:
        return np.array([rot[2, 1] - rot[1, 2], rot[0, 2] - rot[2, 0], rot[1, 0] - rot[0, 1]]) / 2.0
    if np.pi - theta < 1e-6:
        # R = 2 a a^T - I near pi: take the column of largest diagonal for a well-conditioned axis.
        sym = (rot + np.eye(3)) / 2.0
        i = int(np.argmax(np.diag(sym)))
        axis = sym[:, i] / np.sqrt(max(sym[i, i], 1e-300))
        return axis / np.linalg.norm(axis) * theta
    axis = np.array([rot[2, 1] - rot[1, 2], rot[0, 2] - rot[2, 0], rot[1, 0] - rot[0, 1]])
    return axis / (2.0 * np.sin(theta)) * theta


def pose_to_ur(a_from_b: ArrayLike) -> FloatArray:
    """UR pose vector [x, y, z, rx, ry, rz] (metres, axis-angle radians) of a (4, 4) pose."""
    pose = as_float_array(a_from_b, "a_from_b", (4, 4))
    return np.concatenate([pose[:3, 3], rotation_to_rotvec(pose[:3, :3])])


def pose_from_ur(pose_vector: ArrayLike) -> FloatArray:
    """(4, 4) pose from a UR pose vector [x, y, z, rx, ry, rz]."""
    vec = as_float_array(pose_vector, "pose_vector", (6,))
    return make_pose(rotation_from_rotvec(vec[3:]), vec[:3])


def random_rotation(rng: np.random.Generator) -> FloatArray:
    """Uniformly distributed (3, 3) rotation drawn from `rng` (a unit quaternion, Shoemake)."""
    u1, u2, u3 = rng.random(3)
    q = np.array(
        [
            np.sqrt(1 - u1) * np.sin(2 * np.pi * u2),
            np.sqrt(1 - u1) * np.cos(2 * np.pi * u2),
            np.sqrt(u1) * np.sin(2 * np.pi * u3),
            np.sqrt(u1) * np.cos(2 * np.pi * u3),
        ]
    )
    return rotation_from_quaternion(q)


def rotation_from_quaternion(quat_xyzw: ArrayLike) -> FloatArray:
    """(3, 3) rotation from a quaternion [x, y, z, w] (normalised here)."""
    x, y, z, w = np.asarray(quat_xyzw, dtype=np.float64) / np.linalg.norm(quat_xyzw)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def look_at(eye: ArrayLike, target: ArrayLike, up: ArrayLike = (0.0, 0.0, 1.0)) -> FloatArray:
    """`world_from_camera` for an OpenCV camera (z forward, y down) at `eye` looking at `target`."""
    eye_v = as_float_array(eye, "eye", (3,))
    z = as_float_array(target, "target", (3,)) - eye_v
    z /= np.linalg.norm(z)
    up_v = as_float_array(up, "up", (3,))
    x = np.cross(z, up_v)
    if np.linalg.norm(x) < 1e-9:  # looking along `up`: pick any perpendicular
        x = np.cross(z, [1.0, 0.0, 0.0] if abs(z[0]) < 0.9 else [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)  # image right = forward x up
    y = np.cross(z, x)  # image down = -(up projected onto the image plane)
    return make_pose(np.column_stack([x, y, z]), eye_v)


def _skew(v: FloatArray) -> FloatArray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
