"""Depth estimation from a raw depth image: the paper's neighbourhood-window mean (Eq. 6-7) and an edge-aware variant.

Eq. 6-7: Z(i, j) = sum_w phi * Z / sum_w phi over the (2S+1)^2 window w, phi = 1 for valid depths, else 0.
Computed with unnormalised box filters (a sum of depths and a count of valid pixels), so the cost does not
depend on S and there is no per-pixel Python loop. The plain mean averages across depth discontinuities
and creates "flying" points between an object and the table; `edge_aware=True` averages only neighbours
within a depth tolerance of the centre and fills a hole only where its valid neighbours agree.

Invalid input values: NaN, +-inf, zero, negative, and anything outside [min_depth_m, max_depth_m].
Invalid output pixels are 0.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from normpos_grasp.errors import InputError
from normpos_grasp.typing import ArrayLike, BoolArray, Float32Array, FloatArray

#: largest window half-size S (pixels): a (101 x 101) window already spans a whole part at bin distance
MAX_HALF_WINDOW = 50


@dataclass(frozen=True)
class DepthFillOptions:
    """Settings of the window estimate.

    Attributes:
        half_window: S, the window is (2S+1) x (2S+1) pixels; 0 disables filling (validity mask only).
        min_depth_m, max_depth_m: valid depth range in metres (sensor minimum / maximum range).
        min_valid: fewest valid pixels in the window for a pixel to get a value (>= 1).
        fill_only: True keeps valid pixels' own values and fills only holes; False (the paper) replaces
            every pixel by its window mean, which also smooths noise.
        edge_aware: average only neighbours whose depth lies within r * tol of the centre's (r = pixel
            distance, a slope limit), fill a hole only when its window's depths span at most 2S * tol.
        edge_abs_tol_m, edge_rel_tol: tol = max(edge_abs_tol_m, edge_rel_tol * depth) in metres per pixel
            of offset; a jump larger than this between adjacent pixels is a discontinuity.
    """

    half_window: int = 2
    min_depth_m: float = 0.05
    max_depth_m: float = 20.0
    min_valid: int = 1
    fill_only: bool = False
    edge_aware: bool = False
    edge_abs_tol_m: float = 0.005
    edge_rel_tol: float = 0.01

    def __post_init__(self) -> None:
        if int(self.half_window) != self.half_window or not 0 <= self.half_window <= MAX_HALF_WINDOW:
            raise InputError(
                f"half_window S must be an integer in 0..{MAX_HALF_WINDOW} pixels (the window is (2S+1)^2), "
                f"got {self.half_window}"
            )
        if not 0 <= self.min_depth_m < self.max_depth_m:
            raise InputError(
                f"need 0 <= min_depth_m < max_depth_m (metres), got {self.min_depth_m} and {self.max_depth_m}"
            )
        if not 1 <= self.min_valid <= (2 * self.half_window + 1) ** 2:
            raise InputError(f"min_valid must lie in [1, (2S+1)^2], got {self.min_valid}")
        if not (self.edge_abs_tol_m >= 0 and self.edge_rel_tol >= 0):
            raise InputError("edge tolerances must be >= 0")


def valid_depth_mask(depth_m: ArrayLike, min_depth_m: float = 0.05, max_depth_m: float = 20.0) -> BoolArray:
    """(H, W) bool: finite, positive and within [min_depth_m, max_depth_m]."""
    d = _as_depth(depth_m)
    with np.errstate(invalid="ignore"):
        return np.asarray(np.isfinite(d) & (d > 0) & (d >= min_depth_m) & (d <= max_depth_m))


def fill_depth(
    depth_m: ArrayLike, options: DepthFillOptions | None = None, region: BoolArray | None = None
) -> FloatArray:
    """Window estimate of depth (Eq. 6-7), (H, W) metres in, (H, W) float64 metres out (0 = no estimate).

    `region` (H, W) bool, optional: the pixels whose values are needed; the edge-aware estimate may leave
    the others at 0 (it skips their slow path). Sums run in float32 box filters (OpenCV accumulates them in
    float64); the input is not modified.
    """
    opts = DepthFillOptions() if options is None else options
    d = _as_depth(depth_m)
    valid = valid_depth_mask(d, opts.min_depth_m, opts.max_depth_m)
    if opts.half_window == 0:
        return np.where(valid, d, 0.0)
    clean = np.where(valid, d, 0.0).astype(np.float32)
    mean, count = _box_mean(clean, valid, opts)
    if not opts.edge_aware:
        out = mean.astype(np.float64)
    else:
        if region is not None and np.shape(region) != d.shape:
            raise InputError(f"region must be {d.shape} like the depth, got {np.shape(region)}")
        out = _edge_aware(clean, valid, mean, opts, region).astype(np.float64)
    if opts.fill_only:
        out[valid] = d[valid]
    return out


def _box_mean(clean: Float32Array, valid: BoolArray, opts: DepthFillOptions) -> tuple[Float32Array, Float32Array]:
    """Eq. 6-7 for every pixel: (sum of valid depths) / (number of valid depths) over the window."""
    import cv2

    k = 2 * opts.half_window + 1
    total = np.asarray(
        cv2.boxFilter(clean, cv2.CV_32F, (k, k), normalize=False, borderType=cv2.BORDER_CONSTANT), np.float32
    )
    count = np.asarray(
        cv2.boxFilter(valid.view(np.uint8), cv2.CV_32F, (k, k), normalize=False, borderType=cv2.BORDER_CONSTANT),
        np.float32,
    )
    ok = count >= opts.min_valid - 0.5
    mean = (total / np.maximum(count, np.float32(1.0))).astype(np.float32, copy=False)
    mean[~ok] = 0.0
    return mean, count


def _edge_aware(
    clean: Float32Array, valid: BoolArray, mean: Float32Array, opts: DepthFillOptions, region: BoolArray | None
) -> Float32Array:
    """Slope-limited window mean: a neighbour at Chebyshev pixel distance r counts when its depth lies within
    r * tol(z) of the centre's, tol(z) = max(edge_abs_tol_m, edge_rel_tol * z). A hole is filled with the
    plain mean only when its window's valid depths span at most 2S * tol.

    Where every neighbour passes (checked with min/max filters of each radius r = 1..S) the result equals
    the plain box mean; only the remaining pixels near discontinuities are averaged by a sparse gather of
    their (2S+1)^2 neighbours. No per-pixel Python loop.
    """
    import cv2

    s = opts.half_window
    h, w = clean.shape
    abs_tol = np.float32(opts.edge_abs_tol_m)
    rel_tol = np.float32(opts.edge_rel_tol)
    tol = np.maximum(abs_tol, rel_tol * clean)
    big = np.where(valid, clean, np.float32(np.inf))
    flat = valid.copy()
    wmin = wmax = clean
    for r in range(1, s + 1):
        kernel = np.ones((2 * r + 1, 2 * r + 1), np.uint8)
        wmax = np.asarray(cv2.dilate(clean, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=0.0), np.float32)
        wmin = np.asarray(cv2.erode(big, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=np.inf), np.float32)
        with np.errstate(invalid="ignore"):
            flat &= ((wmax - clean) <= r * tol) & ((clean - wmin) <= r * tol)
    out = np.where(flat, mean, np.float32(0.0))
    need = valid & ~flat
    if region is not None:
        need &= region
    ys, xs = np.nonzero(need)
    if ys.size:
        pad = cv2.copyMakeBorder(clean, s, s, s, s, cv2.BORDER_CONSTANT, value=0.0).ravel()
        dy, dx = np.mgrid[-s : s + 1, -s : s + 1]
        offsets = (dy * (w + 2 * s) + dx).ravel()
        ring = np.maximum(np.abs(dy), np.abs(dx)).ravel().astype(np.float32)
        ring[ring == 0] = 1.0
        base = (ys + s) * (w + 2 * s) + (xs + s)
        nb = pad[base[:, None] + offsets[None, :]]  # (E, (2S+1)^2)
        centre = clean[ys, xs][:, None]
        take = (nb > 0) & (np.abs(nb - centre) <= tol[ys, xs][:, None] * ring[None, :])
        cnt = take.sum(axis=1)
        val = (nb * take).sum(axis=1) / np.maximum(cnt, 1)
        out[ys, xs] = np.where(cnt >= opts.min_valid, val, np.float32(0.0))
    holes = ~valid & (mean > 0)
    if region is not None:
        holes &= region
    if np.any(holes):
        span_tol = 2 * s * np.maximum(abs_tol, rel_tol * wmax)
        with np.errstate(invalid="ignore"):
            agree = holes & ((wmax - wmin) <= span_tol)
        out[agree] = mean[agree]
    return out


def _as_depth(depth_m: ArrayLike) -> FloatArray:
    d = np.asarray(depth_m)
    if d.ndim != 2 or d.size == 0:
        raise InputError(f"depth must be a non-empty (H, W) array, got shape {d.shape}")
    if not (np.issubdtype(d.dtype, np.floating) or np.issubdtype(d.dtype, np.integer)):
        raise InputError(f"depth must be numeric (metres), got dtype {d.dtype}")
    return np.asarray(d, dtype=np.float64)
