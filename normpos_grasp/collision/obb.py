"""Compiled (numba, nogil) separating-axis test of oriented box pairs, for the pairs the tool's cell-box screen
(`CollisionWorld.tool_box_hits`) cannot part by their axis-aligned extents (it replaced a numpy version of ~50 calls
per batch; tests/test_collision_batched.py keeps that one as the reference: same axes, same sums in the same order,
same 1e-12 guard, the same verdicts)."""

from __future__ import annotations

import numpy as np
from numba import njit

from normpos_grasp.typing import BoolArray, FloatArray


def obb_overlap_pairs(
    c1: FloatArray, r1: FloatArray, h1: FloatArray, c2: FloatArray, r2: FloatArray, h2: FloatArray
) -> BoolArray:
    """(P,) bool: True where box pair k overlaps. Box 1: centres c1 (P, 3), rotations r1 (P, 3, 3) (columns = box
    axes), half extents h1 (3,) shared by all pairs; box 2: c2 (P, 3), r2 (P, 3, 3), h2 (P, 3); metres."""
    return np.asarray(
        _overlap(
            np.ascontiguousarray(c1, dtype=np.float64),
            np.ascontiguousarray(r1, dtype=np.float64),
            np.ascontiguousarray(h1, dtype=np.float64).reshape(3),
            np.ascontiguousarray(c2, dtype=np.float64),
            np.ascontiguousarray(r2, dtype=np.float64),
            np.ascontiguousarray(h2, dtype=np.float64),
        ),
        dtype=bool,
    )


def aligned_box_hits(world: FloatArray, half: FloatArray, bc: FloatArray, br: FloatArray, bh: FloatArray) -> BoolArray:
    """(R,) bool: True where tool box r (world_from_shape (R, 4, 4), half extents `half` (3,)) overlaps one of the
    world-aligned boxes (centres bc (B, 3), rotations br (B, 3, 3), half extents bh (B, 3)), m: a pair passes the
    AABB test (|centre distance| <= bh + the tool box's world AABB half extent + 1 nm per axis; the extent summed as
    numpy's `(abs(R) * half).sum(axis=1)` sums it, left to right) before the separating-axis test
    (`obb_overlap_pairs`'s). The cell-box screen of `CollisionWorld.tool_box_hits`."""
    return np.asarray(
        _aligned_hits(
            np.ascontiguousarray(world, dtype=np.float64),
            np.ascontiguousarray(half, dtype=np.float64).reshape(3),
            np.ascontiguousarray(bc, dtype=np.float64),
            np.ascontiguousarray(br, dtype=np.float64),
            np.ascontiguousarray(bh, dtype=np.float64),
        ),
        dtype=bool,
    )


@njit(cache=True, nogil=True)
def _aligned_hits(world, half, bc, br, bh):  # type: ignore[no-untyped-def]
    n = world.shape[0]
    out = np.zeros(n, dtype=np.bool_)
    c1 = np.empty(3)
    r1 = np.empty((3, 3))
    ext = np.empty(3)
    for r in range(n):
        for i in range(3):
            c1[i] = world[r, i, 3]
            for j in range(3):
                r1[i, j] = world[r, i, j]
            ext[i] = (abs(r1[i, 0]) * half[0] + abs(r1[i, 1]) * half[1]) + abs(r1[i, 2]) * half[2]
        for b in range(bc.shape[0]):
            near = True
            for i in range(3):
                if not abs(c1[i] - bc[b, i]) <= bh[b, i] + ext[i] + 1e-9:
                    near = False
            if near and _sat(c1, r1, half, bc[b], br[b], bh[b]):
                out[r] = True
                break
    return out


@njit(cache=True, nogil=True)
def _overlap(c1, r1, h1, c2, r2, h2):  # type: ignore[no-untyped-def]
    n = c1.shape[0]
    out = np.zeros(n, dtype=np.bool_)
    for k in range(n):
        out[k] = _sat(c1[k], r1[k], h1, c2[k], r2[k], h2[k])
    return out


@njit(cache=True, nogil=True)
def _sat(c1, r1, h1, c2, r2, h2):  # type: ignore[no-untyped-def]
    """One pair: centres (3,), rotations (3, 3), half extents (3,); True where the boxes overlap."""
    rot = np.empty((3, 3))
    ar = np.empty((3, 3))
    t = np.empty(3)
    for i in range(3):
        for m in range(3):
            s = 0.0
            for j in range(3):
                s += r1[j, i] * r2[j, m]
            rot[i, m] = s
            ar[i, m] = abs(s) + 1e-12
        s = 0.0
        for j in range(3):
            s += r1[j, i] * (c2[j] - c1[j])
        t[i] = s
    for i in range(3):  # box 1 axes
        rb = 0.0
        for j in range(3):
            rb += h2[j] * ar[i, j]
        if abs(t[i]) > h1[i] + rb:
            return False
    for j in range(3):  # box 2 axes
        ra = 0.0
        d = 0.0
        for i in range(3):
            ra += h1[i] * ar[i, j]
            d += t[i] * rot[i, j]
        if abs(d) > ra + h2[j]:
            return False
    for i in range(3):  # cross products
        i1 = (i + 1) % 3
        i2 = (i + 2) % 3
        for j in range(3):
            j1 = (j + 1) % 3
            j2 = (j + 2) % 3
            ra = h1[i1] * ar[i2, j] + h1[i2] * ar[i1, j]
            rb = h2[j1] * ar[i, j2] + h2[j2] * ar[i, j1]
            if abs(t[i2] * rot[i1, j] - t[i1] * rot[i2, j]) > ra + rb:
                return False
    return True
