"""Norm-position measurement: instance masks + depth + camera -> world surface points, normals and summaries.

Pipeline per frame (the paper's section 3.1): depth window estimate (Eq. 6-7) once, then for every instance
the masked pixels are back-projected through the (undistorted) pixel rays (Eq. 1-4) and moved to the world
(Eq. 5) when the camera has `world_from_camera`. Normals come from central differences of the point map
inside the mask; centroid, axis-aligned box and a PCA oriented box summarise the points.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from normpos_grasp.atomic import atomic_write_text
from normpos_grasp.camera.model import Camera, RGBDFrame
from normpos_grasp.errors import InputError, MeasurementError
from normpos_grasp.geometry.transforms import transform_points
from normpos_grasp.measure.depth import DepthFillOptions, fill_depth
from normpos_grasp.records.instance import Instance
from normpos_grasp.records.kinds import Frame
from normpos_grasp.records.normpos import NormPosition, OrientedBox
from normpos_grasp.typing import ArrayLike, BoolArray, Float32Array, FloatArray, IntArray

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class MeasureOptions:
    """Settings of `measure_instances`.

    Attributes:
        depth: depth window estimate settings (Eq. 6-7); the default is edge-aware with S = 2.
        erode_px: erode each mask by this many pixels first (drops boundary pixels that mix object and
            background depth); 0 keeps the mask.
        min_points: fewest valid points for a measurement; fewer raises MeasurementError (or skips).
        skip_failed: True logs and skips instances that cannot be measured; False raises.
        normal_step_px: pixel step of the central differences used for normals.
        max_normal_jump_m: neighbours farther than this in depth (metres) are not used for a normal.
    """

    depth: DepthFillOptions = field(default_factory=lambda: DepthFillOptions(edge_aware=True))
    erode_px: int = 0
    min_points: int = 3
    skip_failed: bool = True
    normal_step_px: int = 2
    max_normal_jump_m: float = 0.02

    def __post_init__(self) -> None:
        if not (0 <= self.erode_px <= 100 and 1 <= self.normal_step_px <= 50 and self.min_points >= 3):
            raise InputError(
                f"need erode_px in 0..100, normal_step_px in 1..50 (pixels) and min_points >= 3; got "
                f"{self.erode_px}, {self.normal_step_px}, {self.min_points}"
            )
        if not self.max_normal_jump_m > 0:
            raise InputError(f"max_normal_jump_m must be > 0 metres, got {self.max_normal_jump_m}")


@dataclass(frozen=True)
class VoxelOccupancy:
    """Voxels holding at least one point: `indices` (M, 3) int64 of voxel (i, j, k) at `origin` + index *
    `voxel_size_m`; `volume_m3` = M * voxel_size_m^3 (occupied volume of the visible shell)."""

    voxel_size_m: float
    origin: FloatArray
    indices: IntArray

    @property
    def count(self) -> int:
        return int(self.indices.shape[0])

    @property
    def volume_m3(self) -> float:
        return self.count * self.voxel_size_m**3

    def centers(self) -> FloatArray:
        """(M, 3) voxel centres, metres."""
        return self.origin + (self.indices + 0.5) * self.voxel_size_m


# -------------------------------------------------------------------------------------------------
_RAY_CACHE: dict[tuple[bytes, bytes, int, int], FloatArray] = {}


def pixel_rays(camera: Camera) -> FloatArray:
    """(H, W, 2) undistorted normalised coordinates of every pixel, cached per intrinsics (read-only)."""
    key = (camera.K.tobytes(), camera.distortion.tobytes(), camera.width, camera.height)
    rays = _RAY_CACHE.get(key)
    if rays is None:
        if camera.has_distortion:
            rays = camera.pixel_grid_rays()
        else:
            u = (np.arange(camera.width) - camera.cx) / camera.fx
            v = (np.arange(camera.height) - camera.cy) / camera.fy
            rays = np.empty((camera.height, camera.width, 2))
            rays[:, :, 0] = u[None, :]
            rays[:, :, 1] = v[:, None]
        rays.setflags(write=False)
        if len(_RAY_CACHE) >= 8:
            _RAY_CACHE.pop(next(iter(_RAY_CACHE)))
        _RAY_CACHE[key] = rays
    return rays


def backproject_depth(camera: Camera, depth_m: ArrayLike) -> FloatArray:
    """(H, W) depth in metres -> (H, W, 3) camera-frame point map (0 where depth is 0), undistorted."""
    d = np.asarray(depth_m, dtype=np.float64)
    if d.shape != (camera.height, camera.width):
        raise InputError(f"depth must be ({camera.height}, {camera.width}), got {d.shape}")
    rays = pixel_rays(camera)
    out = np.empty((*d.shape, 3))
    out[:, :, 0] = rays[:, :, 0] * d
    out[:, :, 1] = rays[:, :, 1] * d
    out[:, :, 2] = d
    return out


def measure_instances(
    frame: RGBDFrame, instances: list[Instance], options: MeasureOptions | None = None
) -> list[NormPosition]:
    """Measure every instance of `frame`; returns NormPositions in instance order (failed ones skipped or
    raised, see `MeasureOptions.skip_failed`).

    The depth estimate runs on each mask's bounding box plus a margin of S + normal step pixels, which
    gives the same values as filling the whole image and costs only the masked area.
    """
    opts = MeasureOptions() if options is None else options
    raw = np.asarray(frame.depth_m, dtype=np.float64)
    out = []
    for inst in instances:
        try:
            out.append(_measure_one(frame.camera, raw, inst, opts))
        except MeasurementError as exc:
            if not opts.skip_failed:
                raise
            logger.warning("instance %d (%s) skipped: %s", inst.instance_id, inst.label or "?", exc)
    return out


def measure_instance(frame: RGBDFrame, instance: Instance, options: MeasureOptions | None = None) -> NormPosition:
    """Measure one instance; raises MeasurementError when its mask has too few valid depths."""
    opts = MeasureOptions() if options is None else options
    return _measure_one(frame.camera, np.asarray(frame.depth_m, dtype=np.float64), instance, opts)


def _measure_one(camera: Camera, raw_depth: FloatArray, inst: Instance, opts: MeasureOptions) -> NormPosition:
    import cv2

    h, w = raw_depth.shape
    if inst.mask.shape != (h, w):
        raise InputError(f"instance {inst.instance_id}: mask {inst.mask.shape} does not match the frame ({h}, {w})")
    mask8 = inst.mask.view(np.uint8)
    if opts.erode_px > 0:
        k = 2 * opts.erode_px + 1
        mask8 = np.asarray(cv2.erode(mask8, np.ones((k, k), np.uint8), borderType=cv2.BORDER_CONSTANT), np.uint8)
    bx, by, bw, bh = cv2.boundingRect(mask8)
    if bw == 0 or bh == 0:
        raise MeasurementError(f"instance {inst.instance_id} ({inst.label!r}): empty mask")
    st = opts.normal_step_px
    # region whose points/normals we need, and a margin of S around it for the window estimate
    y0, y1 = max(by - st, 0), min(by + bh + st, h)
    x0, x1 = max(bx - st, 0), min(bx + bw + st, w)
    m = opts.depth.half_window
    py0, py1, px0, px1 = max(y0 - m, 0), min(y1 + m, h), max(x0 - m, 0), min(x1 + m, w)
    filled = fill_depth(raw_depth[py0:py1, px0:px1], opts.depth, region=mask8[py0:py1, px0:px1] > 0)
    sub_depth = filled[y0 - py0 : y1 - py0, x0 - px0 : x1 - px0]
    sub_mask = mask8[y0:y1, x0:x1] > 0
    good = sub_mask & (sub_depth > 0)
    n = int(good.sum())
    if n < opts.min_points:
        raise MeasurementError(
            f"instance {inst.instance_id} ({inst.label!r}): {n} of {int(sub_mask.sum())} mask pixels have valid "
            f"depth, need {opts.min_points}; check the depth range or the mask"
        )
    rays = pixel_rays(camera)[y0:y1, x0:x1]
    pts_cam, nrm_cam, gy, gx = _points_and_normals(rays, sub_depth, good, st, opts.max_normal_jump_m)
    pixels = np.column_stack([gx + x0, gy + y0]).astype(np.int64)
    frame_name: Frame
    if camera.world_from_camera is not None:
        wfc = camera.world_from_camera
        points = transform_points(wfc, pts_cam)
        normals = nrm_cam @ wfc[:3, :3].T
        viewpoint = wfc[:3, 3].copy()
        frame_name = "world"
    else:
        points, normals, viewpoint, frame_name = pts_cam, nrm_cam, np.zeros(3), "camera"
    cols = np.ascontiguousarray(points.T)  # (3, N): row reductions are far faster than axis-0 ones
    return NormPosition(
        label=inst.label,
        score=float(inst.score),
        mask=inst.mask,
        points=points,
        normals=normals,
        pixels=pixels,
        frame=frame_name,
        viewpoint=viewpoint,
        instance_id=int(inst.instance_id),
        centroid=cols.mean(axis=1),
        aabb_min=cols.min(axis=1),
        aabb_max=cols.max(axis=1),
        obb=_oriented_box_cols(cols),
    )


def _points_and_normals(
    rays: FloatArray, depth: FloatArray, good: BoolArray, step: int, jump: float
) -> tuple[FloatArray, FloatArray, IntArray, IntArray]:
    """Camera points (N, 3) of the `good` pixels of a crop and their unit normals (N, 3) facing the camera.

    Normals: cross product of the point differences along u and v, central where both neighbours `step`
    pixels away are good and within `jump` metres in depth, one-sided where only one is, the viewing
    direction where neither is. Works on the N good pixels only (flat-index gathers into a padded crop),
    one coordinate at a time.
    """
    h, w = good.shape
    gy, gx = np.nonzero(good)
    s = step
    wp = w + 2 * s
    # points in float64 at the good pixels; the normal stencil in float32 (half the memory traffic)
    cz = depth[gy, gx]
    cx = rays[gy, gx, 0] * cz
    cy = rays[gy, gx, 1] * cz
    d32 = depth.astype(np.float32)
    z = np.pad(d32, s).ravel()
    ok_map = np.pad(good, s).ravel()
    px = np.pad(rays[:, :, 0].astype(np.float32) * d32, s).ravel()
    py = np.pad(rays[:, :, 1].astype(np.float32) * d32, s).ravel()
    idx = (gy + s) * wp + (gx + s)
    cz32, cx32, cy32 = z[idx], px[idx], py[idx]
    jump32 = np.float32(jump)
    one = np.float32(1.0)

    def derivative(off: int) -> tuple[Float32Array, Float32Array, Float32Array]:
        fi, bi = idx + off, idx - off
        zf, zb = z[fi], z[bi]
        wf = (ok_map[fi] & (np.abs(zf - cz32) < jump32)).astype(np.float32)
        wb = (ok_map[bi] & (np.abs(zb - cz32) < jump32)).astype(np.float32)
        inv = one / np.maximum(wf + wb, one)
        cw = wb - wf  # central: (f - b) / 2; forward only: f - c; backward only: c - b; none: 0
        return (
            (px[fi] * wf - px[bi] * wb + cx32 * cw) * inv,
            (py[fi] * wf - py[bi] * wb + cy32 * cw) * inv,
            (zf * wf - zb * wb + cz32 * cw) * inv,
        )

    ux, uy, uz = derivative(s)
    vx, vy, vz = derivative(s * wp)
    nx = (uy * vz - uz * vy).astype(np.float64)
    ny = (uz * vx - ux * vz).astype(np.float64)
    nz = (ux * vy - uy * vx).astype(np.float64)
    norm = np.sqrt(nx * nx + ny * ny + nz * nz)
    bad = norm < 1e-18
    if np.any(bad):  # no usable neighbours: face the camera
        nx[bad], ny[bad], nz[bad] = -cx[bad], -cy[bad], -cz[bad]
        norm[bad] = np.sqrt(cx[bad] ** 2 + cy[bad] ** 2 + cz[bad] ** 2)
    sign = np.where(nx * cx + ny * cy + nz * cz > 0, -1.0, 1.0) / np.maximum(norm, 1e-300)
    normals = np.empty((idx.size, 3))
    normals[:, 0] = nx * sign
    normals[:, 1] = ny * sign
    normals[:, 2] = nz * sign
    points = np.empty((idx.size, 3))
    points[:, 0] = cx
    points[:, 1] = cy
    points[:, 2] = cz
    return points, normals, gy.astype(np.int64), gx.astype(np.int64)


def oriented_box(points: ArrayLike) -> OrientedBox:
    """PCA oriented bounding box of (N, 3) points: axes = covariance eigenvectors (right-handed, largest
    spread first), extents = full sizes along them, centre = box middle; metres."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if pts.shape[0] == 0:
        raise MeasurementError("oriented_box needs at least one point")
    return _oriented_box_cols(np.ascontiguousarray(pts.T))


