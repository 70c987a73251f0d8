"""Point-pair-feature voting (Drost, Ulrich, Navab, Ilic, CVPR 2010): template pose hypotheses in a whole scene cloud.

The model: template surface samples on a grid of `step` (metres), every ordered pair within one diameter described
by F(m1, m2) = (|d|, angle(n1, d), angle(n2, d), angle(n1, n2)), quantised (`step`, pi / n_angle) into a dense table
of keys -> (first point, alpha_m), alpha_m the angle of m2 about the x axis once m1 sits at the origin with n1 along
+x. A scene reference point s_r votes, for each scene point s_j within one diameter, for every model pair with the
same key: the model reference point m_r and the rotation alpha = alpha_s - alpha_m about x; the accumulator's peak
gives camera_from_object = T_s^-1 Rx(alpha) T_m. Own implementation; the voting loop is compiled (numba, GIL
released) like `templates.kernels`.
"""

from __future__ import annotations

import math
import threading
import weakref
from dataclasses import dataclass

import numba
import numpy as np

from normpos_grasp.templates import kernels
from normpos_grasp.templates.features import voxel_downsample
from normpos_grasp.templates.prepared import PreparedTemplate
from normpos_grasp.typing import BoolArray, FloatArray, IntArray

#: angle quantisation of the features and of alpha (pi / N_ANGLE and 2 pi / N_ALPHA radians)
N_ANGLE = 30
N_ALPHA = 30
#: most model pairs stored under one feature key
MAX_BUCKET = 24


@dataclass(frozen=True, eq=False)
class PPFModel:
    """Point-pair table of one template (object frame, metres).

    points / normals: (M, 3) model reference points and outward unit normals; step: distance quantum (metres);
    n_dist: distance bins; offsets: (K + 1,) CSR start of each key's pairs; pair_ref: (P,) first point of each
    pair; pair_alpha: (P,) alpha_m (radians); frames: (M, 4, 4) T_m (model point to origin, normal to +x).
    """

    points: FloatArray
    normals: FloatArray
    step: float
    diameter: float
    n_dist: int
    offsets: IntArray
    pair_ref: IntArray
    pair_alpha: FloatArray
    frames: FloatArray


def ppf_step(diameter: float) -> float:
    """The sampling step of a template of `diameter` metres: 5 % of it, at least 2.5 mm (scene noise)."""
    return max(0.05 * diameter, 0.0025)


_CACHE: weakref.WeakKeyDictionary[PreparedTemplate, PPFModel] = weakref.WeakKeyDictionary()
_LOCK = threading.Lock()


def ppf_model(prep: PreparedTemplate) -> PPFModel:
    """The (cached, per prepared template) `PPFModel`."""
    with _LOCK:
        hit = _CACHE.get(prep)
        if hit is None:
            hit = _CACHE[prep] = _build(prep)
        return hit


def _build(prep: PreparedTemplate) -> PPFModel:
    step = ppf_step(prep.diameter)
    keep = voxel_downsample(prep.samples, step)
    pts = np.ascontiguousarray(prep.samples[keep])
    nrm = np.ascontiguousarray(prep.normals[keep])
    n_dist = int(np.ceil(prep.diameter / step)) + 2
    keys, refs, alphas = _model_pairs(pts, nrm, step, prep.diameter * 1.01, n_dist, N_ANGLE)
    # flat and round surfaces put thousands of pairs under one key: they say little about the pose and would
    # dominate the voting time, so a key keeps at most MAX_BUCKET pairs (a seeded, evenly drawn subset)
    rng = np.random.default_rng(0)
    order = np.lexsort((rng.random(len(keys)), keys))
    ks = keys[order]
    first = np.searchsorted(ks, ks, side="left")
    order = order[np.arange(len(ks)) - first < MAX_BUCKET]
    keys = keys[order]
    n_keys = n_dist * N_ANGLE**3
    counts = np.bincount(keys, minlength=n_keys)
    offsets = np.zeros(n_keys + 1, dtype=np.int64)
    np.cumsum(counts, out=offsets[1:])
    frames = np.stack([_frame_to_x(p, n) for p, n in zip(pts, nrm, strict=True)])
    return PPFModel(pts, nrm, step, prep.diameter, n_dist, offsets, refs[order], alphas[order], frames)


