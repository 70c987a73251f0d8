"""Measured surfaces no instance covers: what the segmenter missed inside a cell's bins, for the collision world.

The planner's collision world holds the accepted fits and the unexplained points of each instance. A surface the
segmenter did not cover (a plate under a ring, a part hidden but for a rim, a foreign object the model does not
know) would not be in it, and a finger could land on it. `uncovered_points` back-projects every valid depth pixel
that no instance mask (grown by a few pixels) covers, keeps those inside a bin's interior (off its floor and walls
by a noise band: those are the cell's own boxes) and returns them in the world frame; `planning.plan.build_world`
adds those no target explains as clutter. Metres.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from normpos_grasp.camera.model import RGBDFrame
from normpos_grasp.cell.config import BinSpec
from normpos_grasp.errors import InputError
from normpos_grasp.geometry.transforms import invert_pose
from normpos_grasp.measure.depth import valid_depth_mask
from normpos_grasp.measure.measure import pixel_rays
from normpos_grasp.typing import BoolArray, FloatArray, UInt8Array


@dataclass(frozen=True)
class UncoveredOptions:
    """floor_band_m: a point is above a bin's floor when its height, averaged over the uncovered valid pixels of its
    smooth_px-pixel neighbourhood (every stride_px-th pixel), is this much over the floor's level, m. With the D435
    model's noise (2.4 mm RMS at 0.9 m, partly correlated) 6 mm over 5 x 5 leaves no point of 6 empty bins, 5 mm up
    to 6 points, 4 mm over 3 x 3 about 160 (`benchmarks/bench_uncovered.py`). The level is the median height of the
    floor pixels (within floor_search_m of the bin's floor), kept within floor_search_m / 3 of it (a bin covered by
    flat parts). wall_band_m: points this close to the inner walls are the walls, m. above_rim_m: highest point kept
    over the rim, m. dilate_px: each mask is grown by this many pixels first (its border pixels mix the part's depth
    with what lies behind it: 3 px is 4.5 mm at 0.9 m). stride_px: every stride_px-th pixel in both directions
    (clutter voxels are 1 cm; 2 px is 3 mm at 0.9 m). smooth_px: side of the averaging window, strided pixels (odd).
    """

    floor_band_m: float = 0.006
    floor_search_m: float = 0.015
    wall_band_m: float = 0.006
    above_rim_m: float = 0.15
    dilate_px: int = 3
    stride_px: int = 2
    smooth_px: int = 5

    def __post_init__(self) -> None:
        bands = (self.floor_band_m, self.floor_search_m, self.wall_band_m, self.above_rim_m)
        if not all(np.isfinite(v) and v >= 0.0 for v in bands) or not (
            1 <= self.stride_px <= 16 and 0 <= self.dilate_px <= 50 and 1 <= self.smooth_px <= 15
        ):
            raise InputError(
                f"uncovered points need bands >= 0 m, stride_px in 1..16, dilate_px in 0..50 and smooth_px in "
                f"1..15, got {bands}, {self.stride_px}, {self.dilate_px} and {self.smooth_px}"
            )
        if self.smooth_px % 2 == 0:
            raise InputError(f"smooth_px must be odd, got {self.smooth_px}")


def uncovered_points(
    frame: RGBDFrame,
    masks: Sequence[BoolArray],
    bins: Sequence[BinSpec],
    options: UncoveredOptions | None = None,
) -> FloatArray:
    """(N, 3) world points, m, of the valid depth pixels of `frame` that none of `masks` ((H, W) bool) covers and
    that lie inside one of `bins`: off its walls by wall_band_m, above its floor's level by floor_band_m (averaged
    over a neighbourhood), up to above_rim_m over the rim. Empty without bins or without world_from_camera."""
    opts = options or UncoveredOptions()
    camera = frame.camera
    if camera.world_from_camera is None or not bins:
        return np.zeros((0, 3))
    s = opts.stride_px
    full = np.asarray(frame.depth_m, dtype=np.float64)
    valid = valid_depth_mask(full)[::s, ::s]
    depth = np.where(valid, full[::s, ::s], 0.0)
    covered: UInt8Array = np.zeros(valid.shape, dtype=np.uint8)
    for mask in masks:
        covered |= np.asarray(mask, dtype=bool)[::s, ::s].view(np.uint8)
    grow = -(-opts.dilate_px // s)  # the growth in strided pixels, rounded up
    if grow and len(masks):
        size = 2 * grow + 1
        covered = np.asarray(cv2.dilate(covered, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))), np.uint8)
    free = valid & (covered == 0)
    rays = pixel_rays(camera)[::s, ::s]
    rx, ry = rays[:, :, 0], rays[:, :, 1]
    pose = np.asarray(camera.world_from_camera, dtype=np.float64)
    k = (opts.smooth_px, opts.smooth_px)
    inside = np.zeros(valid.shape, dtype=bool)
    for b in bins:
        m = invert_pose(b.world_from_bin) @ pose  # bin_from_camera: a pixel's bin coordinates are d (m0 u + m1 v + m2)
        x, y, z = (depth * (m[i, 0] * rx + m[i, 1] * ry + m[i, 2]) + m[i, 3] for i in range(3))
        lx, ly, h = (float(v) for v in b.inner_size)
        interior = valid & (np.abs(x) <= 0.5 * lx - opts.wall_band_m) & (np.abs(y) <= 0.5 * ly - opts.wall_band_m)
        near_floor = interior & (np.abs(z) <= opts.floor_search_m)
        level = float(np.median(z[near_floor])) if near_floor.sum() >= 50 else 0.0
        level = float(np.clip(level, -opts.floor_search_m / 3.0, opts.floor_search_m / 3.0))
        # heights averaged over the uncovered pixels inside the bin only: neither a part nor a wall seen at a slant
        # lifts the floor beside it
        weight = (free & interior).astype(np.float32)
        count = cv2.boxFilter(weight, -1, k, normalize=False, borderType=cv2.BORDER_CONSTANT)
        summed = cv2.boxFilter((z * weight).astype(np.float32), -1, k, normalize=False, borderType=cv2.BORDER_CONSTANT)
        mean_z = summed / np.maximum(count, 1.0)
        inside |= interior & (mean_z >= level + opts.floor_band_m) & (z <= h + opts.above_rim_m)
    keep = inside & free
    d = depth[keep]
    cam = np.column_stack([rx[keep] * d, ry[keep] * d, d])
    world = cam @ pose[:3, :3].T + pose[:3, 3]
    return np.asarray(world, dtype=np.float64)