def _oriented_box_cols(cols: FloatArray) -> OrientedBox:
    """`oriented_box` of points given as (3, N) rows."""
    n = cols.shape[1]
    mean = cols.mean(axis=1)
    centred = cols - mean[:, None]
    cov = centred @ centred.T / n
    _, vecs = np.linalg.eigh(cov)
    axes = vecs[:, ::-1].copy()
    for i in range(3):  # deterministic sign: largest |component| positive
        if axes[np.argmax(np.abs(axes[:, i])), i] < 0:
            axes[:, i] *= -1.0
    if np.linalg.det(axes) < 0:
        axes[:, 2] *= -1.0
    local = axes.T @ centred
    lo, hi = local.min(axis=1), local.max(axis=1)
    center = mean + axes @ ((lo + hi) / 2.0)
    return OrientedBox(center=center, axes=axes, extents=hi - lo)


def occupancy(points: ArrayLike | NormPosition, voxel_size_m: float) -> VoxelOccupancy:
    """Voxels of edge `voxel_size_m` (metres) holding at least one of the (N, 3) points (or a NormPosition's).

    The grid is anchored at the world origin, so occupancies of different objects share voxels.
    """
    pts = points.points if isinstance(points, NormPosition) else np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if not voxel_size_m > 0:
        raise InputError(f"voxel_size_m must be > 0 metres, got {voxel_size_m}")
    if pts.shape[0] == 0:
        return VoxelOccupancy(float(voxel_size_m), np.zeros(3), np.zeros((0, 3), dtype=np.int64))
    idx = np.floor(pts / voxel_size_m).astype(np.int64)
    uniq = np.unique(idx, axis=0)
    return VoxelOccupancy(float(voxel_size_m), np.zeros(3), uniq)