def _frame_to_x(p: FloatArray, n: FloatArray) -> FloatArray:
    """(4, 4) rigid T with T p = 0 and R n = +x."""
    r = _rot_to_x(n[0], n[1], n[2])
    t = np.eye(4)
    t[:3, :3] = r
    t[:3, 3] = -r @ p
    return t


def frames_to_x(p: FloatArray, n: FloatArray) -> FloatArray:
    """(N, 4, 4) rigid T per point p (N, 3) with unit normal n (N, 3): T p = 0 and R n = +x (`_rot_to_x`, vectorised;
    the same matrices as `_frame_to_x` row by row)."""
    m = len(p)
    out = np.tile(np.eye(4), (m, 1, 1))
    if m == 0:
        return out
    c = n[:, 0]
    s = np.sqrt(n[:, 1] ** 2 + n[:, 2] ** 2)
    deg = s < 1e-9
    safe = np.where(deg, 1.0, s)
    k1, k2 = n[:, 2] / safe, -n[:, 1] / safe
    v = 1.0 - c
    r = out[:, :3, :3]
    r[:, 0, 0] = c
    r[:, 0, 1] = -k2 * s
    r[:, 0, 2] = k1 * s
    r[:, 1, 0] = k2 * s
    r[:, 1, 1] = c + k1 * k1 * v
    r[:, 1, 2] = k1 * k2 * v
    r[:, 2, 0] = -k1 * s
    r[:, 2, 1] = k1 * k2 * v
    r[:, 2, 2] = c + k2 * k2 * v
    if deg.any():  # n along +-x: identity, or a half turn about z for -x
        r[deg] = np.eye(3)
        flip = deg & (c < 0)
        r[flip, 0, 0] = -1.0
        r[flip, 1, 1] = -1.0
    out[:, :3, 3] = -np.einsum("nij,nj->ni", r, p)
    return out


@numba.njit(cache=True, nogil=True)
def _rot_to_x(n0, n1, n2):  # type: ignore[no-untyped-def]
    """(3, 3) rotation taking the unit vector n onto +x (about the axis n x x)."""
    r = np.eye(3)
    c = n0
    ax1, ax2 = n2, -n1  # n x x = (0, n2, -n1)
    s = np.sqrt(ax1 * ax1 + ax2 * ax2)
    if s < 1e-9:
        if c < 0:
            r[0, 0] = -1.0
            r[1, 1] = -1.0  # rotation by pi about z
        return r
    k1, k2 = ax1 / s, ax2 / s
    # Rodrigues with k = (0, k1, k2), angle with cos c, sin s
    v = 1.0 - c
    r[0, 0] = c
    r[0, 1] = -k2 * s
    r[0, 2] = k1 * s
    r[1, 0] = k2 * s
    r[1, 1] = c + k1 * k1 * v
    r[1, 2] = k1 * k2 * v
    r[2, 0] = -k1 * s
    r[2, 1] = k1 * k2 * v
    r[2, 2] = c + k2 * k2 * v
    return r


@numba.njit(cache=True, nogil=True)
def _key(d0, d1, d2, dist, n1, n2, step, n_dist, n_angle):  # type: ignore[no-untyped-def]
    """Quantised feature key of the pair (point 1 normal n1, point 2 normal n2, d = p2 - p1 of length dist)."""
    inv = 1.0 / dist
    u0, u1, u2 = d0 * inv, d1 * inv, d2 * inv
    c1 = min(max(n1[0] * u0 + n1[1] * u1 + n1[2] * u2, -1.0), 1.0)
    c2 = min(max(n2[0] * u0 + n2[1] * u1 + n2[2] * u2, -1.0), 1.0)
    c3 = min(max(n1[0] * n2[0] + n1[1] * n2[1] + n1[2] * n2[2], -1.0), 1.0)
    q = n_angle / np.pi
    a1 = min(int(np.arccos(c1) * q), n_angle - 1)
    a2 = min(int(np.arccos(c2) * q), n_angle - 1)
    a3 = min(int(np.arccos(c3) * q), n_angle - 1)
    qd = min(int(dist / step), n_dist - 1)
    return ((qd * n_angle + a1) * n_angle + a2) * n_angle + a3


