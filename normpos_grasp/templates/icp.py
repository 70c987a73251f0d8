"""Batched trimmed point-to-plane ICP of measured points against a template surface (object frame).

Poses are `object_from_frame` (T) with a size factor s: a measured point q corresponds to the CAD point
m = T q / s (the object is s times its CAD size). Only model points whose outward normal agrees with the
measured normal (which faces the camera) are matched, so back faces and hidden sides never attract points.
All hypotheses advance together: one KD-tree / grid query and one batch of 6x6 (7x7) solves per iteration.
"""

from __future__ import annotations

import numpy as np

from normpos_grasp.templates.prepared import PreparedTemplate, normal_bins
from normpos_grasp.typing import FloatArray

NORMAL_COS = 0.35


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

    y, ny: (P, 3) points and their (measured) normals in the object frame.
    Returns residual (P,) point-to-plane distance, dist (P,) point-to-point distance (inf when none),
    model normal (P, 3) and model point (P, 3).
    """
    if exact:
        dist, idx = prep.tree.query(y)
        ok = np.einsum("pd,pd->p", prep.normals[idx], ny) > NORMAL_COS
        if not np.all(ok):
            bad = np.flatnonzero(~ok)
            d2, i2 = prep.nearest_binned(y[bad], normal_bins(ny[bad]))
            dist[bad] = d2
            idx[bad] = i2
            ok[bad] = np.einsum("pd,pd->p", prep.normals[i2], ny[bad]) > NORMAL_COS
        sel = idx
        d = np.where(ok, dist, np.inf)
    else:
        sel, inside = prep.grid_lookup(y)
        ok = np.einsum("pd,pd->p", prep.normals[sel], ny) > NORMAL_COS
        if not np.all(ok):
            bad = np.flatnonzero(~ok)
            s2, in2 = prep.grid_lookup_binned(y[bad], normal_bins(ny[bad]))
            sel[bad] = s2
            inside[bad] = in2
            ok[bad] = np.einsum("pd,pd->p", prep.normals[s2], ny[bad]) > NORMAL_COS
        has = (inside > 0) & ok
        d = np.where(has, np.linalg.norm(y - prep.samples[sel], axis=-1), np.inf)
    n = prep.normals[sel]
    m = prep.samples[sel]
    r = np.einsum("pd,pd->p", y - m, n)
    return r, d, n, m


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
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Refine (H, 4, 4) `object_from_frame` poses and (H,) scales on (P, 3) points/normals.

    thr: (P,) per-point inlier distance (metres, from the depth noise model). The correspondence gate
    shrinks geometrically from `max_corr_start` to 3 thr; correspondences come from the distance grid
    except with `exact` or in the last `exact_last` iterations (KD-tree, normal-compatible); residuals
    above the `trim` quantile are dropped and the rest Huber-weighted.
    point_weight: weight of an added point-to-point term (fixes motions within a single visible plane).
    converge_m: once the gate is at its floor and no hypothesis moves more than this (metres, rotation taken
    at one diameter; default 2e-6 diameter), the grid stage ends early (the exact stage follows) and the
    exact stage stops.
    prune_after / prune_keep: after `prune_after` iterations only the `prune_keep` hypotheses with the highest
    inlier fraction go on (early rejection of hopeless starting poses; 0 = off). The returned arrays then
    hold only the kept hypotheses.
    Returns poses, scales and the (H,) inlier fraction at the last iteration.
    """
    poses = poses.copy()
    scales = scales.copy()
    h = len(poses)
    p = len(pts)
    c = prep.centroid
    gate_end = 3.0 * float(np.median(thr))
    ratio = (gate_end / max(max_corr_start, gate_end)) ** (1.0 / max(iterations - 1, 1))
    gate = max(max_corr_start, gate_end)
    frac = np.zeros(h)
    dof = 7 if fit_scale else 6
    # a prior keeping the scale near 1 unless the data insist (equivalent to a few points at 1 diameter)
    prior = 0.1 * prep.diameter**2
    converge = converge_m if converge_m is not None else 2e-6 * prep.diameter
    it = 0
    while it < iterations:
        rot = poses[:, :3, :3]
        y = (np.einsum("hij,pj->hpi", rot, pts) + poses[:, None, :3, 3]) / scales[:, None, None]
        ny = np.einsum("hij,pj->hpi", rot, nrm)
        use_exact = exact or it >= iterations - exact_last
        r, d, n, m = correspond_points(prep, y.reshape(-1, 3), ny.reshape(-1, 3), exact=use_exact)
        r = r.reshape(h, p)
        d = d.reshape(h, p)
        n = n.reshape(h, p, 3)
        m = m.reshape(h, p, 3)
        valid = d < gate
        absr = np.abs(r)
        frac = (valid & (absr < thr[None])).mean(axis=1)
        # trimming per hypothesis
        big = np.where(valid, absr, np.inf)
        cnt = valid.sum(1)
        kth = np.clip((trim * cnt).astype(int) - 1, 0, p - 1)
        cut = np.take_along_axis(np.sort(big, axis=1), kth[:, None], axis=1)[:, 0]
        valid &= absr <= np.maximum(cut, thr.min())[:, None]
        hub = np.where(absr > thr[None], thr[None] / np.maximum(absr, 1e-12), 1.0)
        w = valid * hub
        jac = np.empty((h, p, dof))
        jac[..., :3] = _cross(y, n)
        jac[..., 3:6] = n
        if fit_scale:
            jac[..., 6] = -np.einsum("hpd,hpd->hp", n, y - c)
        jw = jac * w[..., None]
        a = jw.transpose(0, 2, 1) @ jac
        b = np.asarray(-(jw.transpose(0, 2, 1) @ r[..., None])[..., 0], dtype=np.float64)
        if point_weight > 0:
            # a light point-to-point term pins the in-plane motions point-to-plane leaves free (one flat face);
            # per point J = [-[y]x, I(, -(y - c))]: J^T W J and J^T W e summed in closed form over the points
            wp = np.asarray(w * point_weight, dtype=np.float64)
            ap, bp = point_to_point_normal_equations(y, y - m, wp, c, fit_scale=fit_scale)
            a += ap
            b += bp
        a += np.eye(dof)[None] * 1e-9
        if fit_scale:
            a[:, 6, 6] += prior
            b[:, 6] -= prior * (scales - 1.0)
        enough = cnt >= 6
        a[~enough] = np.eye(dof)
        b[~enough] = 0.0
        delta = np.asarray(np.linalg.solve(a, b[..., None])[..., 0], dtype=np.float64)
        delta[~enough] = 0.0
        rd = batched_rodrigues(delta[:, :3])
        sig = delta[:, 6] if fit_scale else np.zeros(h)
        s_new = np.clip(scales / (1.0 - np.clip(sig, -0.5, 0.5)), 1.0 - scale_tolerance, 1.0 + scale_tolerance)
        new = np.tile(np.eye(4), (h, 1, 1))
        new[:, :3, :3] = rd @ poses[:, :3, :3]
        new[:, :3, 3] = (
            np.einsum("hij,hj->hi", rd, poses[:, :3, 3])
            + scales[:, None] * delta[:, 3:6]
            + (s_new - scales)[:, None] * c[None]
        )
        poses = new
        scales = s_new
        at_floor = gate <= gate_end
        if it < iterations - 1:
            gate = max(gate * ratio, gate_end)
        it += 1
        if prune_after and it == prune_after and h > prune_keep > 0:
            top = np.sort(np.argsort(-frac, kind="stable")[:prune_keep])
            poses, scales, frac = poses[top], scales[top], frac[top]
            h = len(poses)
            continue
        # converged (motion of every hypothesis below `converge`, gate at its floor): the correspondences and
        # so the poses would not change any more; go on with the exact stage or stop
        moved = float(
            np.max(np.linalg.norm(delta[:, :3], axis=1) * prep.diameter + np.linalg.norm(delta[:, 3:6], axis=1))
        )
        if at_floor and moved < converge:
            if not exact and exact_last > 0 and it < iterations - exact_last:
                it = iterations - exact_last
            else:
                break
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
