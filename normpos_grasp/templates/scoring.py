"""Scoring a template pose against the measurement: inliers, RMSE, visible-surface coverage, free space.

The template's camera-visible surface is found by back-face culling and a z-buffer seen from the camera.
Free-space violation: visible template surface lying clearly in FRONT of what the sensor measured along the
same ray (the sensor saw through where the template claims matter): impossible for a right pose.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from normpos_grasp.camera.model import Camera
from normpos_grasp.errors import InputError
from normpos_grasp.geometry.transforms import invert_pose, look_at
from normpos_grasp.templates import kernels
from normpos_grasp.templates.icp import candidates, correspond
from normpos_grasp.templates.prepared import PreparedTemplate
from normpos_grasp.typing import BoolArray, FloatArray, IntArray

FREE_SPACE_WINDOW_PX = 2
#: the band in front of the model (in inlier distances) where a measured surface counts as unexplained, not as
#: a separate occluder
FRONT_LIMIT_TOL = 3.0
#: an inlier's offset along the template surface (beside it, past an edge) is at most this many sample spacings
#: or this share of its inlier distance
BESIDE_SPACINGS = 1.5
BESIDE_THR = 0.35


@dataclass(frozen=True)
class PoseScore:
    """Evaluation of one pose. Shares in [0, 1]; rmse_m metres; n_visible template samples seen.

    explained_share: share of ALL camera-visible template samples (occluded and outside the image included) that
    measured depth explains; front_share: share of them under a measured surface running just in front of the
    model (between tol and `FRONT_LIMIT_TOL` tol): measured points inside the silhouette the pose leaves
    unexplained. Both from the depth image (1.0 and 0.0 without one).
    """

    score: float
    inlier_ratio: float
    rmse_m: float
    coverage: float
    free_space_violation: float
    n_visible: int
    occluded_share: float
    consistency: float = 1.0
    explained_share: float = 1.0
    front_share: float = 0.0


def visible_samples(
    prep: PreparedTemplate, frame_from_object: FloatArray, scale: float, camera_from_frame: FloatArray
) -> tuple[BoolArray, FloatArray]:
    """(S,) mask of template samples visible from the camera (culling + z-buffer) and their (S, 3) camera points."""
    cfo = camera_from_frame @ frame_from_object
    pc = (prep.samples * scale) @ cfo[:3, :3].T + cfo[:3, 3]
    nc = prep.normals @ cfo[:3, :3].T
    return kernels.visible_mask(pc, nc, prep.spacing * scale), pc


def score_bounds(
    prep: PreparedTemplate,
    object_from_frame: FloatArray,
    scales: FloatArray,
    pts: FloatArray,
    nrm: FloatArray,
    thr: FloatArray,
    neighbours: IntArray | None = None,
    thr_median: float | None = None,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Upper bounds (H,) of `evaluate`'s score for (H, 4, 4) poses with (H,) scales, from one batched query.

    The bound is the score with perfect coverage and no free-space violation (inliers, RMSE and consistency
    exactly as `evaluate` computes them), so a pose whose bound is below a threshold can be dropped without
    the costly visibility tests. Also returns the residuals r (H, P) and distances d (H, P) for `evaluate`.
    """
    h, p = len(object_from_frame), len(pts)
    if h == 0 or p == 0:
        return np.zeros(h), np.zeros((h, p)), np.full((h, p), np.inf)
    r, d = kernels.correspond_posed(
        np.ascontiguousarray(object_from_frame, dtype=np.float64),
        np.ascontiguousarray(scales, dtype=np.float64),
        np.ascontiguousarray(pts, dtype=np.float64),
        np.ascontiguousarray(nrm, dtype=np.float64),
        True,
        # beyond this no point counts as near in `_fit_stats` (see there), so farther distances may be inf
        max(3.0 * float(np.max(thr)) / float(np.min(scales)), 2.0 * prep.spacing) * 1.001,
        prep.samples,
        prep.normals,
        prep.grid,
        prep.kd,
        candidates(prep),
    )
    tol = float(np.median(thr)) if thr_median is None else thr_median
    nb = neighbours if neighbours is not None else consistency_neighbours(pts)
    ratio, rmse, consistency = kernels.fit_stats_many(
        r,
        d,
        np.ascontiguousarray(scales, dtype=np.float64),
        np.ascontiguousarray(thr, dtype=np.float64),
        prep.spacing,
        BESIDE_SPACINGS,
        BESIDE_THR,
        nb,
        nb.shape[1],
        SYSTEMATIC_FLOOR_M,
    )
    bound = np.array([_combine(ratio[i], rmse[i], 1.0, 0.0, tol) * consistency[i] for i in range(h)])
    return bound, r, d