@numba.njit(cache=True, nogil=True)
def _model_pairs(pts, nrm, step, max_d, n_dist, n_angle):  # type: ignore[no-untyped-def]
    m = pts.shape[0]
    cnt = 0
    for i in range(m):
        for j in range(m):
            if i != j:
                d0 = pts[j, 0] - pts[i, 0]
                d1 = pts[j, 1] - pts[i, 1]
                d2 = pts[j, 2] - pts[i, 2]
                dd = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
                if dd > 0.5 * step and dd <= max_d:
                    cnt += 1
    keys = np.empty(cnt, dtype=np.int64)
    refs = np.empty(cnt, dtype=np.int32)
    alphas = np.empty(cnt, dtype=np.float64)
    k = 0
    for i in range(m):
        r = _rot_to_x(nrm[i, 0], nrm[i, 1], nrm[i, 2])
        for j in range(m):
            if i == j:
                continue
            d0 = pts[j, 0] - pts[i, 0]
            d1 = pts[j, 1] - pts[i, 1]
            d2 = pts[j, 2] - pts[i, 2]
            dd = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
            if dd <= 0.5 * step or dd > max_d:
                continue
            keys[k] = _key(d0, d1, d2, dd, nrm[i], nrm[j], step, n_dist, n_angle)
            y = r[1, 0] * d0 + r[1, 1] * d1 + r[1, 2] * d2
            z = r[2, 0] * d0 + r[2, 1] * d1 + r[2, 2] * d2
            alphas[k] = np.arctan2(z, y)
            refs[k] = i
            k += 1
    return keys, refs, alphas


@numba.njit(cache=True, nogil=True)
def _vote(  # type: ignore[no-untyped-def]
    spts, snrm, ref_idx, offsets, pair_ref, pair_alpha, n_model, step, max_d, n_dist, n_angle, n_alpha, n_peaks
):
    """For each scene reference point: the `n_peaks` best (model point, alpha bin, votes) of its accumulator."""
    nr = ref_idx.shape[0]
    ns = spts.shape[0]
    out_m = np.full((nr, n_peaks), -1, dtype=np.int64)
    out_a = np.zeros((nr, n_peaks), dtype=np.int64)
    out_v = np.zeros((nr, n_peaks), dtype=np.int64)
    acc = np.zeros(n_model * n_alpha, dtype=np.int32)
    touched = np.empty(n_model * n_alpha, dtype=np.int64)
    two_pi = 2.0 * np.pi
    for q in range(nr):
        r_i = ref_idx[q]
        p0, p1, p2 = spts[r_i, 0], spts[r_i, 1], spts[r_i, 2]
        n1 = snrm[r_i]
        rot = _rot_to_x(n1[0], n1[1], n1[2])
        nt = 0
        for j in range(ns):
            if j == r_i:
                continue
            d0 = spts[j, 0] - p0
            d1 = spts[j, 1] - p1
            d2 = spts[j, 2] - p2
            dd = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
            if dd <= 0.5 * step or dd > max_d:
                continue
            key = _key(d0, d1, d2, dd, n1, snrm[j], step, n_dist, n_angle)
            lo, hi = offsets[key], offsets[key + 1]
            if lo == hi:
                continue
            y = rot[1, 0] * d0 + rot[1, 1] * d1 + rot[1, 2] * d2
            z = rot[2, 0] * d0 + rot[2, 1] * d1 + rot[2, 2] * d2
            a_s = np.arctan2(z, y)
            for k in range(lo, hi):
                a = a_s - pair_alpha[k]
                a = a - two_pi * np.floor(a / two_pi)
                ab = min(int(a / two_pi * n_alpha), n_alpha - 1)
                cell = pair_ref[k] * n_alpha + ab
                if acc[cell] == 0:
                    touched[nt] = cell
                    nt += 1
                acc[cell] += 1
        for t in range(nt):
            cell = touched[t]
            v = acc[cell]
            # insert into the per-reference top list (sorted descending)
            if v > out_v[q, n_peaks - 1]:
                pos = n_peaks - 1
                while pos > 0 and out_v[q, pos - 1] < v:
                    out_v[q, pos] = out_v[q, pos - 1]
                    out_m[q, pos] = out_m[q, pos - 1]
                    out_a[q, pos] = out_a[q, pos - 1]
                    pos -= 1
                out_v[q, pos] = v
                out_m[q, pos] = cell // n_alpha
                out_a[q, pos] = cell % n_alpha
        for t in range(nt):
            acc[touched[t]] = 0
    return out_m, out_a, out_v


