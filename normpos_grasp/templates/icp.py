"""Batched trimmed point-to-plane ICP of measured points against a template surface (object frame).

Poses are `object_from_frame` (T) with a size factor s: a measured point q corresponds to the CAD point
m = T q / s (the object is s times its CAD size). Only model points whose outward normal agrees with the
measured normal (which faces the camera) are matched, so back faces and hidden sides never attract points.
All hypotheses advance together: one KD-tree / grid query and one batch of 6x6 (7x7) solves per iteration.
"""

from __future__ import annotations

import threading
import weakref

import numpy as np

from normpos_grasp.templates import kernels
from normpos_grasp.templates.prepared import PreparedTemplate
from normpos_grasp.typing import FloatArray

NORMAL_COS = kernels.NORMAL_COS

_CANDIDATES: weakref.WeakKeyDictionary[PreparedTemplate, tuple[np.ndarray, ...]] = weakref.WeakKeyDictionary()
_LOCK = threading.Lock()


def candidates(prep: PreparedTemplate) -> tuple[np.ndarray, ...]:
    """The template's exact-nearest candidates sorted per grid cell (`kernels.sorted_candidates`), built once."""
    with _LOCK:
        hit = _CANDIDATES.get(prep)
        if hit is None:
            hit = kernels.sorted_candidates(prep.samples, prep.grid[6], prep.grid)
            _CANDIDATES[prep] = hit
    return hit