def _fit_stats(
    prep: PreparedTemplate,
    r: FloatArray,
    d: FloatArray,
    scale: float,
    pts: FloatArray,
    thr: FloatArray,
    neighbours: IntArray | None,
) -> tuple[float, float, float]:
    """Inlier ratio, inlier RMSE (metres, inf without inliers) and consistency from (P,) residuals / distances
    (`kernels.fit_stats`; `neighbours` from `consistency_neighbours(pts)`, computed when None)."""
    r = np.ascontiguousarray(r, dtype=np.float64)
    d = np.ascontiguousarray(d, dtype=np.float64)
    thr = np.ascontiguousarray(thr, dtype=np.float64)
    nb = neighbours if neighbours is not None else consistency_neighbours(pts)
    inlier_ratio, rmse, consistency = kernels.fit_stats(
        r, d, float(scale), thr, prep.spacing, BESIDE_SPACINGS, BESIDE_THR, nb, nb.shape[1], SYSTEMATIC_FLOOR_M
    )
    return inlier_ratio, rmse, consistency


def evaluate(
    prep: PreparedTemplate,
    object_from_frame: FloatArray,
    scale: float,
    pts: FloatArray,
    nrm: FloatArray,
    thr: FloatArray,
    meas_tree: cKDTree | None,
    viewpoint: FloatArray,
    *,
    camera: Camera | None = None,
    depth_m: FloatArray | None = None,
    camera_from_frame: FloatArray | None = None,
    neighbours: IntArray | None = None,
    corr: tuple[FloatArray, FloatArray] | None = None,
    thr_median: float | None = None,
) -> PoseScore:
    """Score one pose. pts/nrm (P, 3): measured points/normals used for inliers; thr (P,) inlier distances.

    meas_tree: KD-tree over ALL measured points (frame). With camera + depth_m (H, W metres) +
    camera_from_frame, coverage and free space use the depth image (occlusion aware, sees the whole
    silhouette; meas_tree may be None); without, a virtual camera at `viewpoint` and the measured points
    themselves (meas_tree required).
    neighbours: `consistency_neighbours(pts)` when precomputed; corr: (P,) residuals and distances of `pts`
    at this pose when precomputed (`score_bounds`); thr_median: median of thr when known.
    """
    if corr is None:
        y = (pts @ object_from_frame[:3, :3].T + object_from_frame[:3, 3]) / scale
        ny = nrm @ object_from_frame[:3, :3].T
        r, d, _ = correspond(prep, y, ny, exact=True)
    else:
        r, d = corr
    inlier_ratio, rmse, consistency = _fit_stats(prep, r, d, scale, pts, thr, neighbours)
    tol = float(np.median(thr)) if thr_median is None else thr_median
    frame_from_object = np.eye(4)  # rigid inverse
    frame_from_object[:3, :3] = object_from_frame[:3, :3].T
    frame_from_object[:3, 3] = -object_from_frame[:3, :3].T @ object_from_frame[:3, 3]
    if camera is not None and depth_m is not None and camera_from_frame is not None:
        cff = camera_from_frame
    else:
        if meas_tree is None:
            raise InputError("evaluate without a depth image needs meas_tree (a KD-tree of the measured points)")
        camera = depth_m = None
        centre = meas_tree.data.mean(axis=0)
        cff = invert_pose(look_at(viewpoint, centre, up=_any_up(centre - viewpoint)))
    cfo = np.ascontiguousarray(cff @ frame_from_object, dtype=np.float64)
    if camera is not None and depth_m is not None and not camera.has_distortion:
        n_vis, n_sup, n_den, n_vio, n_mis, n_ng, n_occ, n_exp, n_front = kernels.depth_scores(
            prep.samples,
            prep.normals,
            cfo,
            float(scale),
            prep.spacing,
            camera.fx,
            camera.fy,
            camera.cx,
            camera.cy,
            np.ascontiguousarray(depth_m, dtype=np.float64),
            tol,
            FREE_SPACE_WINDOW_PX,
            FRONT_LIMIT_TOL * tol,
        )
        if n_vis == 0:
            return PoseScore(0.0, inlier_ratio, rmse, 0.0, 1.0, 0, 0.0, consistency)
        coverage = float(n_sup) / max(n_den, 1)
        fsv = float(n_vio + 0.5 * n_mis) / max(n_ng, 1)
        score = _combine(inlier_ratio, rmse, coverage, fsv, tol) * consistency
        return PoseScore(
            score,
            inlier_ratio,
            rmse,
            coverage,
            fsv,
            n_vis,
            float(n_occ) / n_vis,
            consistency,
            n_exp / n_vis,
            n_front / n_vis,
        )
    pv, nv = kernels.visible_points(prep.samples, prep.normals, cfo, float(scale), prep.spacing)
    n_vis = len(pv)
    if n_vis == 0:
        return PoseScore(0.0, inlier_ratio, rmse, 0.0, 1.0, 0, 0.0, consistency)
    if camera is not None and depth_m is not None:
        if camera.has_distortion:
            uv = np.rint(camera.project(pv))
            uv = np.where(np.isfinite(uv) & (np.abs(uv) < 1e9), uv, -1.0).astype(np.int64)
        else:
            uv = kernels.project_pinhole(pv, camera.fx, camera.fy, camera.cx, camera.cy)
        n_sup, n_den, n_vio, n_mis, n_ng, n_occ = kernels.depth_evidence(
            pv, nv, uv, np.ascontiguousarray(depth_m, dtype=np.float64), tol, FREE_SPACE_WINDOW_PX
        )
        # see-through test on the nearest valid depth in a small window: robust to depth edges that are
        # misaligned by a pixel or two (stereo and Kinect depth both shift silhouettes); camera-facing template
        # surface where the sensor returned nothing within the window is unexplained (half weight); support:
        # some depth within the window agrees; occluded points are out of numerator and denominator
        coverage = float(n_sup) / max(n_den, 1)
        fsv = float(n_vio + 0.5 * n_mis) / max(n_ng, 1)
        occ_share = float(n_occ) / n_vis
        _, n_exp, n_front = kernels.silhouette_evidence(
            pv, uv, np.ascontiguousarray(depth_m, dtype=np.float64), tol, FREE_SPACE_WINDOW_PX, FRONT_LIMIT_TOL * tol
        )
        explained = float(n_exp) / n_vis
        front = float(n_front) / n_vis
    elif meas_tree is not None:  # (never None here: checked above)
        grazing = np.abs(np.einsum("ij,ij->i", nv, pv)) < 0.3 * np.linalg.norm(pv, axis=1)
        world_v = pv @ invert_pose(cff)[:3, :3].T + invert_pose(cff)[:3, 3]
        dd, _ = meas_tree.query(world_v, distance_upper_bound=2.0 * tol + prep.spacing * scale)
        supported = np.isfinite(dd)
        coverage = float(supported.mean())
        # z-buffer of the measured points in the same virtual camera
        mp = meas_tree.data @ cff[:3, :3].T + cff[:3, 3]
        cell = 1.6 * prep.spacing * scale / float(np.median(pv[:, 2]))
        zmin = _zbuffer(mp, cell)
        key = _cell_keys(pv, cell)
        has = np.isin(key, zmin[0])
        zm = np.full(len(pv), np.nan)
        pos = np.searchsorted(zmin[0], key[has])
        zm[has] = zmin[1][pos]
        violating = has & ~grazing & (np.nan_to_num(zm, nan=0.0) - pv[:, 2] > np.maximum(3.0 * tol, 0.01))
        fsv = float(violating.sum()) / max(int((~grazing).sum()), 1)
        occ_share = 0.0
        explained, front = 1.0, 0.0
    score = _combine(inlier_ratio, rmse, coverage, fsv, tol) * consistency
    return PoseScore(score, inlier_ratio, rmse, coverage, fsv, n_vis, occ_share, consistency, explained, front)