def vote_poses(
    model: PPFModel,
    scene_points: FloatArray,
    scene_normals: FloatArray,
    ref_idx: IntArray,
    n_peaks: int = 2,
) -> tuple[FloatArray, FloatArray]:
    """Pose hypotheses of `model` in a scene cloud ((N, 3) points, (N, 3) unit normals facing the sensor).

    ref_idx: (R,) scene reference points. Returns (R * n_peaks, 4, 4) scene_from_object poses and their (R *
    n_peaks,) votes (0 where a reference point had fewer peaks).
    """
    spts = np.ascontiguousarray(scene_points, dtype=np.float64)
    snrm = np.ascontiguousarray(scene_normals, dtype=np.float64)
    refs = np.ascontiguousarray(ref_idx, dtype=np.int64)
    if len(refs) == 0 or len(spts) < 3:
        return np.zeros((0, 4, 4)), np.zeros(0)
    out_m, out_a, out_v = _vote(
        spts,
        snrm,
        refs,
        model.offsets,
        model.pair_ref,
        model.pair_alpha,
        len(model.points),
        model.step,
        model.diameter * 1.01,
        model.n_dist,
        N_ANGLE,
        N_ALPHA,
        n_peaks,
    )
    ok = out_m.reshape(-1) >= 0
    ref_rep = np.repeat(refs, n_peaks)[ok]
    mi = out_m.reshape(-1)[ok]
    alpha = (out_a.reshape(-1)[ok] + 0.5) * (2.0 * np.pi / N_ALPHA)
    votes = out_v.reshape(-1)[ok].astype(np.float64)
    # T_s: scene reference point to the origin, its normal to +x
    ts = frames_to_x(spts[ref_rep], snrm[ref_rep])
    rx = np.tile(np.eye(4), (len(alpha), 1, 1))
    c, s = np.cos(alpha), np.sin(alpha)
    rx[:, 1, 1], rx[:, 1, 2], rx[:, 2, 1], rx[:, 2, 2] = c, -s, s, c
    ts_inv = np.tile(np.eye(4), (len(ts), 1, 1))
    ts_inv[:, :3, :3] = np.transpose(ts[:, :3, :3], (0, 2, 1))
    ts_inv[:, :3, 3] = -np.einsum("nji,nj->ni", ts[:, :3, :3], ts[:, :3, 3])
    poses = ts_inv @ rx @ model.frames[mi]
    return poses, votes


