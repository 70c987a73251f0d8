"""Compiled (numba, nogil) inner loops of the template fitter: correspondences, batched ICP, scoring helpers.

The kernels keep the numpy implementation's semantics (same correspondence rules, gates, trimming, weights,
normal equations and pose update) but run one hypothesis at a time without temporary arrays, and release the
GIL so that several objects can be fitted in parallel threads (`fit.fit_many`).

Shared arguments (built once per template in `prepared.PreparedTemplate`):
    samples, normals: (S, 3) float64 template surface points and unit outward normals (object frame, metres).
    grid: (origin (3,), [cell, pad] (2,), cells (G, G, G, 8) int16/int32, cand_start (G^3 + 1,), cand_idx (C,)
        int32, cell_dist (G^3,) distance of each cell centre to its nearest sample, sample_bin (S,) normal bins):
        the distance grid (per cell: nearest sample, then the nearest of each normal bin, -1 where a bin has no
        sample; one cache line per cell) and, for cells near the surface, every sample that can be the exact
        nearest one of a point in the cell (cand_idx[cand_start[c]:cand_start[c + 1]], c = (i G + j) G + k;
        empty elsewhere).
    kd: (dim, split, left, right, start, end, perm, roots): flat arrays of 7 KD-trees over the samples
        (all samples, then one per normal bin; roots (7,) with -1 for an empty bin); leaves hold
        perm[start:end] (sample indices).
Compiled on first use and cached on disk (`cache=True`): about 25 s CPU once per installation, then ~0.2 s.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from normpos_grasp.typing import FloatArray, IntArray

NORMAL_COS = 0.35
LEAF_SIZE = 8
_STACK = 128


# -- KD-tree (built in numpy, queried in numba) -------------------------------------------------------------------


def build_kdtrees(samples: FloatArray, groups: list[IntArray]) -> tuple[np.ndarray, ...]:
    """Flat KD-trees over `samples` (S, 3), one per index group; returns the `kd` tuple described above."""
    dim: list[int] = []
    split: list[float] = []
    left: list[int] = []
    right: list[int] = []
    start: list[int] = []
    end: list[int] = []
    perm: list[np.ndarray] = []
    roots = np.full(len(groups), -1, dtype=np.int64)
    offset = 0
    for g, members in enumerate(groups):
        members = np.asarray(members, dtype=np.int64)
        if len(members) == 0:
            continue
        order = members.copy()
        roots[g] = len(dim)
        # iterative build: (node, lo, hi) ranges into `order`
        dim.append(0)
        split.append(0.0)
        left.append(-1)
        right.append(-1)
        start.append(0)
        end.append(0)
        todo = [(roots[g], 0, len(order))]
        while todo:
            node, lo, hi = todo.pop()
            idx = order[lo:hi]
            if hi - lo <= LEAF_SIZE:
                start[node] = offset + lo
                end[node] = offset + hi
                continue
            pts = samples[idx]
            ax = int(np.argmax(pts.max(0) - pts.min(0)))
            srt = idx[np.argsort(pts[:, ax], kind="stable")]
            order[lo:hi] = srt
            mid = (hi - lo) // 2
            dim[node] = ax
            split[node] = float(samples[srt[mid], ax])
            for child, (clo, chi) in enumerate(((lo, lo + mid), (lo + mid, hi))):
                k = len(dim)
                dim.append(0)
                split.append(0.0)
                left.append(-1)
                right.append(-1)
                start.append(0)
                end.append(0)
                if child == 0:
                    left[node] = k
                else:
                    right[node] = k
                todo.append((k, clo, chi))
        perm.append(order)
        offset += len(order)
    return (
        np.asarray(dim, dtype=np.int64),
        np.asarray(split, dtype=np.float64),
        np.asarray(left, dtype=np.int64),
        np.asarray(right, dtype=np.int64),
        np.asarray(start, dtype=np.int64),
        np.asarray(end, dtype=np.int64),
        np.concatenate(perm) if perm else np.zeros(0, dtype=np.int64),
        roots,
    )


def sorted_candidates(
    samples: FloatArray, normal_bin: IntArray, grid: tuple[np.ndarray, ...]
) -> tuple[np.ndarray, ...]:
    """The grid's exact-nearest candidates packed for `_correspond_block`: each cell's list (same ranges
    cand_start) sorted by distance to the cell centre; returns (points (C, 3), distance to the centre (C,),
    sample index (C,), normal bin (C,))."""
    origin, cellarr, cells, cand_start, cand_idx, _, _ = grid
    return _sort_candidates(
        samples, np.asarray(normal_bin, dtype=np.int64), origin, float(cellarr[0]), cells.shape[0], cand_start, cand_idx
    )


@njit(cache=True, nogil=True)
def _sort_candidates(samples, normal_bin, origin, cell, g, cand_start, cand_idx):  # type: ignore[no-untyped-def]
    """`sorted_candidates` of one grid (the cells' lists sorted in place, stable)."""
    c_all = cand_idx.shape[0]
    pts = np.empty((c_all, 3))
    key = np.empty(c_all)
    sidx = np.empty(c_all, dtype=np.int64)
    sbin = np.empty(c_all, dtype=np.int64)
    for c in range(g * g * g):
        lo = cand_start[c]
        hi = cand_start[c + 1]
        if hi <= lo:
            continue
        i = c // (g * g)
        j = (c // g) % g
        k = c % g
        m0 = origin[0] + (i + 0.5) * cell
        m1 = origin[1] + (j + 0.5) * cell
        m2 = origin[2] + (k + 0.5) * cell
        dist = np.empty(hi - lo)
        for m in range(lo, hi):
            s = cand_idx[m]
            e0 = samples[s, 0] - m0
            e1 = samples[s, 1] - m1
            e2 = samples[s, 2] - m2
            dist[m - lo] = math.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
        order = np.argsort(dist, kind="mergesort")
        for q in range(hi - lo):
            m = lo + q
            s = cand_idx[lo + order[q]]
            key[m] = dist[order[q]]
            sidx[m] = s
            sbin[m] = normal_bin[s]
            pts[m, 0] = samples[s, 0]
            pts[m, 1] = samples[s, 1]
            pts[m, 2] = samples[s, 2]
    return pts, key, sidx, sbin


@njit(cache=True, nogil=True)
def _kd_nearest(  # type: ignore[no-untyped-def]
    q0, q1, q2, root, samples, dim, split, left, right, start, end, perm, best_d2, best_i, stack_n, stack_b
):
    """Exact nearest sample of the tree at `root` to (q0, q1, q2), starting from an upper bound best_d2 / best_i."""
    stack_n[0] = root
    stack_b[0] = 0.0
    top = 1
    while top > 0:
        top -= 1
        node = stack_n[top]
        if stack_b[top] >= best_d2:
            continue
        while left[node] >= 0:
            ax = dim[node]
            q = q0 if ax == 0 else (q1 if ax == 1 else q2)
            diff = q - split[node]
            if diff < 0.0:
                near = left[node]
                far = right[node]
            else:
                near = right[node]
                far = left[node]
            dd = diff * diff
            if dd < best_d2 and top < stack_n.shape[0]:
                stack_n[top] = far
                stack_b[top] = dd
                top += 1
            node = near
        for j in range(start[node], end[node]):
            s = perm[j]
            a = samples[s, 0] - q0
            b = samples[s, 1] - q1
            c = samples[s, 2] - q2
            d2 = a * a + b * b + c * c
            if d2 < best_d2:
                best_d2 = d2
                best_i = s
    return best_d2, best_i


# -- correspondences --------------------------------------------------------------------------------------------


@njit(cache=True, nogil=True, inline="always")
def _normal_bin(n0, n1, n2):  # type: ignore[no-untyped-def]
    """Bin 0..5 of a normal: dominant axis and sign (+x, -x, +y, -y, +z, -z), as `prepared.normal_bins`."""
    a0, a1, a2 = abs(n0), abs(n1), abs(n2)
    if a0 >= a1 and a0 >= a2:
        return 0 if n0 >= 0 else 1
    if a1 >= a2:
        return 2 if n1 >= 0 else 3
    return 4 if n2 >= 0 else 5


@njit(cache=True, nogil=True)
def _correspond_block(y, ny, exact, max_d, samples, normals, grid, kd, cand, stack_n, stack_b, r, d, sel):  # type: ignore[no-untyped-def]
    """Closest normal-compatible samples of object-frame points y (P, 3) with normals ny (P, 3), into
    r (P,) point-to-plane residual, d (P,) distance (inf when none) and sel (P,) sample index.

    Grid mode: the grid cell's nearest sample, else (normal disagrees, cos <= 0.35) the cell's nearest sample of
    the normal's bin; points outside the grid get none. Exact mode: the exact nearest sample (KD-tree), else the
    exact nearest one of the normal's bin; a point that provably lies farther than max_d (metres) from every
    sample (the grid cell's distance bound) gets distance inf without a search. `cand` (`sorted_candidates`, or
    empty arrays): the cells' candidates packed and sorted by distance to the cell centre, so a scan stops at the
    first candidate that cannot be nearer (triangle inequality); the same nearest samples (up to exact ties).
    Written as one loop (per-point helper calls cost more than the work).
    """
    origin, cellarr, cells, cand_start, cand_idx, cell_dist, sample_bin = grid
    dim, split, left, right, start, end, perm, roots = kd
    cand_pts, cand_key, cand_sample, cand_bin = cand
    packed = cand_key.shape[0] > 0
    cell = cellarr[0]
    pad = cellarr[1]
    half_diag = 0.5 * math.sqrt(3.0) * cell
    o0, o1, o2 = origin[0], origin[1], origin[2]
    g = cells.shape[0]
    gf = g - 1.0
    s_last = samples.shape[0] - 1
    for q in range(y.shape[0]):
        y0, y1, y2 = y[q, 0], y[q, 1], y[q, 2]
        n0, n1, n2 = ny[q, 0], ny[q, 1], ny[q, 2]
        fi = math.floor((y0 - o0) / cell)
        fj = math.floor((y1 - o1) / cell)
        fk = math.floor((y2 - o2) / cell)
        inside = fi >= 0.0 and fj >= 0.0 and fk >= 0.0 and fi < g and fj < g and fk < g
        i = int(min(max(fi, 0.0), gf)) if fi == fi else 0
        j = int(min(max(fj, 0.0), gf)) if fj == fj else 0
        k = int(min(max(fk, 0.0), gf)) if fk == fk else 0
        s = int(cells[i, j, k, 0])
        ok = normals[s, 0] * n0 + normals[s, 1] * n1 + normals[s, 2] * n2 > NORMAL_COS
        if not exact:
            if not ok:
                b = _normal_bin(n0, n1, n2)
                s2 = int(cells[i, j, k, 1 + b])
                inside = inside and s2 >= 0
                s = s2 if s2 >= 0 else s_last
                ok = normals[s, 0] * n0 + normals[s, 1] * n1 + normals[s, 2] * n2 > NORMAL_COS
            e0 = y0 - samples[s, 0]
            e1 = y1 - samples[s, 1]
            e2 = y2 - samples[s, 2]
            d[q] = math.sqrt(e0 * e0 + e1 * e1 + e2 * e2) if (inside and ok) else np.inf
        elif (cell_dist[(i * g + j) * g + k] - half_diag if inside else pad) > max_d:
            d[q] = np.inf  # every sample is farther than max_d: no search needed
        else:
            c = (i * g + j) * g + k
            qb = _normal_bin(n0, n1, n2)
            bin_d2 = np.inf  # nearest candidate of the normal's bin, exact when within the cell's reach
            bin_s = -1
            listed = inside and cand_start[c + 1] > cand_start[c]
            if listed and packed:
                # sorted scan: a candidate key[m] from the cell centre is at least key[m] - |y - centre| away
                e0 = y0 - (o0 + (i + 0.5) * cell)
                e1 = y1 - (o1 + (j + 0.5) * cell)
                e2 = y2 - (o2 + (k + 0.5) * cell)
                yc = math.sqrt(e0 * e0 + e1 * e1 + e2 * e2) + 1e-12
                d2 = np.inf
                for m in range(cand_start[c], cand_start[c + 1]):
                    lb = cand_key[m] - yc
                    if lb > 0.0 and lb * lb >= d2:
                        break
                    e0 = y0 - cand_pts[m, 0]
                    e1 = y1 - cand_pts[m, 1]
                    e2 = y2 - cand_pts[m, 2]
                    dm = e0 * e0 + e1 * e1 + e2 * e2
                    if dm < d2:
                        d2 = dm
                        s = cand_sample[m]
                if not (normals[s, 0] * n0 + normals[s, 1] * n1 + normals[s, 2] * n2 > NORMAL_COS):
                    # the nearest candidate of the normal's bin, exact when within the cell's reach
                    reach = cell_dist[c] + half_diag
                    reach2 = reach * reach
                    for m in range(cand_start[c], cand_start[c + 1]):
                        lb = cand_key[m] - yc
                        if lb > 0.0 and (lb * lb >= bin_d2 or lb > reach):
                            break
                        if cand_bin[m] != qb:
                            continue
                        e0 = y0 - cand_pts[m, 0]
                        e1 = y1 - cand_pts[m, 1]
                        e2 = y2 - cand_pts[m, 2]
                        dm = e0 * e0 + e1 * e1 + e2 * e2
                        if dm < bin_d2:
                            bin_d2 = dm
                            bin_s = cand_sample[m]
                    if bin_d2 > reach2:
                        bin_s = -1
            elif listed:
                d2 = np.inf
                for m in range(cand_start[c], cand_start[c + 1]):
                    sm = cand_idx[m]
                    e0 = y0 - samples[sm, 0]
                    e1 = y1 - samples[sm, 1]
                    e2 = y2 - samples[sm, 2]
                    dm = e0 * e0 + e1 * e1 + e2 * e2
                    if dm < d2:
                        d2 = dm
                        s = sm
                    if dm < bin_d2 and sample_bin[sm] == qb:
                        bin_d2 = dm
                        bin_s = sm
            else:
                e0 = y0 - samples[s, 0]
                e1 = y1 - samples[s, 1]
                e2 = y2 - samples[s, 2]
                d2, s = _kd_nearest(
                    y0,
                    y1,
                    y2,
                    roots[0],
                    samples,
                    dim,
                    split,
                    left,
                    right,
                    start,
                    end,
                    perm,
                    e0 * e0 + e1 * e1 + e2 * e2,
                    s,
                    stack_n,
                    stack_b,
                )
            ok = normals[s, 0] * n0 + normals[s, 1] * n1 + normals[s, 2] * n2 > NORMAL_COS
            if not ok:
                b = qb
                root = roots[1 + b]
                reach = cell_dist[c] + half_diag  # a candidate this close beats every sample off the list
                if listed and bin_s >= 0 and bin_d2 <= reach * reach:
                    d2 = bin_d2
                    s = bin_s
                elif root < 0:
                    d2 = np.inf
                    s = 0
                else:
                    s2 = int(cells[i, j, k, 1 + b])
                    if s2 >= 0:
                        e0 = y0 - samples[s2, 0]
                        e1 = y1 - samples[s2, 1]
                        e2 = y2 - samples[s2, 2]
                        init = e0 * e0 + e1 * e1 + e2 * e2
                    else:
                        init = np.inf
                        s2 = 0
                    d2, s = _kd_nearest(
                        y0, y1, y2, root, samples, dim, split, left, right, start, end, perm, init, s2, stack_n, stack_b
                    )
                ok = normals[s, 0] * n0 + normals[s, 1] * n1 + normals[s, 2] * n2 > NORMAL_COS
            d[q] = math.sqrt(d2) if ok else np.inf
        sel[q] = s
        r[q] = (
            (y0 - samples[s, 0]) * normals[s, 0]
            + (y1 - samples[s, 1]) * normals[s, 1]
            + (y2 - samples[s, 2]) * normals[s, 2]
        )


@njit(cache=True, nogil=True)
def correspond_many(y, ny, exact, samples, normals, grid, kd):  # type: ignore[no-untyped-def]
    """(P, 3) object-frame points and normals -> residual (P,), distance (P,), sample index (P,)."""
    p = y.shape[0]
    r = np.empty(p)
    d = np.empty(p)
    idx = np.empty(p, dtype=np.int64)
    stack_n = np.empty(_STACK, dtype=np.int64)
    stack_b = np.empty(_STACK)
    cand = (np.zeros((0, 3)), np.zeros(0), np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64))
    _correspond_block(y, ny, exact, np.inf, samples, normals, grid, kd, cand, stack_n, stack_b, r, d, idx)
    return r, d, idx


@njit(cache=True, nogil=True, inline="always")
def _pose_points(rot, t, s, pts, nrm, y, ny):  # type: ignore[no-untyped-def]
    """y = (R pts + t) / s and ny = R nrm, (P, 3) each, in place."""
    for q in range(pts.shape[0]):
        for u in range(3):
            y[q, u] = (rot[u, 0] * pts[q, 0] + rot[u, 1] * pts[q, 1] + rot[u, 2] * pts[q, 2] + t[u]) / s
            ny[q, u] = rot[u, 0] * nrm[q, 0] + rot[u, 1] * nrm[q, 1] + rot[u, 2] * nrm[q, 2]


@njit(cache=True, nogil=True)
def correspond_posed(poses, scales, pts, nrm, exact, max_d, samples, normals, grid, kd, cand):  # type: ignore[no-untyped-def]
    """Correspondences of (P, 3) frame points under (H, 4, 4) object_from_frame poses / (H,) scales: r, d (H, P);
    distances that would exceed max_d may come back as inf (see `_correspond_block`)."""
    h = poses.shape[0]
    p = pts.shape[0]
    r = np.empty((h, p))
    d = np.empty((h, p))
    sel = np.empty(p, dtype=np.int64)
    y = np.empty((p, 3))
    ny = np.empty((p, 3))
    stack_n = np.empty(_STACK, dtype=np.int64)
    stack_b = np.empty(_STACK)
    for a in range(h):
        _pose_points(poses[a, :3, :3], poses[a, :3, 3], scales[a], pts, nrm, y, ny)
        _correspond_block(y, ny, exact, max_d, samples, normals, grid, kd, cand, stack_n, stack_b, r[a], d[a], sel)
    return r, d


@njit(cache=True, nogil=True)
def _kth_smallest(values, n, k):  # type: ignore[no-untyped-def]
    """The k-th smallest (0-based) of values[:n] (quickselect on values[:n], which is reordered)."""
    lo = 0
    hi = n - 1
    while lo < hi:
        pivot = values[(lo + hi) // 2]
        i = lo
        j = hi
        while i <= j:
            while values[i] < pivot:
                i += 1
            while values[j] > pivot:
                j -= 1
            if i <= j:
                tmp = values[i]
                values[i] = values[j]
                values[j] = tmp
                i += 1
                j -= 1
        if k <= j:
            hi = j
        elif k >= i:
            lo = i
        else:
            return values[k]
    return values[k]


# -- ICP --------------------------------------------------------------------------------------------------------


@njit(cache=True, nogil=True)
def _solve(a, b, n):  # type: ignore[no-untyped-def]
    """Solve the n x n system a x = b in place (Gaussian elimination, partial pivoting); returns x."""
    for col in range(n):
        piv = col
        best = abs(a[col, col])
        for row in range(col + 1, n):
            if abs(a[row, col]) > best:
                best = abs(a[row, col])
                piv = row
        if piv != col:
            for c in range(n):
                tmp = a[col, c]
                a[col, c] = a[piv, c]
                a[piv, c] = tmp
            tmp = b[col]
            b[col] = b[piv]
            b[piv] = tmp
        dg = a[col, col]
        if dg == 0.0:
            continue
        for row in range(col + 1, n):
            f = a[row, col] / dg
            if f != 0.0:
                for c in range(col, n):
                    a[row, c] -= f * a[col, c]
                b[row] -= f * b[col]
    x = np.zeros(n)
    for row in range(n - 1, -1, -1):
        acc = b[row]
        for c in range(row + 1, n):
            acc -= a[row, c] * x[c]
        x[row] = acc / a[row, row] if a[row, row] != 0.0 else 0.0
    return x


@njit(cache=True, nogil=True)
def _rodrigues(k0, k1, k2, st, ct):  # type: ignore[no-untyped-def]
    """I + st [k]x + ct [k]x^2 (3, 3) for a unit axis k (st = sin, ct = 1 - cos of the angle)."""
    kx = np.zeros((3, 3))
    kx[0, 1] = -k2
    kx[0, 2] = k1
    kx[1, 0] = k2
    kx[1, 2] = -k0
    kx[2, 0] = -k1
    kx[2, 1] = k0
    rd = np.eye(3)
    for u in range(3):
        for v in range(3):
            rd[u, v] += st * kx[u, v] + ct * (kx[u, 0] * kx[0, v] + kx[u, 1] * kx[1, v] + kx[u, 2] * kx[2, v])
    return rd


@njit(cache=True, nogil=True)
def _add_point_terms(a, b, pp, c, fit_scale):  # type: ignore[no-untyped-def]
    """Add the point-to-point normal equations (upper triangle of a, and b) from the sums `pp` (see icp_run):
    per point J = [-[y]x, I(, -(y - c))], e = y - model point; a += sum w J^T J, b -= sum w J^T e
    (as `icp.point_to_point_normal_equations`)."""
    s0 = pp[0]
    s1x, s1y, s1z = pp[1], pp[2], pp[3]
    xx, xy, xz, yy, yz, zz = pp[4], pp[5], pp[6], pp[7], pp[8], pp[9]
    tr = xx + yy + zz
    a[0, 0] += tr - xx
    a[0, 1] -= xy
    a[0, 2] -= xz
    a[1, 1] += tr - yy
    a[1, 2] -= yz
    a[2, 2] += tr - zz
    # [s1]x in the rotation-translation block
    a[0, 4] -= s1z
    a[0, 5] += s1y
    a[1, 3] += s1z
    a[1, 5] -= s1x
    a[2, 3] -= s1y
    a[2, 4] += s1x
    a[3, 3] += s0
    a[4, 4] += s0
    a[5, 5] += s0
    b[0] -= pp[13]
    b[1] -= pp[14]
    b[2] -= pp[15]
    b[3] -= pp[10]
    b[4] -= pp[11]
    b[5] -= pp[12]
    if fit_scale:
        c0, c1, c2 = c[0], c[1], c[2]
        a[0, 6] += s1y * c2 - s1z * c1
        a[1, 6] += s1z * c0 - s1x * c2
        a[2, 6] += s1x * c1 - s1y * c0
        a[3, 6] -= s1x - s0 * c0
        a[4, 6] -= s1y - s0 * c1
        a[5, 6] -= s1z - s0 * c2
        a[6, 6] += tr - 2.0 * (c0 * s1x + c1 * s1y + c2 * s1z) + s0 * (c0 * c0 + c1 * c1 + c2 * c2)
        b[6] += pp[16] - (c0 * pp[10] + c1 * pp[11] + c2 * pp[12])


@njit(cache=True, nogil=True)
def icp_run(  # type: ignore[no-untyped-def]
    poses,
    scales,
    frac,
    it_state,
    pts,
    nrm,
    thr,
    gates,
    exact_iter,
    it_stop,
    jump_to,
    gate_end,
    fit_scale,
    scale_tolerance,
    trim,
    point_weight,
    prior,
    converge,
    centroid,
    diameter,
    samples,
    normals,
    grid,
    kd,
    cand,
):
    """Trimmed point-to-plane ICP iterations of every hypothesis, in place.

    poses (H, 4, 4) object_from_frame, scales (H,), frac (H,) inlier fraction of the last iteration,
    it_state (H,) next iteration of each hypothesis (set to `len(gates)` once converged); pts / nrm (P, 3)
    frame points / normals, thr (P,) inlier distances; gates (I,) correspondence gate per iteration, exact_iter
    (I,) exact (KD-tree) correspondences per iteration; iterations run while it < it_stop. A hypothesis whose
    gate is at its floor (gate_end) and that moved less than `converge` (metres, rotation at one diameter)
    jumps to iteration `jump_to` (the exact stage) when that lies ahead, else stops. cand: `sorted_candidates`.
    """
    h = poses.shape[0]
    p = pts.shape[0]
    n_it = gates.shape[0]
    dof = 7 if fit_scale else 6
    thr_min = np.inf
    for q in range(p):
        thr_min = min(thr_min, thr[q])
    y = np.empty((p, 3))
    ny = np.empty((p, 3))
    r = np.empty(p)
    d = np.empty(p)
    sel = np.empty(p, dtype=np.int64)
    absv = np.empty(p)
    a = np.empty((7, 7))
    b = np.empty(7)
    jac = np.empty(7)
    pp = np.zeros(17)
    stack_n = np.empty(_STACK, dtype=np.int64)
    stack_b = np.empty(_STACK)
    c0, c1, c2 = centroid[0], centroid[1], centroid[2]
    for hh in range(h):
        while it_state[hh] < it_stop:
            it = it_state[hh]
            gate = gates[it]
            exact = exact_iter[it]
            rot = poses[hh, :3, :3].copy()
            t = poses[hh, :3, 3].copy()
            s = scales[hh]
            # correspondences
            _pose_points(rot, t, s, pts, nrm, y, ny)
            _correspond_block(y, ny, exact, gate, samples, normals, grid, kd, cand, stack_n, stack_b, r, d, sel)
            cnt = 0
            inl = 0
            for q in range(p):
                if d[q] < gate:
                    absv[cnt] = abs(r[q])
                    cnt += 1
                    if abs(r[q]) < thr[q]:
                        inl += 1
            frac[hh] = inl / p
            # trimming: keep residuals up to the `trim` quantile of the valid ones (at least thr_min)
            kth = int(trim * cnt) - 1
            kth = min(max(kth, 0), p - 1)
            if kth < cnt:
                cut = _kth_smallest(absv, cnt, kth)
            else:
                cut = np.inf
            cut = max(cut, thr_min)
            # normal equations
            for u in range(7):
                b[u] = 0.0
                for v in range(7):
                    a[u, v] = 0.0
            pp[:] = 0.0
            for q in range(p):
                if not (d[q] < gate) or abs(r[q]) > cut:
                    continue
                ar = abs(r[q])
                w = thr[q] / max(ar, 1e-12) if ar > thr[q] else 1.0
                m = sel[q]
                nx, ny_, nz = normals[m, 0], normals[m, 1], normals[m, 2]
                y0, y1, y2 = y[q, 0], y[q, 1], y[q, 2]
                jac[0] = y1 * nz - y2 * ny_
                jac[1] = y2 * nx - y0 * nz
                jac[2] = y0 * ny_ - y1 * nx
                jac[3] = nx
                jac[4] = ny_
                jac[5] = nz
                if fit_scale:
                    jac[6] = -(nx * (y0 - c0) + ny_ * (y1 - c1) + nz * (y2 - c2))
                for u in range(dof):
                    wu = w * jac[u]
                    b[u] -= wu * r[q]
                    for v in range(u, dof):
                        a[u, v] += wu * jac[v]
                if point_weight > 0.0:
                    # point-to-point term, J = [-[y]x, I, -(y - c)]: its normal equations are sums of
                    # w, w y, w y y^T, w e, w y x e and w y.e (assembled in closed form below)
                    wp = w * point_weight
                    e0 = y0 - samples[m, 0]
                    e1 = y1 - samples[m, 1]
                    e2 = y2 - samples[m, 2]
                    pp[0] += wp
                    pp[1] += wp * y0
                    pp[2] += wp * y1
                    pp[3] += wp * y2
                    pp[4] += wp * y0 * y0
                    pp[5] += wp * y0 * y1
                    pp[6] += wp * y0 * y2
                    pp[7] += wp * y1 * y1
                    pp[8] += wp * y1 * y2
                    pp[9] += wp * y2 * y2
                    pp[10] += wp * e0
                    pp[11] += wp * e1
                    pp[12] += wp * e2
                    pp[13] += wp * (y1 * e2 - y2 * e1)
                    pp[14] += wp * (y2 * e0 - y0 * e2)
                    pp[15] += wp * (y0 * e1 - y1 * e0)
                    pp[16] += wp * (y0 * e0 + y1 * e1 + y2 * e2)
            if point_weight > 0.0:
                _add_point_terms(a, b, pp, centroid, fit_scale)
            for u in range(dof):
                a[u, u] += 1e-9
                for v in range(u):
                    a[u, v] = a[v, u]
            if fit_scale:
                a[6, 6] += prior
                b[6] -= prior * (s - 1.0)
            if cnt >= 6:
                delta = _solve(a, b, dof)
            else:
                delta = np.zeros(dof)
            # pose update
            w0, w1, w2 = delta[0], delta[1], delta[2]
            theta = math.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
            if theta < 1e-12:
                k0 = w0
                k1 = w1
                k2 = w2
            else:
                k0 = w0 / theta
                k1 = w1 / theta
                k2 = w2 / theta
            st = math.sin(theta)
            ct = 1.0 - math.cos(theta)
            rd = _rodrigues(k0, k1, k2, st, ct)
            sig = delta[6] if fit_scale else 0.0
            sig = min(max(sig, -0.5), 0.5)
            s_new = min(max(s / (1.0 - sig), 1.0 - scale_tolerance), 1.0 + scale_tolerance)
            for u in range(3):
                for v in range(3):
                    poses[hh, u, v] = rd[u, 0] * rot[0, v] + rd[u, 1] * rot[1, v] + rd[u, 2] * rot[2, v]
            for u in range(3):
                poses[hh, u, 3] = (
                    rd[u, 0] * t[0] + rd[u, 1] * t[1] + rd[u, 2] * t[2] + s * delta[3 + u] + (s_new - s) * centroid[u]
                )
            scales[hh] = s_new
            it += 1
            moved = theta * diameter + math.sqrt(delta[3] ** 2 + delta[4] ** 2 + delta[5] ** 2)
            if gate <= gate_end and moved < converge:
                it = jump_to if it < jump_to else n_it
            it_state[hh] = it


# -- scoring helpers --------------------------------------------------------------------------------------------


@njit(cache=True, nogil=True)
def visible_mask(pc, nc, spacing_scaled):  # type: ignore[no-untyped-def]
    """(S,) visibility of camera-frame samples pc (S, 3) with normals nc (S, 3): back-face culling + z-buffer.

    The z-buffer cell is 1.6 spacing / median facing z (in normalised image units); a facing sample is visible
    when its z is within 2 spacings of the nearest facing sample in its cell (as `scoring.visible_samples`).
    """
    s = pc.shape[0]
    facing = np.zeros(s, dtype=np.bool_)
    nf = 0
    for i in range(s):
        dist = math.sqrt(pc[i, 0] ** 2 + pc[i, 1] ** 2 + pc[i, 2] ** 2)
        f = -(nc[i, 0] * pc[i, 0] + nc[i, 1] * pc[i, 1] + nc[i, 2] * pc[i, 2]) > 0.05 * dist
        if f and pc[i, 2] > 1e-3:
            facing[i] = True
            nf += 1
    visible = np.zeros(s, dtype=np.bool_)
    if nf == 0:
        return visible
    zf = np.empty(nf)
    j = 0
    for i in range(s):
        if facing[i]:
            zf[j] = pc[i, 2]
            j += 1
    if nf % 2 == 1:
        med = _kth_smallest(zf, nf, nf // 2)
    else:
        med = 0.5 * (_kth_smallest(zf, nf, nf // 2 - 1) + _kth_smallest(zf, nf, nf // 2))
    cell = 1.6 * spacing_scaled / med
    ui = np.empty(s, dtype=np.int64)
    vi = np.empty(s, dtype=np.int64)
    umin = vmin = 1 << 62
    umax = vmax = -(1 << 62)
    for i in range(s):
        if facing[i]:
            z = max(pc[i, 2], 1e-3)
            ui[i] = int(math.floor(pc[i, 0] / z / cell))
            vi[i] = int(math.floor(pc[i, 1] / z / cell))
            umin = min(umin, ui[i])
            umax = max(umax, ui[i])
            vmin = min(vmin, vi[i])
            vmax = max(vmax, vi[i])
    nu = umax - umin + 1
    nv = vmax - vmin + 1
    zmin = np.full((nu, nv), np.inf)
    for i in range(s):
        if facing[i]:
            cu = ui[i] - umin
            cv = vi[i] - vmin
            if pc[i, 2] < zmin[cu, cv]:
                zmin[cu, cv] = pc[i, 2]
    lim = 2.0 * spacing_scaled
    for i in range(s):
        if facing[i] and pc[i, 2] <= zmin[ui[i] - umin, vi[i] - vmin] + lim:
            visible[i] = True
    return visible


@njit(cache=True, nogil=True)
def fit_stats(r, d, scale, thr, spacing, beside_spacings, beside_thr, neighbours, k, floor_m):  # type: ignore[no-untyped-def]
    """Inlier ratio, inlier RMSE (metres, inf without inliers) and consistency of (P,) residuals / distances.

    As `scoring._fit_stats` / `scoring._consistency`: a point is near when d < max(3 thr / scale, 2 spacing);
    an inlier is near, |r| scale < thr and its offset along the surface is within
    max(beside_spacings spacing scale, beside_thr thr); consistent when near, at least k // 2 of its k
    neighbours (rows of `neighbours` (P, k)) are near and their mean residual is within
    max(floor_m, 3 sigma / sqrt(count)), sigma = thr / 2.5.
    """
    p = r.shape[0]
    near = np.zeros(p, dtype=np.bool_)
    n_inl = 0
    ss = 0.0
    for q in range(p):
        lim = max(3.0 * thr[q] / scale, 2.0 * spacing)
        if d[q] < lim:
            near[q] = True
            off2 = d[q] * d[q] - r[q] * r[q]
            beside = math.sqrt(off2 if off2 > 0.0 else 0.0) * scale
            if abs(r[q]) * scale < thr[q] and beside <= max(beside_spacings * spacing * scale, beside_thr * thr[q]):
                n_inl += 1
                ss += (r[q] * scale) ** 2
    ratio = n_inl / p if p > 0 else 0.0
    rmse = math.sqrt(ss / n_inl) if n_inl > 0 else np.inf
    if p < 4:
        return ratio, rmse, 0.0
    n_ok = 0
    for q in range(p):
        if not near[q]:
            continue
        cnt = 0
        acc = 0.0
        for j in range(k):
            nb = neighbours[q, j]
            if near[nb]:
                cnt += 1
                acc += r[nb] * scale
        mean = acc / max(cnt, 1)
        lim = max(floor_m, 3.0 * (thr[q] / 2.5) / math.sqrt(max(cnt, 1)))
        if cnt >= k // 2 and abs(mean) <= lim:
            n_ok += 1
    return ratio, rmse, n_ok / p


@njit(cache=True, nogil=True, inline="always")
def _window_depths(depth, u, v, rad, z):  # type: ignore[no-untyped-def]
    """Within +-rad pixels of (u, v) (clamped to the image): the nearest valid depth and the smallest |depth - z|,
    metres (inf where no pixel has a valid reading)."""
    hgt, wid = depth.shape
    nearest = np.inf
    closest = np.inf
    for dv in range(-rad, rad + 1):
        vv = min(max(v + dv, 0), hgt - 1)
        for du in range(-rad, rad + 1):
            uu = min(max(u + du, 0), wid - 1)
            val = depth[vv, uu]
            if val > 0 and np.isfinite(val):
                nearest = min(nearest, val)
                closest = min(closest, abs(val - z))
    return nearest, closest


@njit(cache=True, nogil=True, inline="always")
def _window_support(depth, u, v, rad, z, tol):  # type: ignore[no-untyped-def]
    """`_window_depths` for a caller that only needs the nearest depth when no pixel of the window is within tol
    of z: the scan (own pixel first) stops at the first such pixel and returns it with its |depth - z|. A depth
    within tol of z lies less than 3 tol (the see-through limit) behind z, so that caller's counts are the same.
    (u, v) must lie in the image."""
    hgt, wid = depth.shape
    val = depth[v, u]
    if val > 0 and np.isfinite(val) and abs(val - z) <= tol:
        return val, abs(val - z)
    nearest = np.inf
    closest = np.inf
    for dv in range(-rad, rad + 1):
        vv = min(max(v + dv, 0), hgt - 1)
        for du in range(-rad, rad + 1):
            uu = min(max(u + du, 0), wid - 1)
            val = depth[vv, uu]
            if val > 0 and np.isfinite(val):
                if abs(val - z) <= tol:
                    return val, abs(val - z)
                nearest = min(nearest, val)
                closest = min(closest, abs(val - z))
    return nearest, closest


@njit(cache=True, nogil=True)
def depth_evidence(pv, nv, uv, depth, tol, rad):  # type: ignore[no-untyped-def]
    """Depth-image tests of visible template points pv (V, 3) (camera frame) with normals nv (V, 3), pixels uv (V, 2).

    Returns counts (supported, inside and not occluded, violating, missing, inside and not grazing, occluded)
    as in `scoring.evaluate`: occluded: the pixel's depth lies more than tol in front; within +-rad pixels the
    nearest valid depth seen more than max(3 tol, 1 cm) behind the point is a free-space violation, no valid
    depth at all is missing; supported: not occluded and some depth in the window within tol of the point.
    Grazing points (|n . p| < 0.3 |p|) are left out of the free-space tests.
    """
    hgt, wid = depth.shape
    n_sup = n_den = n_vio = n_mis = n_ng = n_occ = 0
    see_lim = max(3.0 * tol, 0.01)
    for i in range(pv.shape[0]):
        u = uv[i, 0]
        v = uv[i, 1]
        if not (u >= 0 and u < wid and v >= 0 and v < hgt):
            continue
        z = pv[i, 2]
        plen = math.sqrt(pv[i, 0] ** 2 + pv[i, 1] ** 2 + z * z)
        grazing = abs(nv[i, 0] * pv[i, 0] + nv[i, 1] * pv[i, 1] + nv[i, 2] * z) < 0.3 * plen
        meas = depth[v, u]
        occluded = meas > 0 and np.isfinite(meas) and meas - z < -tol
        nearest, closest = _window_depths(depth, u, v, rad, z)
        if occluded:
            n_occ += 1
        else:
            n_den += 1
            if closest <= tol:
                n_sup += 1
        if not grazing:
            n_ng += 1
            if np.isfinite(nearest):
                if nearest - z > see_lim:
                    n_vio += 1
            else:
                n_mis += 1
    return n_sup, n_den, n_vio, n_mis, n_ng, n_occ


@njit(cache=True, nogil=True)
def silhouette_evidence(pv, uv, depth, tol, rad, front_lim):  # type: ignore[no-untyped-def]
    """Evidence of a pose over its whole camera-visible surface: pv (V, 3) visible template points (camera frame),
    uv (V, 2) their pixels, depth (H, W) metres (0 = no reading).

    Returns (in_image, explained, front): points whose pixel lies in the image; points explained (some valid
    depth within +-rad pixels within tol of the point, as `depth_evidence`'s support); unexplained points whose
    own pixel reads between tol and front_lim metres IN FRONT of the point (a measured surface running just in
    front of the model: the model would lie right behind a surface it does not explain; a separate occluder
    lies farther in front or touches only along a line).
    """
    hgt, wid = depth.shape
    n_in = n_exp = n_front = 0
    for i in range(pv.shape[0]):
        u = uv[i, 0]
        v = uv[i, 1]
        if not (u >= 0 and u < wid and v >= 0 and v < hgt):
            continue
        n_in += 1
        z = pv[i, 2]
        closest = np.inf
        for dv in range(-rad, rad + 1):
            vv = min(max(v + dv, 0), hgt - 1)
            for du in range(-rad, rad + 1):
                uu = min(max(u + du, 0), wid - 1)
                val = depth[vv, uu]
                if val > 0 and np.isfinite(val):
                    closest = min(closest, abs(val - z))
        if closest <= tol:
            n_exp += 1
            continue
        meas = depth[v, u]
        if meas > 0 and np.isfinite(meas) and z - meas > tol and z - meas <= front_lim:
            n_front += 1
    return n_in, n_exp, n_front


@njit(cache=True, nogil=True)
def nearest_rows(query, data_t, k):  # type: ignore[no-untyped-def]
    """(N, k) indices of the k nearest columns of data_t (D, F) to each row of query (N, D), nearest first.

    Brute force with a vectorisable inner loop (faster than a KD-tree in 33 dimensions for a few hundred rows);
    equal distances keep the lower index.
    """
    n, dd = query.shape
    f = data_t.shape[1]
    k = min(k, f)
    out = np.empty((n, k), dtype=np.int64)
    acc = np.empty(f)
    for i in range(n):
        acc[:] = 0.0
        for c in range(dd):
            qc = query[i, c]
            row = data_t[c]
            for m in range(f):
                diff = qc - row[m]
                acc[m] += diff * diff
        for j in range(k):
            best = np.inf
            bi = 0
            for m in range(f):
                if acc[m] < best:
                    best = acc[m]
                    bi = m
            out[i, j] = bi
            acc[bi] = np.inf
    return out


@njit(cache=True, nogil=True)
def visible_points(samples, normals, cfo, scale, spacing):  # type: ignore[no-untyped-def]
    """Camera-frame points pv (V, 3) and normals nv (V, 3) of the visible template samples.

    cfo (4, 4): camera_from_object; samples are scaled by `scale` first; visibility as `visible_mask`.
    """
    s = samples.shape[0]
    pc = np.empty((s, 3))
    nc = np.empty((s, 3))
    for i in range(s):
        for u in range(3):
            pc[i, u] = (
                cfo[u, 0] * samples[i, 0] * scale
                + cfo[u, 1] * samples[i, 1] * scale
                + cfo[u, 2] * samples[i, 2] * scale
                + cfo[u, 3]
            )
            nc[i, u] = cfo[u, 0] * normals[i, 0] + cfo[u, 1] * normals[i, 1] + cfo[u, 2] * normals[i, 2]
    vis = visible_mask(pc, nc, spacing * scale)
    n = 0
    for i in range(s):
        if vis[i]:
            n += 1
    pv = np.empty((n, 3))
    nv = np.empty((n, 3))
    j = 0
    for i in range(s):
        if vis[i]:
            for u in range(3):  # element copies: row-slice assignment costs more than the copy
                pv[j, u] = pc[i, u]
                nv[j, u] = nc[i, u]
            j += 1
    return pv, nv


@njit(cache=True, nogil=True)
def project_pinhole(pv, fx, fy, cx, cy):  # type: ignore[no-untyped-def]
    """(V, 2) int64 pixels (rounded) of camera-frame points pv (V, 3) without distortion; -1 where not finite."""
    n = pv.shape[0]
    uv = np.empty((n, 2), dtype=np.int64)
    for i in range(n):
        u = np.rint(fx * (pv[i, 0] / pv[i, 2]) + cx)
        v = np.rint(fy * (pv[i, 1] / pv[i, 2]) + cy)
        if np.isfinite(u) and np.isfinite(v) and abs(u) < 1e9 and abs(v) < 1e9:
            uv[i, 0] = int(u)
            uv[i, 1] = int(v)
        else:
            uv[i, 0] = -1
            uv[i, 1] = -1
    return uv


@njit(cache=True, nogil=True)
def mean_closest(a, b):  # type: ignore[no-untyped-def]
    """Mean over the points of a (N, 3) of the distance to the closest point of b (M, 3).

    Exact: b sorted along x, each point's search runs outwards from its x position and stops once the x gap
    alone reaches the best distance (the same closest distances as a brute-force scan, summed in a's order).
    """
    n = a.shape[0]
    m = b.shape[0]
    if n == 0 or m == 0:
        return np.inf
    order = np.argsort(b[:, 0])
    bs = np.empty((m, 3))
    for j in range(m):
        bs[j, 0] = b[order[j], 0]
        bs[j, 1] = b[order[j], 1]
        bs[j, 2] = b[order[j], 2]
    xs = bs[:, 0].copy()
    acc = 0.0
    for i in range(n):
        a0, a1, a2 = a[i, 0], a[i, 1], a[i, 2]
        best = np.inf
        start = np.searchsorted(xs, a0)
        j = start
        while j < m:
            e0 = a0 - bs[j, 0]
            if e0 * e0 >= best:
                break
            e1 = a1 - bs[j, 1]
            e2 = a2 - bs[j, 2]
            dd = e0 * e0 + e1 * e1 + e2 * e2
            if dd < best:
                best = dd
            j += 1
        j = start - 1
        while j >= 0:
            e0 = a0 - bs[j, 0]
            if e0 * e0 >= best:
                break
            e1 = a1 - bs[j, 1]
            e2 = a2 - bs[j, 2]
            dd = e0 * e0 + e1 * e1 + e2 * e2
            if dd < best:
                best = dd
            j -= 1
        acc += math.sqrt(best)
    return acc / n


@njit(cache=True, nogil=True)
def fpfh_histograms(points, normals, idx, dist, valid, n_bins):  # type: ignore[no-untyped-def]
    """(N, 3 n_bins) FPFH of points (N, 3) with unit normals from their neighbours idx / dist / valid (N, K).

    As `features.fpfh`: per pair (Darboux frame u = n_i, v = u x d, w = u x v) the angles alpha = v.n_j,
    phi = u.d, theta = atan2(w.n_j, u.n_j) are binned (SPFH, divided by the neighbour count); the FPFH adds the
    neighbours' SPFH weighted by 1 / distance, and each angle's histogram is normalised to sum 1.
    """
    n, k = idx.shape
    nb3 = 3 * n_bins
    spfh = np.zeros((n, nb3))
    cnt = np.zeros(n)
    for i in range(n):
        u0, u1, u2 = normals[i, 0], normals[i, 1], normals[i, 2]
        for kk in range(k):
            if not valid[i, kk]:
                continue
            j = idx[i, kk]
            cnt[i] += 1.0
            d0 = points[j, 0] - points[i, 0]
            d1 = points[j, 1] - points[i, 1]
            d2 = points[j, 2] - points[i, 2]
            dn = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
            if dn < 1e-12:
                dn = 1.0
            d0 /= dn
            d1 /= dn
            d2 /= dn
            v0 = u1 * d2 - u2 * d1
            v1 = u2 * d0 - u0 * d2
            v2 = u0 * d1 - u1 * d0
            vn = math.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
            if vn < 1e-12:
                vn = 1.0
            v0 /= vn
            v1 /= vn
            v2 /= vn
            w0 = u1 * v2 - u2 * v1
            w1 = u2 * v0 - u0 * v2
            w2 = u0 * v1 - u1 * v0
            m0, m1, m2 = normals[j, 0], normals[j, 1], normals[j, 2]
            alpha = v0 * m0 + v1 * m1 + v2 * m2
            phi = u0 * d0 + u1 * d1 + u2 * d2
            wm = w0 * m0 + w1 * m1 + w2 * m2
            theta = math.atan2(wm if abs(wm) >= 1e-12 else 0.0, u0 * m0 + u1 * m1 + u2 * m2)
            b1 = min(max(int((alpha + 1) / 2 * n_bins), 0), n_bins - 1)
            b2 = min(max(int((phi + 1) / 2 * n_bins), 0), n_bins - 1)
            b3 = min(max(int((theta + np.pi) / (2 * np.pi) * n_bins), 0), n_bins - 1)
            spfh[i, b1] += 1.0
            spfh[i, n_bins + b2] += 1.0
            spfh[i, 2 * n_bins + b3] += 1.0
        c = max(cnt[i], 1.0)
        for b in range(nb3):
            spfh[i, b] /= c
    out = np.empty((n, nb3))
    neigh = np.empty(nb3)
    for i in range(n):
        neigh[:] = 0.0
        wsum = 0.0
        for kk in range(k):
            if not valid[i, kk]:
                continue
            w = 1.0 / max(dist[i, kk], 1e-9)
            wsum += w
            j = idx[i, kk]
            for b in range(nb3):
                neigh[b] += w * spfh[j, b]
        c = max(cnt[i], 1.0)
        wn = max(wsum, 1e-12) / c
        for b in range(nb3):
            out[i, b] = spfh[i, b] + neigh[b] / c / wn
        for a in range(3):
            s = 0.0
            for b in range(a * n_bins, (a + 1) * n_bins):
                s += out[i, b]
            s = max(s, 1e-12)
            for b in range(a * n_bins, (a + 1) * n_bins):
                out[i, b] /= s
    return out


@njit(cache=True, nogil=True)
def knn_points(pts, k):  # type: ignore[no-untyped-def]
    """(N, k) indices of each point's k nearest points of pts (N, 3), itself included, nearest first; equal
    distances keep the lower index (the k smallest (distance, index) pairs).

    Exact search on a cubic cell grid (about 2 points per cell over the bounding box): shells of cells around
    the point's cell until the next shell lies farther than the k-th distance (faster than a KD-tree or brute
    force for a few hundred points).
    """
    n = pts.shape[0]
    k = min(k, n)
    out = np.empty((n, k), dtype=np.int64)
    if k == 0:
        return out
    lo = np.empty(3)
    hi = np.empty(3)
    for u in range(3):
        lo[u] = pts[0, u]
        hi[u] = pts[0, u]
    for i in range(n):
        for u in range(3):
            lo[u] = min(lo[u], pts[i, u])
            hi[u] = max(hi[u], pts[i, u])
    ext = max(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2])
    per_axis = max(1, int(round((n / 2.0) ** (1.0 / 3.0))))
    h = ext / per_axis if ext > 0.0 else 1.0
    dims = np.empty(3, dtype=np.int64)
    for u in range(3):
        dims[u] = min(int((hi[u] - lo[u]) / h) + 1, 4 * per_axis)
    cell_of = np.empty(n, dtype=np.int64)
    ci = np.empty((n, 3), dtype=np.int64)
    for i in range(n):
        for u in range(3):
            ci[i, u] = min(int((pts[i, u] - lo[u]) / h), dims[u] - 1)
        cell_of[i] = (ci[i, 0] * dims[1] + ci[i, 1]) * dims[2] + ci[i, 2]
    n_cells = dims[0] * dims[1] * dims[2]
    start = np.zeros(n_cells + 1, dtype=np.int64)
    for i in range(n):
        start[cell_of[i] + 1] += 1
    for c in range(n_cells):
        start[c + 1] += start[c]
    fill = start[:-1].copy()
    members = np.empty(n, dtype=np.int64)
    for i in range(n):
        members[fill[cell_of[i]]] = i
        fill[cell_of[i]] += 1
    bd = np.empty(k)
    bi = np.empty(k, dtype=np.int64)
    max_r = max(dims[0], dims[1], dims[2])
    for i in range(n):
        for j in range(k):
            bd[j] = np.inf
            bi[j] = n
        c0, c1, c2 = ci[i, 0], ci[i, 1], ci[i, 2]
        # distance from the point to its own cell's faces (the shell bound grows by h per shell)
        margin = np.inf
        for u in range(3):
            off = pts[i, u] - (lo[u] + ci[i, u] * h)
            margin = min(margin, off, h - off)
        margin = max(margin, 0.0)
        for r in range(max_r + 1):
            if r > 0:
                reach = margin + (r - 1) * h  # every point in shell r lies at least this far
                if reach * reach > bd[k - 1]:
                    break
            for a in range(max(c0 - r, 0), min(c0 + r, dims[0] - 1) + 1):
                for b in range(max(c1 - r, 0), min(c1 + r, dims[1] - 1) + 1):
                    on_a = a == c0 - r or a == c0 + r
                    on_b = b == c1 - r or b == c1 + r
                    step = 1 if (on_a or on_b) else 2 * r
                    cz = max(c2 - r, 0)
                    while cz <= min(c2 + r, dims[2] - 1):
                        if not (on_a or on_b or cz == c2 - r or cz == c2 + r):
                            cz = c2 + r  # inside the shell: already visited
                            continue
                        c = (a * dims[1] + b) * dims[2] + cz
                        for q in range(start[c], start[c + 1]):
                            m = members[q]
                            e0 = pts[i, 0] - pts[m, 0]
                            e1 = pts[i, 1] - pts[m, 1]
                            e2 = pts[i, 2] - pts[m, 2]
                            dd = e0 * e0 + e1 * e1 + e2 * e2
                            if dd < bd[k - 1] or (dd == bd[k - 1] and m < bi[k - 1]):
                                j = k - 1
                                while j > 0 and (bd[j - 1] > dd or (bd[j - 1] == dd and bi[j - 1] > m)):
                                    bd[j] = bd[j - 1]
                                    bi[j] = bi[j - 1]
                                    j -= 1
                                bd[j] = dd
                                bi[j] = m
                        cz += step if r > 0 else 1
        for j in range(k):
            out[i, j] = bi[j]
    return out


@njit(cache=True, nogil=True)
def radius_neighbours(pts, k, radius):  # type: ignore[no-untyped-def]
    """Each point's k - 1 nearest other points within `radius` metres, as `features.fpfh` had them from
    cKDTree.query(k, distance_upper_bound): (N, k - 1) indices (0 where none), distances (1.0 where none) and
    validity; the point itself (the nearest, column 0 of `knn_points`) is left out. Distances are
    sqrt(e0^2 + e1^2 + e2^2) summed in that order, a neighbour counts when its squared distance is below radius^2."""
    n = pts.shape[0]
    nb = knn_points(pts, k)
    kk = nb.shape[1] - 1 if nb.shape[1] > 0 else 0
    idx = np.zeros((n, kk), dtype=np.int64)
    dist = np.ones((n, kk))
    valid = np.zeros((n, kk), dtype=np.bool_)
    lim = radius * radius
    for i in range(n):
        for j in range(kk):
            m = nb[i, j + 1]
            e0 = pts[i, 0] - pts[m, 0]
            e1 = pts[i, 1] - pts[m, 1]
            e2 = pts[i, 2] - pts[m, 2]
            dd = e0 * e0 + e1 * e1 + e2 * e2
            if dd < lim:
                idx[i, j] = m
                dist[i, j] = math.sqrt(dd)
                valid[i, j] = True
    return idx, dist, valid


@njit(cache=True, nogil=True)
def voxel_first(points, voxel):  # type: ignore[no-untyped-def]
    """`features.voxel_downsample`: sorted indices of one point per occupied voxel, the one nearest the voxel
    centre (lowest index among equal distances), with the same arithmetic (key = floor(p / voxel),
    offset = p / voxel - key - 0.5)."""
    n = points.shape[0]
    key = np.empty((n, 3), dtype=np.int64)
    dd = np.empty(n)
    for i in range(n):
        acc = 0.0
        for u in range(3):
            f = points[i, u] / voxel
            kf = math.floor(f)
            key[i, u] = int(kf)
            o = f - float(key[i, u]) - 0.5
            acc += o * o
        dd[i] = acc
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    lo = key[0].copy()
    hi = key[0].copy()
    for i in range(n):
        for u in range(3):
            lo[u] = min(lo[u], key[i, u])
            hi[u] = max(hi[u], key[i, u])
    s1 = hi[1] - lo[1] + 1
    s2 = hi[2] - lo[2] + 1
    s0 = hi[0] - lo[0] + 1
    if s0 < (1 << 20) and s1 < (1 << 20) and s2 < (1 << 20):
        comb = np.empty(n, dtype=np.int64)
        for i in range(n):
            comb[i] = ((key[i, 0] - lo[0]) * s1 + (key[i, 1] - lo[1])) * s2 + (key[i, 2] - lo[2])
        order = np.argsort(comb, kind="mergesort")
    else:  # lexicographic by stable sorts (last key first)
        order = np.argsort(key[:, 2], kind="mergesort")
        order = order[np.argsort(key[order, 1], kind="mergesort")]
        order = order[np.argsort(key[order, 0], kind="mergesort")]
    out = np.empty(n, dtype=np.int64)
    m = 0
    g = 0
    while g < n:
        best = order[g]
        e = g + 1
        while e < n:
            c = order[e]
            if key[c, 0] != key[best, 0] or key[c, 1] != key[best, 1] or key[c, 2] != key[best, 2]:
                break
            if dd[c] < dd[best]:
                best = c
            e += 1
        out[m] = best
        m += 1
        g = e
    res = out[:m].copy()
    res.sort()
    return res


# -- fit helpers (hypothesis bookkeeping and the full pose score, one call each) ----------------------------------


@njit(cache=True, nogil=True)
def poses_near(a, b, max_dt, min_cos):  # type: ignore[no-untyped-def]
    """Whether (4, 4) poses a and b differ by less than max_dt metres in translation and by a rotation whose
    (trace - 1) / 2 exceeds min_cos (as `fit._near`)."""
    d0 = a[0, 3] - b[0, 3]
    d1 = a[1, 3] - b[1, 3]
    d2 = a[2, 3] - b[2, 3]
    dt = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    tr = 0.0
    for i in range(3):
        tr += a[i, 0] * b[i, 0] + a[i, 1] * b[i, 1] + a[i, 2] * b[i, 2]
    return dt < max_dt and (tr - 1.0) / 2.0 > min_cos


@njit(cache=True, nogil=True)
def distinct_poses(poses, order, max_dt, min_cos, n):  # type: ignore[no-untyped-def]
    """Up to n indices of (H, 4, 4) poses, taken in `order` (H,), none near an earlier chosen one (`poses_near`)."""
    chosen = np.empty(n, dtype=np.int64)
    m = 0
    for i in order:
        if m >= n:
            break
        ok = True
        for c in range(m):
            if poses_near(poses[i], poses[chosen[c]], max_dt, min_cos):
                ok = False
                break
        if ok:
            chosen[m] = i
            m += 1
    return chosen[:m]


@njit(cache=True, nogil=True)
def add_sym(sub, syms, pa, scale_b, pose_b):  # type: ignore[no-untyped-def]
    """Smallest mean distance between posed points pa (N, 3) and template points sub (N, 3) relabelled by each
    symmetry (M, 4, 4), scaled by scale_b and posed by the inverse of object_from_frame pose_b (as `fit._add_sym`)."""
    n = sub.shape[0]
    best = np.inf
    for k in range(syms.shape[0]):
        acc = 0.0
        for i in range(n):
            s0, s1, s2 = sub[i, 0], sub[i, 1], sub[i, 2]
            q0 = (s0 * syms[k, 0, 0] + s1 * syms[k, 0, 1] + s2 * syms[k, 0, 2] + syms[k, 0, 3]) * scale_b - pose_b[0, 3]
            q1 = (s0 * syms[k, 1, 0] + s1 * syms[k, 1, 1] + s2 * syms[k, 1, 2] + syms[k, 1, 3]) * scale_b - pose_b[1, 3]
            q2 = (s0 * syms[k, 2, 0] + s1 * syms[k, 2, 1] + s2 * syms[k, 2, 2] + syms[k, 2, 3]) * scale_b - pose_b[2, 3]
            dd = 0.0
            for v in range(3):
                e = pa[i, v] - (q0 * pose_b[0, v] + q1 * pose_b[1, v] + q2 * pose_b[2, v])
                dd += e * e
            acc += math.sqrt(dd)
        best = min(best, acc / n)
    return best


@njit(cache=True, nogil=True)
def fit_stats_many(r, d, scales, thr, spacing, beside_spacings, beside_thr, neighbours, k, floor_m):  # type: ignore[no-untyped-def]
    """`fit_stats` of each row of r, d (H, P) with scales (H,): inlier ratio, RMSE and consistency, (H,) each."""
    h = r.shape[0]
    ratio = np.empty(h)
    rmse = np.empty(h)
    cons = np.empty(h)
    for i in range(h):
        ratio[i], rmse[i], cons[i] = fit_stats(
            r[i], d[i], scales[i], thr, spacing, beside_spacings, beside_thr, neighbours, k, floor_m
        )
    return ratio, rmse, cons


@njit(cache=True, nogil=True)
def depth_scores(samples, normals, cfo, scale, spacing, fx, fy, cx, cy, depth, tol, rad, front_lim):  # type: ignore[no-untyped-def]
    """Depth-image evidence of one pose in a pinhole camera (no distortion), in one call: `visible_points`,
    `project_pinhole`, then `depth_evidence` and `silhouette_evidence` from one scan of each point's window.
    Returns (n_visible, supported, inside and not occluded, violating, missing, not grazing, occluded,
    explained, front)."""
    pv, nv = visible_points(samples, normals, cfo, scale, spacing)
    if pv.shape[0] == 0:
        return 0, 0, 0, 0, 0, 0, 0, 0, 0
    uv = project_pinhole(pv, fx, fy, cx, cy)
    hgt, wid = depth.shape
    n_sup = n_den = n_vio = n_mis = n_ng = n_occ = n_exp = n_front = 0
    see_lim = max(3.0 * tol, 0.01)
    for i in range(pv.shape[0]):
        u = uv[i, 0]
        v = uv[i, 1]
        if not (u >= 0 and u < wid and v >= 0 and v < hgt):
            continue
        z = pv[i, 2]
        plen = math.sqrt(pv[i, 0] ** 2 + pv[i, 1] ** 2 + z * z)
        grazing = abs(nv[i, 0] * pv[i, 0] + nv[i, 1] * pv[i, 1] + nv[i, 2] * z) < 0.3 * plen
        meas = depth[v, u]
        valid = meas > 0 and np.isfinite(meas)
        occluded = valid and meas - z < -tol
        nearest, closest = _window_support(depth, u, v, rad, z, tol)
        if occluded:
            n_occ += 1
        else:
            n_den += 1
            if closest <= tol:
                n_sup += 1
        if not grazing:
            n_ng += 1
            if np.isfinite(nearest):
                if nearest - z > see_lim:
                    n_vio += 1
            else:
                n_mis += 1
        if closest <= tol:
            n_exp += 1
        elif valid and z - meas > tol and z - meas <= front_lim:
            n_front += 1
    return pv.shape[0], n_sup, n_den, n_vio, n_mis, n_ng, n_occ, n_exp, n_front


@njit(cache=True, nogil=True)
def consistent_triples(a, b, tol, min_edge, ia, distinct):  # type: ignore[no-untyped-def]
    """(T,) mask of point triples a, b (T, 3, 3) whose three edge lengths agree within tol, whose shortest edge
    of a exceeds min_edge and, with `distinct`, whose index triple ia (T, 3) has no repeat (as
    `features.ransac_hypotheses` and `control_points.control_point_hypotheses`)."""
    n = a.shape[0]
    ok = np.zeros(n, dtype=np.bool_)
    for t in range(n):
        if distinct and (ia[t, 0] == ia[t, 1] or ia[t, 1] == ia[t, 2] or ia[t, 0] == ia[t, 2]):
            continue
        good = True
        for e in range(3):
            f = (e + 1) % 3
            da = math.sqrt(
                (a[t, e, 0] - a[t, f, 0]) ** 2 + (a[t, e, 1] - a[t, f, 1]) ** 2 + (a[t, e, 2] - a[t, f, 2]) ** 2
            )
            db = math.sqrt(
                (b[t, e, 0] - b[t, f, 0]) ** 2 + (b[t, e, 1] - b[t, f, 1]) ** 2 + (b[t, e, 2] - b[t, f, 2]) ** 2
            )
            if not (abs(da - db) < tol and da > min_edge):
                good = False
                break
        ok[t] = good
    return ok


@njit(cache=True, nogil=True)
def near_surface_share(poses, pts, samples, grid_origin, grid_cell, grid_index, lim):  # type: ignore[no-untyped-def]
    """(H,) share of points pts (P, 3) that (H, 4, 4) poses put inside the distance grid within lim metres of
    the grid cell's nearest sample (the RANSAC hypotheses' quick score, as `prepared.grid_lookup`)."""
    h = poses.shape[0]
    p = pts.shape[0]
    g = grid_index.shape[0]
    out = np.zeros(h)
    for a in range(h):
        cnt = 0
        for q in range(p):
            x0, x1, x2 = pts[q, 0], pts[q, 1], pts[q, 2]
            y0 = poses[a, 0, 0] * x0 + poses[a, 0, 1] * x1 + poses[a, 0, 2] * x2 + poses[a, 0, 3]
            y1 = poses[a, 1, 0] * x0 + poses[a, 1, 1] * x1 + poses[a, 1, 2] * x2 + poses[a, 1, 3]
            y2 = poses[a, 2, 0] * x0 + poses[a, 2, 1] * x1 + poses[a, 2, 2] * x2 + poses[a, 2, 3]
            f0 = math.floor((y0 - grid_origin[0]) / grid_cell)
            f1 = math.floor((y1 - grid_origin[1]) / grid_cell)
            f2 = math.floor((y2 - grid_origin[2]) / grid_cell)
            if not (0 <= f0 < g and 0 <= f1 < g and 0 <= f2 < g):
                continue
            s = grid_index[int(f0), int(f1), int(f2)]
            e0 = y0 - samples[s, 0]
            e1 = y1 - samples[s, 1]
            e2 = y2 - samples[s, 2]
            if math.sqrt(e0 * e0 + e1 * e1 + e2 * e2) < lim:
                cnt += 1
        out[a] = cnt / p
    return out
