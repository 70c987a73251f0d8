"""Local shape descriptors (FPFH-style) and descriptor-matched RANSAC pose hypotheses, vectorised with numpy."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from normpos_grasp.templates import kernels
from normpos_grasp.typing import FloatArray, IntArray

N_BINS = 11
K_NEIGHBOURS = 12


def voxel_downsample(points: FloatArray, voxel: float) -> IntArray:
    """Indices (V,) of one point per occupied voxel of size `voxel` (metres), the one nearest the voxel centre
    (lowest index among equal distances), ascending (compiled: `kernels.voxel_first`; `voxel_downsample_reference`
    is the numpy form it is tested against)."""
    return kernels.voxel_first(np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3), float(voxel))


def voxel_downsample_reference(points: FloatArray, voxel: float) -> IntArray:
    """`voxel_downsample` in plain numpy."""
    key = np.floor(points / voxel).astype(np.int64)
    off = points / voxel - key - 0.5
    d = np.einsum("ij,ij->i", off, off)
    order = np.lexsort((d, key[:, 2], key[:, 1], key[:, 0]))
    ks = key[order]
    first = np.ones(len(order), dtype=bool)
    first[1:] = np.any(ks[1:] != ks[:-1], axis=1)
    return np.sort(order[first])


def fpfh(points: FloatArray, normals: FloatArray, radius: float) -> FloatArray:
    """(N, 33) fast point feature histograms (Rusu 2009) of (N, 3) points with unit normals.

    Neighbourhoods: up to 12 nearest neighbours within `radius` metres (`kernels.radius_neighbours`; the numpy
    `fpfh_reference` takes them from a cKDTree). Each histogram is normalised to sum 1 per angle (3 x 11 bins).
    """
    pts = np.ascontiguousarray(points, dtype=np.float64)
    idx, dist, valid = kernels.radius_neighbours(pts, min(K_NEIGHBOURS + 1, len(pts)), float(radius))
    return kernels.fpfh_histograms(pts, np.ascontiguousarray(normals, dtype=np.float64), idx, dist, valid, N_BINS)


def fpfh_reference(points: FloatArray, normals: FloatArray, radius: float) -> FloatArray:
    """`fpfh` in plain numpy (the reference the compiled kernel is tested against)."""
    n = len(points)
    k = min(K_NEIGHBOURS + 1, n)
    dist, idx = cKDTree(points).query(points, k=k, distance_upper_bound=radius)
    dist = dist[:, 1:]
    idx = idx[:, 1:]
    valid = np.isfinite(dist) & (idx < n)
    idx = np.where(valid, idx, 0)
    spfh = _spfh(points, normals, idx, valid)
    w = np.where(valid, 1.0 / np.maximum(np.where(valid, dist, 1.0), 1e-9), 0.0)
    cnt = valid.sum(1)
    neigh = np.einsum("nk,nkd->nd", w, spfh[idx]) / np.maximum(cnt, 1)[:, None]
    wsum = np.maximum(w.sum(1), 1e-12) / np.maximum(cnt, 1)
    out = spfh + neigh / wsum[:, None]
    out = out.reshape(n, 3, N_BINS)
    out = out / np.maximum(out.sum(-1, keepdims=True), 1e-12)
    return out.reshape(n, 3 * N_BINS)


def _spfh(points: FloatArray, normals: FloatArray, idx: IntArray, valid: np.ndarray) -> FloatArray:
    n, k = idx.shape
    ps = points[:, None, :]
    ns = np.broadcast_to(normals[:, None, :], (n, k, 3))
    pt = points[idx]
    nt = normals[idx]
    d = pt - ps
    dn = np.linalg.norm(d, axis=-1, keepdims=True)
    dn = np.where(dn < 1e-12, 1.0, dn)
    d = d / dn
    u = ns
    v = np.cross(u, d)
    vn = np.linalg.norm(v, axis=-1, keepdims=True)
    v = v / np.where(vn < 1e-12, 1.0, vn)
    w = np.cross(u, v)
    alpha = np.einsum("nkd,nkd->nk", v, nt)
    phi = np.einsum("nkd,nkd->nk", u, d)
    # a neighbour normal in the u-v plane has w.n_j = +-0 up to rounding: +0 (theta = +pi), not a coin flip
    wn = np.einsum("nkd,nkd->nk", w, nt)
    theta = np.arctan2(np.where(np.abs(wn) < 1e-12, 0.0, wn), np.einsum("nkd,nkd->nk", u, nt))
    b1 = np.clip(((alpha + 1) / 2 * N_BINS).astype(np.int64), 0, N_BINS - 1)
    b2 = np.clip(((phi + 1) / 2 * N_BINS).astype(np.int64), 0, N_BINS - 1)
    b3 = np.clip(((theta + np.pi) / (2 * np.pi) * N_BINS).astype(np.int64), 0, N_BINS - 1)
    rows = np.repeat(np.arange(n), k).reshape(n, k)
    hist = np.zeros(n * 3 * N_BINS)
    for j, b in enumerate((b1, b2, b3)):
        flat = rows * 3 * N_BINS + j * N_BINS + b
        hist += np.bincount(flat[valid], minlength=n * 3 * N_BINS)
    hist = hist.reshape(n, 3 * N_BINS)
    return hist / np.maximum(valid.sum(1), 1)[:, None]


def batched_kabsch(src: FloatArray, dst: FloatArray) -> FloatArray:
    """(B, 4, 4) `dst_from_src` for (B, P, 3) corresponding point sets, det(R) = +1 (no scaling)."""
    cs = src.mean(1, keepdims=True)
    cd = dst.mean(1, keepdims=True)
    h = np.einsum("bpi,bpj->bij", dst - cd, src - cs)
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(u @ vt))
    d = np.where(d == 0, 1.0, d)
    u = u.copy()
    u[:, :, 2] *= d[:, None]
    rot = u @ vt
    out = np.tile(np.eye(4), (len(src), 1, 1))
    out[:, :3, :3] = rot
    out[:, :3, 3] = cd[:, 0] - np.einsum("bij,bj->bi", rot, cs[:, 0])
    return out


def ransac_hypotheses(
    meas_pts: FloatArray,
    meas_desc: FloatArray,
    model_pts: FloatArray,
    desc_tree: cKDTree,
    *,
    n_iter: int,
    tol: float,
    min_edge: float,
    rng: np.random.Generator,
    n_candidates: int = 3,
) -> FloatArray:
    """(B, 4, 4) `object_from_frame` hypotheses from 3-point descriptor correspondences.

    meas_pts (N, 3) with descriptors (N, 33); model_pts (F, 3) are the points of `desc_tree`'s descriptors.
    Triples are kept when all three edge lengths agree within `tol` metres and the shortest edge exceeds
    `min_edge`; each surviving triple gives one Kabsch pose. Returns (0, 4, 4) when nothing survives.
    """
    n = len(meas_pts)
    if n < 3:
        return np.zeros((0, 4, 4))
    kc = min(n_candidates, len(model_pts))
    cand = kernels.nearest_rows(
        np.ascontiguousarray(meas_desc, dtype=np.float64),
        np.ascontiguousarray(np.asarray(desc_tree.data, dtype=np.float64).T),
        kc,
    )
    tri = rng.integers(0, n, size=(n_iter, 3))
    pick = rng.integers(0, kc, size=(n_iter, 3))
    mi = cand[tri, pick]
    a = meas_pts[tri]
    b = model_pts[mi]
    ok = kernels.consistent_triples(a, b, float(tol), float(min_edge), tri, True)
    if not np.any(ok):
        return np.zeros((0, 4, 4))
    return batched_kabsch(a[ok], b[ok])