def cluster_poses(
    poses: FloatArray,
    votes: FloatArray,
    centroid: FloatArray,
    dist_m: float,
    angle_rad: float,
    n_max: int,
    symmetries: FloatArray | None = None,
) -> tuple[FloatArray, FloatArray]:
    """Greedy pose clustering (highest votes first): each unassigned pose with the most votes gathers the
    unassigned poses whose posed object `centroid` lies within `dist_m` (metres) and whose rotation differs by
    less than `angle_rad` from it or from one of its symmetric copies (`symmetries`, (M, 4, 4) object_from_object;
    the votes of a symmetric part spread over its equivalent poses); clusters are scored by their summed votes and
    represented by their best pose. Returns the `n_max` best (K, 4, 4) poses and (K,) cluster votes."""
    order = np.argsort(-votes, kind="stable")
    order = order[votes[order] > 0]
    if len(order) == 0:
        return np.zeros((0, 4, 4)), np.zeros(0)
    p = poses[order]
    v = votes[order]
    centres = p[:, :3, :3] @ centroid + p[:, :3, 3]
    rot = p[:, :3, :3].reshape(len(p), 9)
    sym_r = np.eye(3)[None] if symmetries is None or len(symmetries) == 0 else symmetries[:, :3, :3]
    free = np.ones(len(p), dtype=bool)
    cos_lim = 1.0 + 2.0 * np.cos(angle_rad)  # trace(Ra Rb^T) above this: closer than angle_rad
    reps: list[int] = []
    total: list[float] = []
    for i in range(len(p)):
        if not free[i]:
            continue
        cand = np.flatnonzero(free)
        near = np.linalg.norm(centres[cand] - centres[i], axis=1) < dist_m
        cand = cand[near]
        equiv = (p[i, :3, :3] @ sym_r).reshape(-1, 9)  # (M, 9) the rotation's symmetric copies
        near = np.max(rot[cand] @ equiv.T, axis=1) > cos_lim
        members = cand[near]
        free[members] = False
        free[i] = False
        reps.append(i)
        total.append(float(v[members].sum()) + (0.0 if i in members else float(v[i])))
        if len(reps) >= 4 * n_max:
            break
    tv = np.asarray(total)
    best = np.argsort(-tv, kind="stable")[:n_max]
    return p[np.asarray(reps)[best]], tv[best]


def scene_references(n: int, every: int) -> IntArray:
    """Every `every`-th scene point as a reference point."""
    return np.arange(0, n, max(1, every), dtype=np.int64)


@numba.njit(cache=True, nogil=True)
def _score_poses(poses, pts, nrm, depth, inside, fx, fy, cx, cy, tol_m, noise_per_m2):  # type: ignore[no-untyped-def]
    """Per pose (K, 4, 4) camera_from_object: counts over the model points (M, 3) with normals (M, 3) that face the
    camera: (supported inside the region, supported outside it, seen through, visible)."""
    k_n = poses.shape[0]
    hgt, wid = depth.shape
    out = np.zeros((k_n, 4), dtype=np.int64)
    for k in range(k_n):
        r = poses[k]
        n_in = n_out = n_see = n_vis = 0
        for i in range(pts.shape[0]):
            x = r[0, 0] * pts[i, 0] + r[0, 1] * pts[i, 1] + r[0, 2] * pts[i, 2] + r[0, 3]
            y = r[1, 0] * pts[i, 0] + r[1, 1] * pts[i, 1] + r[1, 2] * pts[i, 2] + r[1, 3]
            z = r[2, 0] * pts[i, 0] + r[2, 1] * pts[i, 1] + r[2, 2] * pts[i, 2] + r[2, 3]
            if z <= 0.05:
                continue
            nx = r[0, 0] * nrm[i, 0] + r[0, 1] * nrm[i, 1] + r[0, 2] * nrm[i, 2]
            ny = r[1, 0] * nrm[i, 0] + r[1, 1] * nrm[i, 1] + r[1, 2] * nrm[i, 2]
            nz = r[2, 0] * nrm[i, 0] + r[2, 1] * nrm[i, 1] + r[2, 2] * nrm[i, 2]
            if nx * x + ny * y + nz * z >= 0.0:
                continue  # faces away from the camera
            u = int(fx * x / z + cx + 0.5)
            v = int(fy * y / z + cy + 0.5)
            if u < 0 or u >= wid or v < 0 or v >= hgt:
                continue
            n_vis += 1
            meas = depth[v, u]
            if not (meas > 0.0):
                continue
            tol = tol_m + 2.5 * noise_per_m2 * z * z
            diff = meas - z
            if abs(diff) <= tol:
                if inside[v, u]:
                    n_in += 1
                else:
                    n_out += 1
            elif diff > max(3.0 * tol, 0.01):
                n_see += 1
        out[k, 0] = n_in
        out[k, 1] = n_out
        out[k, 2] = n_see
        out[k, 3] = n_vis
    return out


