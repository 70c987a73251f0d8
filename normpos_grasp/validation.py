"""Input checks that raise `InputError` naming the argument, the expected shape and what came."""

from __future__ import annotations

import numpy as np

from normpos_grasp.errors import InputError
from normpos_grasp.typing import ArrayLike, FloatArray


def short_repr(value: object, limit: int = 60) -> str:
    """repr(value) cut to `limit` characters (with '...'): a bad value quoted in a one-line error."""
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def as_float_array(value: ArrayLike, name: str, shape: tuple[int | None, ...]) -> FloatArray:
    """Return `value` as a new float64 array of `shape` (None matches any length); all finite.

    >>> as_float_array([1, 2, 3], "t", (3,)).dtype
    dtype('float64')
    """
    try:
        arr = np.array(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name}: expected numeric array of shape {_fmt(shape)}, got {type(value).__name__}") from exc
    if arr.ndim != len(shape) or any(s is not None and s != d for s, d in zip(shape, arr.shape, strict=True)):
        raise InputError(f"{name}: expected shape {_fmt(shape)}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise InputError(f"{name}: contains NaN or inf values")
    return arr


def check_pose(value: ArrayLike, name: str = "pose", tol: float = 1e-6) -> FloatArray:
    """Return a validated (4, 4) homogeneous transform: orthonormal rotation with det +1, last row [0 0 0 1]."""
    pose = as_float_array(value, name, (4, 4))
    if not np.allclose(pose[3], [0.0, 0.0, 0.0, 1.0], atol=tol):
        raise InputError(f"{name}: last row must be [0, 0, 0, 1], got {pose[3].tolist()}")
    rot = pose[:3, :3]
    if not np.allclose(rot @ rot.T, np.eye(3), atol=tol) or np.linalg.det(rot) < 0:
        raise InputError(f"{name}: rotation block is not a proper rotation (det={np.linalg.det(rot):.6f})")
    return pose


def _fmt(shape: tuple[int | None, ...]) -> str:
    return "(" + ", ".join("N" if s is None else str(s) for s in shape) + ("," if len(shape) == 1 else "") + ")"
