"""Compiled (numba, nogil) bounding-sphere proofs of `CollisionWorld.configs_clear` (the movers' spheres of each
configuration against the enabled elements' axis-aligned boxes, the arm's spheres against each other and against the
tool's and the held object's) and the per-shape broad phase of `CollisionWorld.near`. They replace numpy passes of
~20 calls per batch with the same arithmetic in the same order (numpy's `einsum('pmi,pmi->pm')` adds the squares of
x and z, then y; `linalg.norm` adds x, y, then z), so the verdicts are the numpy passes' bit for bit
(tests/test_collision_spheres.py keeps those as the reference)."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from normpos_grasp.typing import BoolArray, FloatArray, IntArray


def spheres_off_boxes(
    centres: FloatArray, radii: FloatArray, lo: FloatArray, hi: FloatArray, held_rows: BoolArray, held_index: int
) -> BoolArray:
    """(K,) bool: True where no sphere of configuration k (centres (K, M, 3), radii (K, M), m) touches any box
    (lo, hi (E, 3), m). Only boxes meeting the box around all of a configuration's spheres (1 nm of slack) are
    tested; box `held_index` (-1: none) is skipped for the configurations in `held_rows` (K,)."""
    return np.asarray(
        _off_boxes(
            np.ascontiguousarray(centres, dtype=np.float64),
            np.ascontiguousarray(radii, dtype=np.float64),
            np.ascontiguousarray(lo, dtype=np.float64).reshape(-1, 3),
            np.ascontiguousarray(hi, dtype=np.float64).reshape(-1, 3),
            np.ascontiguousarray(held_rows, dtype=np.bool_),
            int(held_index),
        ),
        dtype=bool,
    )


def spheres_near_boxes(centres: FloatArray, radii: FloatArray, lo: FloatArray, hi: FloatArray) -> BoolArray:
    """(K,) bool: True where sphere k (centres (K, 3), radii (K,), m) touches some box (lo, hi (E, 3), m): the
    per-shape broad phase of `CollisionWorld.near`."""
    return np.asarray(
        _near_boxes(
            np.ascontiguousarray(centres, dtype=np.float64).reshape(-1, 3),
            np.ascontiguousarray(radii, dtype=np.float64).reshape(-1),
            np.ascontiguousarray(lo, dtype=np.float64).reshape(-1, 3),
            np.ascontiguousarray(hi, dtype=np.float64).reshape(-1, 3),
        ),
        dtype=bool,
    )


def spheres_apart(
    arm_c: FloatArray,
    arm_r: FloatArray,
    pair_mask: BoolArray,
    low: IntArray,
    extra_c: FloatArray,
    extra_r: FloatArray,
) -> BoolArray:
    """(K,) bool: True where, in configuration k, no pair of arm spheres (centres arm_c (K, S, 3), radii arm_r (S,),
    m) that `pair_mask` (S, S) checks touches, and no arm sphere of the links `low` (L,) touches a sphere of the
    tool or the held object (centres extra_c (K, T, 3), radii extra_r (K, T), m)."""
    return np.asarray(
        _apart(
            np.ascontiguousarray(arm_c, dtype=np.float64),
            np.ascontiguousarray(arm_r, dtype=np.float64),
            np.ascontiguousarray(pair_mask, dtype=np.bool_),
            np.ascontiguousarray(low, dtype=np.int64),
            np.ascontiguousarray(extra_c, dtype=np.float64),
            np.ascontiguousarray(extra_r, dtype=np.float64),
        ),
        dtype=bool,
    )


@njit(cache=True, nogil=True)
def _off_boxes(centres, radii, lo, hi, held_rows, held_index):  # type: ignore[no-untyped-def]
    k_n, m_n = radii.shape
    e_n = lo.shape[0]
    out = np.ones(k_n, dtype=np.bool_)
    box_lo = np.empty(3)
    box_hi = np.empty(3)
    for k in range(k_n):
        for i in range(3):
            box_lo[i] = centres[k, 0, i] - radii[k, 0]
            box_hi[i] = centres[k, 0, i] + radii[k, 0]
        for m in range(1, m_n):
            for i in range(3):
                box_lo[i] = min(box_lo[i], centres[k, m, i] - radii[k, m])
                box_hi[i] = max(box_hi[i], centres[k, m, i] + radii[k, m])
        for i in range(3):
            box_lo[i] -= 1e-9
            box_hi[i] += 1e-9
        for e in range(e_n):
            if e == held_index and held_rows[k]:
                continue
            meets = True
            for i in range(3):
                if not (lo[e, i] <= box_hi[i] and hi[e, i] >= box_lo[i]):
                    meets = False
            if not meets:
                continue
            for m in range(m_n):
                g0 = min(max(centres[k, m, 0], lo[e, 0]), hi[e, 0]) - centres[k, m, 0]
                g1 = min(max(centres[k, m, 1], lo[e, 1]), hi[e, 1]) - centres[k, m, 1]
                g2 = min(max(centres[k, m, 2], lo[e, 2]), hi[e, 2]) - centres[k, m, 2]
                d2 = (g0 * g0 + g2 * g2) + g1 * g1  # einsum's order
                if d2 <= radii[k, m] * radii[k, m]:
                    out[k] = False
                    break
            if not out[k]:
                break
    return out


@njit(cache=True, nogil=True)
def _near_boxes(centres, radii, lo, hi):  # type: ignore[no-untyped-def]
    out = np.zeros(centres.shape[0], dtype=np.bool_)
    for k in range(centres.shape[0]):
        rr = radii[k] * radii[k]
        for e in range(lo.shape[0]):
            g0 = min(max(centres[k, 0], lo[e, 0]), hi[e, 0]) - centres[k, 0]
            g1 = min(max(centres[k, 1], lo[e, 1]), hi[e, 1]) - centres[k, 1]
            g2 = min(max(centres[k, 2], lo[e, 2]), hi[e, 2]) - centres[k, 2]
            if (g0 * g0 + g2 * g2) + g1 * g1 <= rr:  # einsum's order
                out[k] = True
                break
    return out


@njit(cache=True, nogil=True)
def _apart(arm_c, arm_r, pair_mask, low, extra_c, extra_r):  # type: ignore[no-untyped-def]
    k_n, s_n = arm_c.shape[0], arm_c.shape[1]
    t_n = extra_c.shape[1]
    out = np.ones(k_n, dtype=np.bool_)
    for k in range(k_n):
        hit = False
        for i in range(s_n):
            for j in range(s_n):
                if not pair_mask[i, j]:
                    continue
                x = arm_c[k, i, 0] - arm_c[k, j, 0]
                y = arm_c[k, i, 1] - arm_c[k, j, 1]
                z = arm_c[k, i, 2] - arm_c[k, j, 2]
                if math.sqrt((x * x + y * y) + z * z) - (arm_r[i] + arm_r[j]) <= 0.0:  # linalg.norm's order
                    hit = True
                    break
            if hit:
                break
        if not hit:
            for a in range(low.shape[0]):
                i = low[a]
                for m in range(t_n):
                    x = arm_c[k, i, 0] - extra_c[k, m, 0]
                    y = arm_c[k, i, 1] - extra_c[k, m, 1]
                    z = arm_c[k, i, 2] - extra_c[k, m, 2]
                    if math.sqrt((x * x + y * y) + z * z) - (arm_r[i] + extra_r[k, m]) <= 0.0:
                        hit = True
                        break
                if hit:
                    break
        out[k] = not hit
    return out