def depth_counts(
    points: FloatArray,
    normals: FloatArray,
    poses: FloatArray,
    depth: FloatArray,
    inside: BoolArray,
    k: FloatArray,
    tol_m: float,
    noise_per_m2: float,
) -> IntArray:
    """(K, 4) counts per (K, 4, 4) camera_from_object pose over the object-frame points (M, 3) with outward normals
    (M, 3) that face the camera and project into the (H, W) depth image (metres; intrinsics k (3, 3), no
    distortion): those whose pixel's depth agrees (within tol_m + 2.5 x noise_per_m2 x z^2) and lies inside the region
    (`inside`, (H, W) bool), those agreeing outside it, those the sensor sees through (depth more than 3 tol, at least
    1 cm, behind them), and all of them. Visibility is back-face culling (no self-occlusion)."""
    if len(poses) == 0:
        return np.zeros((0, 4), dtype=np.int64)
    return np.asarray(
        _score_poses(
            np.ascontiguousarray(poses, dtype=np.float64),
            np.ascontiguousarray(points, dtype=np.float64),
            np.ascontiguousarray(normals, dtype=np.float64),
            np.ascontiguousarray(depth, dtype=np.float64),
            np.ascontiguousarray(inside, dtype=np.bool_),
            float(k[0, 0]),
            float(k[1, 1]),
            float(k[0, 2]),
            float(k[1, 2]),
            float(tol_m),
            float(noise_per_m2),
        )
    )


def depth_scores(
    model: PPFModel,
    poses: FloatArray,
    depth: FloatArray,
    inside: BoolArray,
    k: FloatArray,
    tol_m: float,
    noise_per_m2: float,
) -> FloatArray:
    """Cheap depth-image evidence of (K, 4, 4) camera_from_object poses on the model's points, (K,) in model points:
    visible points whose pixel's depth agrees (within tol_m + 2.5 x the noise at their range) and lies inside the
    region (`inside`, (H, W) bool: the residual ROI), minus those agreeing with depth outside it (the support plane,
    claimed parts), minus 3 x those the sensor sees through (`depth_counts`)."""
    c = depth_counts(model.points, model.normals, poses, depth, inside, k, tol_m, noise_per_m2)
    return np.asarray(c[:, 0] - c[:, 1] - 3.0 * c[:, 2], dtype=np.float64)


def nms_poses(
    poses: FloatArray,
    scores: FloatArray,
    centroid: FloatArray,
    dist_m: float,
    angle_rad: float,
    n_max: int,
    symmetries: FloatArray | None = None,
    per_place: int = 0,
    place_m: float = 0.0,
) -> tuple[FloatArray, FloatArray]:
    """Greedy non-maximum suppression, best score first: a pose is dropped when a kept one has its posed `centroid`
    within `dist_m` and its rotation within `angle_rad` (up to `symmetries`, (M, 4, 4)), or, with `per_place` > 0,
    when `per_place` kept ones have their centroids within `place_m` of its (whatever their rotation: one place of
    the scene does not take the whole budget). Returns the `n_max` best (K, 4, 4) poses and their (K,) scores
    (scores <= 0 are not kept)."""
    order = np.argsort(-scores, kind="stable")
    order = order[scores[order] > 0]
    if len(order) == 0:
        return np.zeros((0, 4, 4)), np.zeros(0)
    p = poses[order]
    centres = p[:, :3, :3] @ centroid + p[:, :3, 3]
    rot = p[:, :3, :3].reshape(len(p), 9)
    sym_r = np.eye(3)[None] if symmetries is None or len(symmetries) == 0 else symmetries[:, :3, :3]
    cos_lim = 1.0 + 2.0 * np.cos(angle_rad)
    kept: list[int] = []
    for i in range(len(p)):
        if kept:
            kk = np.asarray(kept)
            dc = np.linalg.norm(centres[kk] - centres[i], axis=1)
            if per_place > 0 and int(np.count_nonzero(dc < place_m)) >= per_place:
                continue
            near = dc < dist_m
            if near.any():
                equiv = (p[i, :3, :3] @ sym_r).reshape(-1, 9)
                if np.any(np.max(rot[kk[near]] @ equiv.T, axis=1) > cos_lim):
                    continue
        kept.append(i)
        if len(kept) >= n_max:
            break
    ki = np.asarray(kept)
    return p[ki], scores[order][ki]