def _combine(inlier_ratio: float, rmse: float, coverage: float, fsv: float, tol: float) -> float:
    if not math.isfinite(rmse):
        return 0.0
    fit = math.exp(-0.5 * (rmse / max(tol, 1e-6)) ** 2)
    return min(
        max(float(inlier_ratio * (0.5 + 0.5 * fit) * min(1.0, coverage / 0.9) ** 2 * (1.0 - fsv) ** 2), 0.0), 1.0
    )


SMOOTH_K = 16
#: residual floor for the consistency test (CAD vs part deviations, sampling), metres
SYSTEMATIC_FLOOR_M = 0.0012


def consistency_neighbours(pts: FloatArray) -> IntArray:
    """(P, k) indices of each point's k = min(16, P) nearest points (itself included), for `evaluate`."""
    if len(pts) == 0:
        return np.zeros((0, 0), dtype=np.int64)
    return kernels.knn_points(np.ascontiguousarray(pts, dtype=np.float64), SMOOTH_K)


def _consistency(
    pts: FloatArray, r: FloatArray, near: BoolArray, thr: FloatArray, neighbours: IntArray | None = None
) -> float:
    """Share of points whose neighbourhood-mean residual is within noise: a wrong template leaves
    spatially coherent residuals that averaging does not remove, while sensor noise averages out.
    thr is 2.5 sigma per point; points without a correspondence count as inconsistent."""
    n = len(pts)
    if n < 4:
        return 0.0
    k = min(SMOOTH_K, n)
    idx = neighbours if neighbours is not None else consistency_neighbours(pts)
    rr = np.where(near, r, np.nan)[idx]
    cnt = np.sum(np.isfinite(rr), axis=1)
    mean = np.nansum(rr, axis=1) / np.maximum(cnt, 1)
    sigma = thr / 2.5
    lim = np.maximum(SYSTEMATIC_FLOOR_M, 3.0 * sigma / np.sqrt(np.maximum(cnt, 1)))
    ok = near & (cnt >= k // 2) & (np.abs(mean) <= lim)
    return float(ok.mean())


def _cell_keys(pc: FloatArray, cell: float) -> FloatArray:
    uv = np.floor(pc[:, :2] / np.maximum(pc[:, 2], 1e-3)[:, None] / cell).astype(np.int64)
    return (uv[:, 0] * 1_000_003 + uv[:, 1]).astype(np.int64)


def _zbuffer(pc: FloatArray, cell: float) -> tuple[FloatArray, FloatArray]:
    """Sorted unique cell keys and the nearest z per cell."""
    key = _cell_keys(pc, cell)
    order = np.lexsort((pc[:, 2], key))
    ks = key[order]
    first = np.ones(len(order), dtype=bool)
    first[1:] = ks[1:] != ks[:-1]
    return ks[first], pc[order, 2][first]


def _any_up(direction: FloatArray) -> FloatArray:
    d = direction / max(float(np.linalg.norm(direction)), 1e-12)
    up = np.array([0.0, 0.0, 1.0])
    if abs(float(d @ up)) > 0.95:
        up = np.array([0.0, 1.0, 0.0])
    return up