def correspond(
    prep: PreparedTemplate, y: FloatArray, ny: FloatArray, *, exact: bool
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Closest normal-compatible model sample: point-to-plane residual (P,), distance (P,), normal (P, 3)."""
    r, d, n, _ = correspond_points(prep, y, ny, exact=exact)
    return r, d, n


def correspond_points(
    prep: PreparedTemplate,
    y: FloatArray,
    ny: FloatArray,
    *,
    exact: bool,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Closest normal-compatible model sample for object-frame points.

    y, ny: (P, 3) points and their (measured) normals in the object frame. `exact`: exact nearest samples
    (KD-tree), else the distance grid's (outside the grid: no correspondence). A sample whose normal disagrees
    with ny (cos <= 0.35) is replaced by the nearest one in the same normal bin (`prepared.normal_bins`).
    Returns residual (P,) point-to-plane distance, dist (P,) point-to-point distance (inf when none),
    model normal (P, 3) and model point (P, 3).
    """
    y = np.ascontiguousarray(y, dtype=np.float64).reshape(-1, 3)
    ny = np.ascontiguousarray(ny, dtype=np.float64).reshape(-1, 3)
    r, d, sel = kernels.correspond_many(y, ny, exact, prep.samples, prep.normals, prep.grid, prep.kd)
    return r, d, prep.normals[sel], prep.samples[sel]


def icp(
    prep: PreparedTemplate,
    poses: FloatArray,
    scales: FloatArray,
    pts: FloatArray,
    nrm: FloatArray,
    thr: FloatArray,
    *,
    iterations: int,
    exact: bool,
    fit_scale: bool,
    scale_tolerance: float,
    max_corr_start: float,
    trim: float = 0.85,
    exact_last: int = 0,
    point_weight: float = 0.05,
    converge_m: float | None = None,
    prune_after: int = 0,
    prune_keep: int = 0,
    thr_median: float | None = None,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Refine (H, 4, 4) `object_from_frame` poses and (H,) scales on (P, 3) points/normals.

    thr: (P,) per-point inlier distance (metres, from the depth noise model). The correspondence gate
    shrinks geometrically from `max_corr_start` to 3 thr; correspondences come from the distance grid
    except with `exact` or in the last `exact_last` iterations (KD-tree, normal-compatible); residuals
    above the `trim` quantile are dropped and the rest Huber-weighted.
    point_weight: weight of an added point-to-point term (fixes motions within a single visible plane).
    converge_m: once the gate is at its floor and a hypothesis moves less than this (metres, rotation taken
    at one diameter; default 2e-6 diameter), its grid stage ends early (the exact stage follows) or, in the
    exact stage, it stops (each hypothesis on its own).
    prune_after / prune_keep: after `prune_after` iterations only the `prune_keep` hypotheses with the highest
    inlier fraction go on (early rejection of hopeless starting poses; 0 = off). The returned arrays then
    hold only the kept hypotheses.
    thr_median: median of thr when the caller knows it (saves recomputing it).
    Returns poses, scales and the (H,) inlier fraction at the last iteration.
    The iterations run in the compiled `kernels.icp_run` (GIL released).
    """
    poses = np.array(poses, dtype=np.float64, order="C").reshape(-1, 4, 4)
    scales = np.array(scales, dtype=np.float64).reshape(-1)
    pts = np.ascontiguousarray(pts, dtype=np.float64)
    nrm = np.ascontiguousarray(nrm, dtype=np.float64)
    thr = np.ascontiguousarray(thr, dtype=np.float64)
    h = len(poses)
    frac = np.zeros(h)
    if h == 0 or iterations <= 0 or len(pts) == 0:
        return poses, scales, frac
    gate_end = 3.0 * (float(np.median(thr)) if thr_median is None else thr_median)
    ratio = (gate_end / max(max_corr_start, gate_end)) ** (1.0 / max(iterations - 1, 1))
    gates = np.empty(iterations)
    gate = max(max_corr_start, gate_end)
    for it in range(iterations):
        gates[it] = gate
        if it < iterations - 1:
            gate = max(gate * ratio, gate_end)
    exact_iter = np.array([exact or it >= iterations - exact_last for it in range(iterations)])
    jump_to = iterations - exact_last if (not exact and exact_last > 0) else iterations
    # a prior keeping the scale near 1 unless the data insist (equivalent to a few points at 1 diameter)
    prior = 0.1 * prep.diameter**2
    converge = converge_m if converge_m is not None else 2e-6 * prep.diameter
    it_state = np.zeros(h, dtype=np.int64)

    def run(stop: int) -> None:
        kernels.icp_run(
            poses,
            scales,
            frac,
            it_state,
            pts,
            nrm,
            thr,
            gates,
            exact_iter,
            stop,
            jump_to,
            gate_end,
            fit_scale,
            float(scale_tolerance),
            float(trim),
            float(point_weight),
            prior,
            float(converge),
            prep.centroid,
            prep.diameter,
            prep.samples,
            prep.normals,
            prep.grid,
            prep.kd,
            cand,
        )

    cand = candidates(prep)
    if prune_after and h > prune_keep > 0 and prune_after < iterations:
        run(prune_after)
        top = np.sort(np.argsort(-frac, kind="stable")[:prune_keep])
        poses, scales, frac, it_state = poses[top], scales[top], frac[top], it_state[top]
    run(iterations)
    return poses, scales, frac


def point_to_point_normal_equations(
    y: FloatArray, e: FloatArray, w: FloatArray, c: FloatArray, *, fit_scale: bool
) -> tuple[FloatArray, FloatArray]:
    """Gauss-Newton terms of a weighted point-to-point residual, summed in closed form over the points.

    y (H, P, 3) object-frame points, e (H, P, 3) residuals y - model point, w (H, P) weights, c (3,) scale
    centre. Per point J = [-[y]x, I(, -(y - c))]; returns sum w J^T J (H, dof, dof) and -sum w J^T e (H, dof),
    dof 6 (7 with the size factor).
    """
    h = y.shape[0]
    dof = 7 if fit_scale else 6
    a = np.zeros((h, dof, dof))
    b = np.zeros((h, dof))
    s0 = w.sum(1)
    s1 = (w[:, None, :] @ y)[:, 0]  # (h, 3) sum w y
    s2 = (y * w[..., None]).transpose(0, 2, 1) @ y  # (h, 3, 3) sum w y y^T
    sx = _skew(s1)
    a[:, :3, :3] = np.einsum("hii->h", s2)[:, None, None] * np.eye(3) - s2
    a[:, :3, 3:6] = sx
    a[:, 3:6, :3] = -sx
    a[:, 3:6, 3:6] = s0[:, None, None] * np.eye(3)
    b[:, :3] = -(w[:, None, :] @ _cross(y, e))[:, 0]
    b[:, 3:6] = -(w[:, None, :] @ e)[:, 0]
    if fit_scale:
        yc = y - c
        col_r = (w[:, None, :] @ _cross(y, np.broadcast_to(c, y.shape)))[:, 0]  # sum w y x c
        col_t = -(w[:, None, :] @ yc)[:, 0]
        a[:, :3, 6] = col_r
        a[:, 6, :3] = col_r
        a[:, 3:6, 6] = col_t
        a[:, 6, 3:6] = col_t
        a[:, 6, 6] = np.einsum("hp,hpd,hpd->h", w, yc, yc)
        b[:, 6] = (w[:, None, :] @ np.einsum("hpd,hpd->hp", yc, e)[..., None])[:, 0, 0]
    return a, b


def _skew(v: FloatArray) -> FloatArray:
    """(H, 3, 3) cross-product matrices [v]x of (H, 3) vectors."""
    out = np.zeros((len(v), 3, 3))
    out[:, 0, 1] = -v[:, 2]
    out[:, 0, 2] = v[:, 1]
    out[:, 1, 0] = v[:, 2]
    out[:, 1, 2] = -v[:, 0]
    out[:, 2, 0] = -v[:, 1]
    out[:, 2, 1] = v[:, 0]
    return out


def _cross(a: FloatArray, b: FloatArray) -> FloatArray:
    """Cross product over the last axis of (..., 3) arrays (np.cross without its per-call overhead)."""
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    out[..., 0] = a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1]
    out[..., 1] = a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2]
    out[..., 2] = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    return out


def batched_rodrigues(rotvec: FloatArray) -> FloatArray:
    """(H, 3, 3) rotations from (H, 3) rotation vectors (radians)."""
    theta = np.linalg.norm(rotvec, axis=1)
    small = theta < 1e-12
    axis = rotvec / np.where(small, 1.0, theta)[:, None]
    kx = np.zeros((len(rotvec), 3, 3))
    kx[:, 0, 1] = -axis[:, 2]
    kx[:, 0, 2] = axis[:, 1]
    kx[:, 1, 0] = axis[:, 2]
    kx[:, 1, 2] = -axis[:, 0]
    kx[:, 2, 0] = -axis[:, 1]
    kx[:, 2, 1] = axis[:, 0]
    st = np.sin(theta)[:, None, None]
    ct = (1.0 - np.cos(theta))[:, None, None]
    return np.eye(3)[None] + st * kx + ct * (kx @ kx)
