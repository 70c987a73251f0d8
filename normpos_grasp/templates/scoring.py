"""Scoring a template pose against the measurement: inliers, RMSE, visible-surface coverage, free space.

The template's camera-visible surface is found by back-face culling and a z-buffer seen from the camera.
Free-space violation: visible template surface lying clearly in FRONT of what the sensor measured along the
same ray (the sensor saw through where the template claims matter): impossible for a right pose.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from normpos_grasp.camera.model import Camera
from normpos_grasp.geometry.transforms import invert_pose, look_at
from normpos_grasp.templates.icp import correspond
from normpos_grasp.templates.prepared import PreparedTemplate
from normpos_grasp.typing import BoolArray, FloatArray


@dataclass(frozen=True)
class PoseScore:
    """Evaluation of one pose. Shares in [0, 1]; rmse_m metres; n_visible template samples seen."""

    score: float
    inlier_ratio: float
    rmse_m: float
    coverage: float
    free_space_violation: float
    n_visible: int
    occluded_share: float


def visible_samples(
    prep: PreparedTemplate, frame_from_object: FloatArray, scale: float, camera_from_frame: FloatArray
) -> tuple[BoolArray, FloatArray]:
    """(S,) mask of template samples visible from the camera (culling + z-buffer) and their (S, 3) camera points."""
    cfo = camera_from_frame @ frame_from_object
    pc = (prep.samples * scale) @ cfo[:3, :3].T + cfo[:3, 3]
    nc = prep.normals @ cfo[:3, :3].T
    dist = np.linalg.norm(pc, axis=1)
    facing = np.einsum("ij,ij->i", nc, -pc) > 0.05 * dist
    facing &= pc[:, 2] > 1e-3
    if not np.any(facing):
        return facing, pc
    z = pc[:, 2]
    cell = 1.6 * prep.spacing * scale / float(np.median(z[facing]))
    uv = np.floor(pc[:, :2] / np.maximum(z, 1e-3)[:, None] / cell).astype(np.int64)
    idx = np.flatnonzero(facing)
    key = uv[idx, 0] * 1_000_003 + uv[idx, 1]
    order = np.lexsort((z[idx], key))
    ks = key[order]
    first = np.ones(len(order), dtype=bool)
    first[1:] = ks[1:] != ks[:-1]
    group = np.cumsum(first) - 1
    zmin = z[idx][order][first][group]
    vis_sorted = z[idx][order] <= zmin + 2.0 * prep.spacing * scale
    visible = np.zeros(len(z), dtype=bool)
    visible[idx[order[vis_sorted]]] = True
    return visible, pc


def evaluate(
    prep: PreparedTemplate,
    object_from_frame: FloatArray,
    scale: float,
    pts: FloatArray,
    nrm: FloatArray,
    thr: FloatArray,
    meas_tree: cKDTree,
    viewpoint: FloatArray,
    *,
    camera: Camera | None = None,
    depth_m: FloatArray | None = None,
    camera_from_frame: FloatArray | None = None,
) -> PoseScore:
    """Score one pose. pts/nrm (P, 3): measured points/normals used for inliers; thr (P,) inlier distances.

    meas_tree: KD-tree over ALL measured points (frame). With camera + depth_m (H, W metres) +
    camera_from_frame, coverage and free space use the depth image (occlusion aware, sees the whole
    silhouette); without, a virtual camera at `viewpoint` and the measured points themselves.
    """
    y = (pts @ object_from_frame[:3, :3].T + object_from_frame[:3, 3]) / scale
    ny = nrm @ object_from_frame[:3, :3].T
    r, d, _ = correspond(prep, y, ny, exact=True)
    near = d < np.maximum(3.0 * thr / scale, 2.0 * prep.spacing)
    inl = near & (np.abs(r) * scale < thr)
    inlier_ratio = float(inl.mean()) if len(inl) else 0.0
    rmse = float(np.sqrt(np.mean((r[inl] * scale) ** 2))) if np.any(inl) else float("inf")
    tol = float(np.median(thr))
    frame_from_object = invert_pose(object_from_frame)
    use_depth = camera is not None and depth_m is not None and camera_from_frame is not None
    if use_depth:
        assert camera_from_frame is not None  # for type checkers; guarded by use_depth
        cff = camera_from_frame
    else:
        centre = meas_tree.data.mean(axis=0)
        cff = invert_pose(look_at(viewpoint, centre, up=_any_up(centre - viewpoint)))
    visible, pc = visible_samples(prep, frame_from_object, scale, cff)
    n_vis = int(visible.sum())
    if n_vis == 0:
        return PoseScore(0.0, inlier_ratio, rmse, 0.0, 1.0, 0, 0.0)
    pv = pc[visible]
    nv = (prep.normals[visible]) @ (cff @ frame_from_object)[:3, :3].T
    grazing = np.abs(np.einsum("ij,ij->i", nv, pv)) < 0.3 * np.linalg.norm(pv, axis=1)
    if use_depth:
        assert camera is not None and depth_m is not None
        uv = np.rint(camera.project(pv)).astype(np.int64)
        inside = (uv[:, 0] >= 0) & (uv[:, 0] < camera.width) & (uv[:, 1] >= 0) & (uv[:, 1] < camera.height)
        meas = np.zeros(len(pv))
        meas[inside] = depth_m[uv[inside, 1], uv[inside, 0]]
        known = inside & (meas > 0) & np.isfinite(meas)
        diff = np.where(known, meas - pv[:, 2], 0.0)
        tol_z = np.maximum(tol, 3.0 * _noise(pv[:, 2], thr, tol))
        occluded = known & (diff < -tol_z)
        violating = known & (diff > np.maximum(3.0 * tol_z, 0.01)) & ~grazing
        supported = known & (np.abs(diff) <= tol_z)
        denom = max(int((known & ~occluded).sum()), 1)
        coverage = float(supported.sum()) / denom
        fsv = float(violating.sum()) / max(int((known & ~grazing).sum()), 1)
        occ_share = float(occluded.sum()) / n_vis
    else:
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
    score = _combine(inlier_ratio, rmse, coverage, fsv, tol)
    return PoseScore(score, inlier_ratio, rmse, coverage, fsv, n_vis, occ_share)


def _combine(inlier_ratio: float, rmse: float, coverage: float, fsv: float, tol: float) -> float:
    if not np.isfinite(rmse):
        return 0.0
    fit = float(np.exp(-0.5 * (rmse / max(tol, 1e-6)) ** 2))
    return float(np.clip(inlier_ratio * (0.5 + 0.5 * fit) * np.sqrt(min(1.0, coverage / 0.8)) * (1.0 - fsv) ** 2, 0, 1))


def _noise(z: FloatArray, thr: FloatArray, tol: float) -> FloatArray:
    return np.full(len(z), tol / 3.0)


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