@numba.njit(cache=True, nogil=True)
def _explained_box(  # type: ignore[no-untyped-def]
    pmap, allowed, box, ofc, scale, centroid, r_obj, bound, tol_m, noise_per_m2, samples, kd
):
    """Row-major flat indices of the `allowed` pixels in box (v0, v1, u0, u1) whose point (pmap, camera frame)
    ofc (object_from_camera) puts within r_obj of the centroid and within tol_m + 2.5 noise_per_m2 z^2 (scaled)
    of the nearest sample (exact, the flat KD-tree of all samples), nearer than `bound` (object frame, metres)."""
    dim, split, left, right, start, end, perm, roots = kd
    wid = pmap.shape[1]
    v0, v1, u0, u1 = box[0], box[1], box[2], box[3]
    out = np.empty(max((v1 - v0) * (u1 - u0), 0), dtype=np.int64)
    stack_n = np.empty(128, dtype=np.int64)
    stack_b = np.empty(128)
    n = 0
    for v in range(v0, v1):
        for u in range(u0, u1):
            if not allowed[v, u]:
                continue
            x = pmap[v, u, 0]
            y = pmap[v, u, 1]
            z = pmap[v, u, 2]
            q0 = (ofc[0, 0] * x + ofc[0, 1] * y + ofc[0, 2] * z + ofc[0, 3]) / scale
            q1 = (ofc[1, 0] * x + ofc[1, 1] * y + ofc[1, 2] * z + ofc[1, 3]) / scale
            q2 = (ofc[2, 0] * x + ofc[2, 1] * y + ofc[2, 2] * z + ofc[2, 3]) / scale
            a = q0 - centroid[0]
            b = q1 - centroid[1]
            c = q2 - centroid[2]
            if not (a * a + b * b + c * c < r_obj * r_obj):
                continue
            # the search starts from the pixel's own tolerance (a far pixel is rejected near the root)
            lim = min(bound, (tol_m + 2.5 * noise_per_m2 * z * z) / scale)
            d2, near = kernels._kd_nearest(
                q0,
                q1,
                q2,
                roots[0],
                samples,
                dim,
                split,
                left,
                right,
                start,
                end,
                perm,
                lim * lim,
                -1,
                stack_n,
                stack_b,
            )
            if near >= 0 and d2 < bound * bound and math.sqrt(d2) * scale < tol_m + 2.5 * noise_per_m2 * z * z:
                out[n] = v * wid + u
                n += 1
    return out[:n]


def explained_pixels(
    pmap: FloatArray,
    allowed: BoolArray,
    box: tuple[int, int, int, int],
    object_from_camera: FloatArray,
    scale: float,
    prep: PreparedTemplate,
    r_obj: float,
    bound: float,
    tol_m: float,
    noise_per_m2: float,
) -> IntArray:
    """Flat indices (row-major over pmap (H, W, 3), camera frame, metres) of the `allowed` (H, W) pixels inside box
    (v0, v1, u0, u1) that the pose explains: within r_obj (object frame) of the template's centroid and nearer to
    its surface samples than tol_m + 2.5 x noise_per_m2 x z^2 (metres, after scaling) and than `bound` (object
    frame). Compiled; the same rule as a KD-tree query per pixel."""
    return np.asarray(
        _explained_box(
            pmap,
            allowed,
            np.asarray(box, dtype=np.int64),
            np.ascontiguousarray(object_from_camera, dtype=np.float64),
            float(scale),
            np.asarray(prep.centroid, dtype=np.float64),
            float(r_obj),
            float(bound),
            float(tol_m),
            float(noise_per_m2),
            prep.samples,
            prep.kd,
        ),
        dtype=np.int64,
    )
