"""Change detection between two frames of a static camera, per instance: is an object where it was?

Used to keep the fit of an object that did not move since the previous frame (after a pick, most of the bin did
not move), so only what changed is fitted again. Medians make the test robust to the sensor's holes and edge
outliers; halves of the mask catch a tilt that raises one side and lowers the other.
"""

from __future__ import annotations

import numpy as np

from normpos_grasp.typing import BoolArray, FloatArray

MIN_OVERLAP_PX = 40  # fewer common valid pixels than this: changed (too little evidence to keep a fit)
MIN_HALF_PX = 10


def mask_iou(a: BoolArray, b: BoolArray) -> float:
    """Intersection over union of two boolean masks of one image (0 when they do not touch)."""
    inter = int(np.count_nonzero(a & b))
    if inter == 0:
        return 0.0
    return inter / float(np.count_nonzero(a | b))


def depth_changed(mask: BoolArray, depth: FloatArray, old_mask: BoolArray, old_depth: FloatArray, tol_m: float) -> bool:
    """True unless the median depth change over the overlap of both masks, and over each of its halves (left / right,
    top / bottom), stays within `tol_m` metres. Depth images (H, W) in metres, 0 = no reading."""
    both = mask & old_mask & (depth > 0) & (old_depth > 0)
    v, u = np.nonzero(both)
    if len(u) < MIN_OVERLAP_PX:
        return True
    diff = depth[v, u] - old_depth[v, u]
    if abs(float(np.median(diff))) > tol_m:
        return True
    for coord in (u, v):
        cut = np.median(coord)
        for half in (coord < cut, coord >= cut):
            if np.count_nonzero(half) >= MIN_HALF_PX and abs(float(np.median(diff[half]))) > tol_m:
                return True
    return False


def unchanged(
    mask: BoolArray,
    depth: FloatArray,
    old_mask: BoolArray,
    old_depth: FloatArray,
    min_iou: float,
    tol_m: float,
) -> bool:
    """The object under `mask` is where it was under `old_mask`: masks overlap by `min_iou` and its depth changed by
    no more than `tol_m` metres (see `depth_changed`)."""
    return mask_iou(mask, old_mask) >= min_iou and not depth_changed(mask, depth, old_mask, old_depth, tol_m)