# -- export ----------------------------------------------------------------------------------------
def normpos_to_dict(np_: NormPosition, points_file: str | None = None) -> dict[str, Any]:
    """JSON-ready summary of a NormPosition (metres); `points_file` names the PLY holding its points."""
    out: dict[str, Any] = {
        "instance_id": np_.instance_id,
        "label": np_.label,
        "score": round(float(np_.score), 6),
        "n_points": np_.n_points,
        "frame": np_.frame,
        "centroid_m": _r(np_.centroid),
        "aabb_min_m": _r(np_.aabb_min),
        "aabb_max_m": _r(np_.aabb_max),
        "obb": {
            "center_m": _r(np_.obb.center),
            "axes": [_r(row) for row in np_.obb.axes],
            "extents_m": _r(np_.obb.extents),
        },
        "viewpoint_m": _r(np_.viewpoint),
        "mask_pixels": int(np_.mask.sum()),
    }
    if points_file is not None:
        out["points_file"] = points_file
    return out


def save_normpos_json(path: str | Path, items: list[NormPosition]) -> None:
    """Write summaries of `items` as a JSON list (atomic)."""
    atomic_write_text(path, json.dumps([normpos_to_dict(n) for n in items], indent=2))


def save_normpos_ply(path: str | Path, item: NormPosition) -> None:
    """Write the points and normals of `item` as a binary PLY (metres)."""
    from normpos_grasp.io.ply import write_ply

    write_ply(path, item.points, normals=item.normals)


def _r(v: ArrayLike) -> list[float]:
    return [round(float(x), 7) for x in np.asarray(v).reshape(-1)]
