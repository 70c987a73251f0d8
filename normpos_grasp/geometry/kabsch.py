"""Reflection-safe rigid alignment of corresponding points (the paper's Eq. 11-16; Kabsch/Umeyama)."""

from __future__ import annotations

import numpy as np

from normpos_grasp.errors import InputError
from normpos_grasp.typing import ArrayLike, FloatArray
from normpos_grasp.validation import as_float_array


def kabsch(
    source: ArrayLike,
    target: ArrayLike,
    weights: ArrayLike | None = None,
    *,
    min_spread: float = 1e-9,
) -> FloatArray:
    """Return `target_from_source` (4, 4) minimising sum w_i |R s_i + t - p_i|^2 with det(R) = +1.

    Centroids first (Eq. 11-13), then H = B^T A = U S V^T (Eq. 14-15), R = U diag(1, 1, d) V^T with
    d = sign(det(U V^T)) so a reflection is never returned, T = p_c - R s_c (Eq. 16). No scaling.

    Args:
        source: (N, 3) points in the source frame (for example template control points), metres.
        target: (N, 3) corresponding points in the target frame (for example measured world points).
        weights: optional (N,) non-negative weights.
        min_spread: points whose second singular value falls below this (metres^2) are collinear.

    Raises:
        InputError: shapes differ, fewer than 3 points, negative weights, or collinear/coincident points.

    >>> import numpy as np
    >>> pts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]])
    >>> np.allclose(kabsch(pts, pts + [1, 2, 3])[:3, 3], [1, 2, 3])
    True
    """
    src = as_float_array(source, "source", (None, 3))
    dst = as_float_array(target, "target", (None, 3))
    if src.shape != dst.shape:
        raise InputError(f"source and target must have the same shape, got {src.shape} and {dst.shape}")
    if len(src) < 3:
        raise InputError(f"kabsch needs at least 3 corresponding points, got {len(src)}")
    if weights is None:
        w = np.ones(len(src))
    else:
        w = as_float_array(weights, "weights", (len(src),))
        if np.any(w < 0) or w.sum() <= 0:
            raise InputError("weights must be non-negative with a positive sum")
    w = w / w.sum()
    src_c = w @ src
    dst_c = w @ dst
    a = src - src_c
    b = dst - dst_c
    spread = np.linalg.svd(a * np.sqrt(w)[:, None], compute_uv=False)
    if spread[1] ** 2 < min_spread:
        raise InputError(
            f"source points are collinear or coincident (singular values {spread.round(9).tolist()}); "
            "use at least 3 non-collinear points"
        )
    h = (b * w[:, None]).T @ a  # 3x3 cross-covariance, target x source
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(u @ vt))
    if d == 0:
        d = 1.0
    rot = u @ np.diag([1.0, 1.0, d]) @ vt
    pose = np.eye(4)
    pose[:3, :3] = rot
    pose[:3, 3] = dst_c - rot @ src_c
    return pose
