"""Closed-form inverse kinematics of UR arms (nominal DH structure), scalar and vectorised.

The eight solutions are indexed 4 * shoulder + 2 * wrist + elbow, each bit 0 for the '+' branch:
shoulder: q1 = psi + pi/2 +- phi, wrist: q5 = +-acos(.), elbow: q3 = +-acos(.). Angles come in (-pi, pi].
At a wrist singularity (|sin q5| < `SINGULAR_SIN`) q6 is free: it takes the caller's `q6_default` and q4
absorbs the rest, which reproduces the pose exactly. Derivation: K. Hawkins, "Analytic inverse kinematics
for the Universal Robots UR-5/UR-10 arms" (2013), rewritten for the standard DH table in ur_params.py.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from normpos_grasp.kinematics.ur_params import URParams
from normpos_grasp.typing import BoolArray, FloatArray

SINGULAR_SIN = 1e-6  # below this |sin q5| the q6 from atan2 is noise (c5 carries ~1e-14 round-off)
# Slack on the acos arguments so poses exactly on a workspace boundary are not lost to round-off.
ACOS_SLACK = 1e-8
_TWO_PI = 2.0 * math.pi

# Branch signs per solution index: (shoulder, wrist, elbow), +1 or -1.
BRANCH_SIGNS = tuple((1 - 2 * (i >> 2), 1 - 2 * ((i >> 1) & 1), 1 - 2 * (i & 1)) for i in range(8))


def dh_lengths(params: URParams) -> tuple[float, float, float, float, float, float]:
    """(d1, a2, a3, d4, d5, d6) of a UR model, metres."""
    return (params.d[0], params.a[1], params.a[2], params.d[3], params.d[4], params.d[5])


def _acos(x: float, slack: float = ACOS_SLACK) -> float | None:
    if x > 1.0 + slack or x < -1.0 - slack:
        return None
    return math.acos(min(1.0, max(-1.0, x)))


def ik_single(
    lengths: tuple[float, float, float, float, float, float],
    pose: list[list[float]],
    q6_default: float = 0.0,
    slack: float = ACOS_SLACK,
) -> tuple[list[tuple[float, ...] | None], str]:
    """The 8 closed-form solutions of one base_from_flange pose (nested lists, 4x4), scalar math.

    `slack`: acos arguments up to 1 + slack are clamped (larger values give approximate seeds for targets
    just outside the nominal workspace, e.g. for a calibrated arm).

    Returns (solutions, reason): solutions[i] is a 6-tuple of radians or None where branch i has no
    solution; reason is '' when some solution exists, else 'out_of_reach'.
    """
    d1, a2, a3, d4, d5, d6 = lengths
    (nx, ox, ax, px), (ny, oy, ay, py), (nz, oz, az, pz) = pose[0], pose[1], pose[2]
    p05x, p05y = px - d6 * ax, py - d6 * ay
    r = math.hypot(p05x, p05y)
    out: list[tuple[float, ...] | None] = [None] * 8
    if r <= 0.0:
        return out, "out_of_reach"
    phi = _acos(d4 / r, slack)
    if phi is None:
        return out, "out_of_reach"
    base = math.atan2(p05x, -p05y)
    inv_a2a3 = 1.0 / (2.0 * a2 * a3)
    aa = a2 * a2 + a3 * a3
    hi, lo = 1.0 + slack, -1.0 - slack
    pz_ = pz - d1 - d6 * az
    for si in range(2):
        t1 = math.remainder(base + phi if si == 0 else base - phi, _TWO_PI)
        c1, s1 = math.cos(t1), math.sin(t1)
        c5 = (px * s1 - py * c1 - d4) / d6
        if c5 > hi or c5 < lo:
            continue
        c5 = min(1.0, max(-1.0, c5))
        t5a = math.acos(c5)
        s5a = math.sqrt(1.0 - c5 * c5)
        n_c = nx * c1 + ny * s1
        o_c = ox * c1 + oy * s1
        a_c = ax * c1 + ay * s1
        num6 = oy * c1 - ox * s1
        den6 = nx * s1 - ny * c1
        pxy = px * c1 + py * s1 - d6 * a_c
        for wi in range(2):
            t5, s5 = (t5a, s5a) if wi == 0 else (-t5a, -s5a)
            if s5a < SINGULAR_SIN:
                t6 = q6_default
            else:
                t6 = math.atan2(num6, den6) if wi == 0 else math.atan2(-num6, -den6)
            c6, s6 = math.cos(t6), math.sin(t6)
            x04x = -s5 * a_c - c5 * (s6 * o_c - c6 * n_c)
            x04y = c5 * (nz * c6 - oz * s6) - az * s5
            t234 = math.atan2(x04y, x04x)
            p13x = d5 * (s6 * n_c + c6 * o_c) + pxy
            p13y = pz_ + d5 * (oz * c6 + nz * s6)
            c3 = (p13x * p13x + p13y * p13y - aa) * inv_a2a3
            if c3 > hi or c3 < lo:
                continue
            c3 = min(1.0, max(-1.0, c3))
            t3a = math.acos(c3)
            s3a = math.sqrt(1.0 - c3 * c3)
            aa_ = a2 + a3 * c3
            for ei in range(2):
                t3, bb = (t3a, a3 * s3a) if ei == 0 else (-t3a, -a3 * s3a)
                t2 = math.atan2(aa_ * p13y - bb * p13x, aa_ * p13x + bb * p13y)
                t4 = math.remainder(t234 - t2 - t3, _TWO_PI)
                out[4 * si + 2 * wi + ei] = (t1, t2, t3, t4, t5, t6)
    return out, ("" if any(s is not None for s in out) else "out_of_reach")


def ik_batch(
    lengths: tuple[float, float, float, float, float, float], poses: FloatArray, q6_default: FloatArray | float = 0.0
) -> tuple[FloatArray, BoolArray]:
    """Vectorised closed form for poses (N, 4, 4): returns q (N, 8, 6) radians and valid (N, 8).

    Invalid entries of q are NaN. `q6_default` (scalar or (N,)) is used for q6 at wrist singularities.
    """
    d1, a2, a3, d4, d5, d6 = lengths
    t = np.asarray(poses, dtype=np.float64)
    n = t.shape[0]
    nx, ny, nz = t[:, 0, 0, None], t[:, 1, 0, None], t[:, 2, 0, None]
    ox, oy, oz = t[:, 0, 1, None], t[:, 1, 1, None], t[:, 2, 1, None]
    ax, ay, az = t[:, 0, 2, None], t[:, 1, 2, None], t[:, 2, 2, None]
    px, py, pz = t[:, 0, 3, None], t[:, 1, 3, None], t[:, 2, 3, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        p05x = px - d6 * ax
        p05y = py - d6 * ay
        ratio = d4 / np.hypot(p05x, p05y)  # (N, 1)
        ok1 = ratio <= 1.0 + ACOS_SLACK
        phi = np.arccos(np.minimum(ratio, 1.0))
        t1 = np.arctan2(p05x, -p05y) + np.concatenate([phi, -phi], axis=1)  # (N, 2)
        t1 = t1 - _TWO_PI * np.round(t1 / _TWO_PI)
        c1, s1 = np.cos(t1), np.sin(t1)
        c5a = (px * s1 - py * c1 - d4) / d6  # (N, 2)
        ok5 = np.abs(c5a) <= 1.0 + ACOS_SLACK
        c5h = np.clip(c5a, -1.0, 1.0)
        t5a = np.arccos(c5h)
        s5a = np.sqrt(1.0 - c5h * c5h)  # sin of +t5a (>= 0); the other wrist branch has -s5a
        t5 = np.stack([t5a, -t5a], axis=2)  # (N, 2, 2)
        s5 = np.stack([s5a, -s5a], axis=2)
        c5 = c5h[:, :, None]
        num6 = (oy * c1 - ox * s1)[:, :, None]
        den6 = (nx * s1 - ny * c1)[:, :, None]
        sgn = np.array([1.0, -1.0])
        t6 = np.arctan2(sgn * num6, sgn * den6)  # (N, 2, 2)
        singular = s5a < SINGULAR_SIN
        if np.any(singular):
            q6d = np.broadcast_to(np.asarray(q6_default, dtype=np.float64).reshape(-1, 1, 1), (n, 2, 2))
            t6 = np.where(singular[:, :, None], q6d, t6)
        c6, s6 = np.cos(t6), np.sin(t6)
        c1e, s1e = c1[:, :, None], s1[:, :, None]
        n_c = nx[:, :, None] * c1e + ny[:, :, None] * s1e
        o_c = ox[:, :, None] * c1e + oy[:, :, None] * s1e
        a_c = ax[:, :, None] * c1e + ay[:, :, None] * s1e
        x04x = -s5 * a_c - c5 * (s6 * o_c - c6 * n_c)
        x04y = c5 * (nz[:, :, None] * c6 - oz[:, :, None] * s6) - az[:, :, None] * s5
        t234 = np.arctan2(x04y, x04x)[..., None]
        p13x = d5 * (s6 * n_c + c6 * o_c) - d6 * a_c + px[:, :, None] * c1e + py[:, :, None] * s1e
        p13y = (pz - d1 - d6 * az)[:, :, None] + d5 * (oz[:, :, None] * c6 + nz[:, :, None] * s6)
        c3a = (p13x * p13x + p13y * p13y - (a2 * a2 + a3 * a3)) / (2.0 * a2 * a3)  # (N, 2, 2)
        ok3 = np.abs(c3a) <= 1.0 + ACOS_SLACK
        c3h = np.clip(c3a, -1.0, 1.0)
        t3a = np.arccos(c3h)
        t3 = np.stack([t3a, -t3a], axis=3)  # (N, 2, 2, 2)
        bb_a = a3 * np.sqrt(1.0 - c3h * c3h)
        bb = np.stack([bb_a, -bb_a], axis=3)  # a3 sin(t3)
        aa = (a2 + a3 * c3h)[..., None]
        p13x, p13y = p13x[..., None], p13y[..., None]
        t2 = np.arctan2(aa * p13y - bb * p13x, aa * p13x + bb * p13y)
        t4 = t234 - t2 - t3
        t4 -= _TWO_PI * np.round(t4 / _TWO_PI)
    valid = (ok1[:, :, None, None] & ok5[:, :, None, None] & ok3[..., None]) & np.ones((1, 1, 1, 2), dtype=bool)
    shape = (n, 2, 2, 2)
    q5d = np.empty((n, 2, 2, 2, 6))
    q5d[..., 0] = np.broadcast_to(t1[:, :, None, None], shape)
    q5d[..., 1] = t2
    q5d[..., 2] = t3
    q5d[..., 3] = t4
    q5d[..., 4] = np.broadcast_to(t5[..., None], shape)
    q5d[..., 5] = np.broadcast_to(t6[..., None], shape)
    valid = valid.reshape(n, 8)
    q = q5d.reshape(n, 8, 6)
    q[~valid] = np.nan
    return q, valid


# -- compiled single-pose solve (nominal model): closed form, +-2 pi copies inside the limits, sorted ------------------

FAST_OK, FAST_POLISH, FAST_BAD_POSE, FAST_BAD_NEAR = 0, 1, 2, 3
SINGULAR_NEAR = 1e-5  # |sin| (or shoulder angle, rad) below which closed-form solutions get Newton-polished


@njit(cache=True, nogil=True, inline="always")
def _remainder_2pi(x: float) -> float:
    """math.remainder(x, 2 pi) (numba has no math.remainder): exact for |x| <= 4 pi (Sterbenz), ties to even."""
    half = 0.5 * _TWO_PI
    if -half <= x <= half:
        return x
    n = np.rint(x / _TWO_PI)
    r = x - n * _TWO_PI
    if r > half or (r == half and n % 2.0 != 0.0):
        r -= _TWO_PI
    elif r < -half or (r == -half and n % 2.0 != 0.0):
        r += _TWO_PI
    return r


@njit(cache=True, nogil=True)
def ik_solve_nominal(
    lengths: FloatArray, pose: FloatArray, near: FloatArray, upper: FloatArray, all_branches: bool
) -> tuple[FloatArray, int]:  # pragma: no cover - compiled; its Python twin is Robot._ik_python
    """`Robot.ik` of the nominal model for one pose, compiled: lengths (6,) = dh_lengths, pose (4, 4)
    base_from_flange, near (6,) radians (zeros for none), upper (6,) symmetric position limits with every
    finite limit below 3 pi (inf: unlimited).

    Returns (q (k, 6), status). FAST_OK: q are the solutions inside the limits sorted by squared joint distance
    to `near` (stable, in the order of the Python path), every +-2 pi copy when all_branches, else each joint's
    nearest copy. FAST_POLISH: a solution lies within 1e-5 of a shoulder, elbow or wrist singularity (the
    caller Newton-polishes); FAST_BAD_POSE / FAST_BAD_NEAR: non-finite or improper input (the caller raises).
    """
    empty = np.empty((0, 6))
    for i in range(4):
        for j in range(4):
            if not math.isfinite(pose[i, j]):
                return empty, FAST_BAD_POSE
    for j in range(6):
        if not math.isfinite(near[j]):
            return empty, FAST_BAD_NEAR
    nx, ox, ax, px = pose[0, 0], pose[0, 1], pose[0, 2], pose[0, 3]
    ny, oy, ay, py = pose[1, 0], pose[1, 1], pose[1, 2], pose[1, 3]
    nz, oz, az, pz = pose[2, 0], pose[2, 1], pose[2, 2], pose[2, 3]
    err = max(
        abs(nx * nx + ny * ny + nz * nz - 1.0),
        abs(ox * ox + oy * oy + oz * oz - 1.0),
        abs(nx * ox + ny * oy + nz * oz),
        abs(ny * oz - nz * oy - ax),
        abs(nz * ox - nx * oz - ay),
        abs(nx * oy - ny * ox - az),
    )
    if err > 1e-6 or pose[3, 0] != 0.0 or pose[3, 1] != 0.0 or pose[3, 2] != 0.0 or pose[3, 3] != 1.0:
        return empty, FAST_BAD_POSE
    d1, a2, a3, d4, d5, d6 = lengths[0], lengths[1], lengths[2], lengths[3], lengths[4], lengths[5]
    q6_default = near[5]
    principal = np.empty((8, 6))
    k = 0
    p05x, p05y = px - d6 * ax, py - d6 * ay
    r = math.hypot(p05x, p05y)
    if r <= 0.0 or d4 / r > 1.0 + ACOS_SLACK or d4 / r < -1.0 - ACOS_SLACK:
        return empty, FAST_OK  # out of reach
    phi = math.acos(min(1.0, max(-1.0, d4 / r)))
    polish = math.acos(min(1.0, d4 / r)) < SINGULAR_NEAR
    base = math.atan2(p05x, -p05y)
    inv_a2a3 = 1.0 / (2.0 * a2 * a3)
    aa = a2 * a2 + a3 * a3
    hi, lo = 1.0 + ACOS_SLACK, -1.0 - ACOS_SLACK
    pz_ = pz - d1 - d6 * az
    for si in range(2):
        t1 = _remainder_2pi(base + phi if si == 0 else base - phi)
        c1, s1 = math.cos(t1), math.sin(t1)
        c5 = (px * s1 - py * c1 - d4) / d6
        if c5 > hi or c5 < lo:
            continue
        c5 = min(1.0, max(-1.0, c5))
        t5a = math.acos(c5)
        s5a = math.sqrt(1.0 - c5 * c5)
        n_c = nx * c1 + ny * s1
        o_c = ox * c1 + oy * s1
        a_c = ax * c1 + ay * s1
        num6 = oy * c1 - ox * s1
        den6 = nx * s1 - ny * c1
        pxy = px * c1 + py * s1 - d6 * a_c
        for wi in range(2):
            t5, s5 = (t5a, s5a) if wi == 0 else (-t5a, -s5a)
            if s5a < SINGULAR_SIN:
                t6 = q6_default
            else:
                t6 = math.atan2(num6, den6) if wi == 0 else math.atan2(-num6, -den6)
            c6, s6 = math.cos(t6), math.sin(t6)
            x04x = -s5 * a_c - c5 * (s6 * o_c - c6 * n_c)
            x04y = c5 * (nz * c6 - oz * s6) - az * s5
            t234 = math.atan2(x04y, x04x)
            p13x = d5 * (s6 * n_c + c6 * o_c) + pxy
            p13y = pz_ + d5 * (oz * c6 + nz * s6)
            c3 = (p13x * p13x + p13y * p13y - aa) * inv_a2a3
            if c3 > hi or c3 < lo:
                continue
            c3 = min(1.0, max(-1.0, c3))
            t3a = math.acos(c3)
            s3a = math.sqrt(1.0 - c3 * c3)
            aa_ = a2 + a3 * c3
            for ei in range(2):
                t3, bb = (t3a, a3 * s3a) if ei == 0 else (-t3a, -a3 * s3a)
                t2 = math.atan2(aa_ * p13y - bb * p13x, aa_ * p13x + bb * p13y)
                t4 = _remainder_2pi(t234 - t2 - t3)
                if abs(math.sin(t3)) < SINGULAR_NEAR or abs(math.sin(t5)) < SINGULAR_NEAR:
                    polish = True
                principal[k, 0], principal[k, 1], principal[k, 2] = t1, t2, t3
                principal[k, 3], principal[k, 4], principal[k, 5] = t4, t5, t6
                k += 1
    if k > 0 and polish:
        return empty, FAST_POLISH
    # branch joints: finite limits above pi (one extra copy each, limits < 3 pi); unlimited joints go near `near`
    jj = np.empty(6, dtype=np.int64)
    m = 0
    for j in range(6):
        if math.isfinite(upper[j]) and upper[j] > math.pi:
            jj[m] = j
            m += 1
    n_bits = 1 << m if all_branches else 1
    rows = np.empty((k * n_bits, 6))
    dist = np.empty(k * n_bits)
    n = 0
    alt = np.empty(6)
    for s in range(k):
        q = principal[s].copy()
        ok = True
        for j in range(6):
            if not math.isfinite(upper[j]):
                q[j] += _TWO_PI * np.rint((near[j] - q[j]) / _TWO_PI)
            elif abs(q[j]) > upper[j]:
                ok = False
        if all_branches:
            if not ok:
                continue
            for b in range(m):
                j = jj[b]
                alt[b] = q[j] - math.copysign(_TWO_PI, q[j])
            for c in range(n_bits):  # itertools.product order: the first branch joint is the top bit
                valid = True
                for b in range(m):
                    if (c >> (m - 1 - b)) & 1 and abs(alt[b]) > upper[jj[b]]:
                        valid = False
                        break
                if not valid:
                    continue
                rows[n] = q
                for b in range(m):
                    if (c >> (m - 1 - b)) & 1:
                        rows[n, jj[b]] = alt[b]
                n += 1
        else:
            ok = True
            for j in range(6):
                v, lim, rj = principal[s, j], upper[j], near[j]
                if not math.isfinite(lim):
                    v = q[j]
                elif lim > math.pi:
                    a = v - math.copysign(_TWO_PI, v)
                    if abs(a) <= lim and abs(a - rj) < abs(v - rj):
                        v = a
                if abs(v) > lim:
                    ok = False
                    break
                rows[n, j] = v
            if ok:
                n += 1
    for i in range(n):
        acc = 0.0
        for j in range(6):
            e = rows[i, j] - near[j]
            acc += e * e
        dist[i] = acc
    order = np.argsort(dist[:n], kind="mergesort")
    out = np.empty((n, 6))
    for i in range(n):
        out[i] = rows[order[i]]
    return out, FAST_OK
