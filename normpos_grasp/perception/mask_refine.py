"""Full-resolution refinement of soft instance masks with the frame's depth image.

The bundled model predicts masks at a quarter of its input resolution (64x48 prototypes for a 256x192 input), so
upsampled to 640x480 each prototype pixel covers 10x10 frame pixels and boundaries come out rounded and up to a few
pixels off. Depth has the full resolution and most part boundaries are depth steps (a part above the bin floor,
one part above another), so the mask boundary is snapped to them:

1. depth steps: a pixel is a *far-side edge pixel* when its (3x3 median filtered) depth lies more than
   `step(z) = edge_step_m + edge_step_per_m2 * z^2` behind a 4-neighbour's (stereo noise grows with range^2);
2. per instance, inside a window around its box, the pixels with valid depth that are not edge pixels and whose
   soft score exceeds `grow_prob` split into 4-connected *depth regions* (no region crosses a depth step);
3. a region joins the instance when its mean soft score is at least `region_prob` (regions the prototypes put
   mostly inside, grown to their depth boundary), leaves it otherwise (blobs across a depth step, like the floor
   beside a part); an edge pixel goes with the region it continues without a step;
4. colour decides the rest: pixels without valid depth (the sensor drops pixels along depth steps), edge pixels
   that continue no region, and pixels where the depth regions and the soft mask disagree (contact lines of a
   part with the floor, parts of nearly the same height) go to the nearer of the local mean colours of the sure
   inside and sure outside pixels around them (a `colour_px` square); without colour, the soft threshold
   `mask_prob` decides them;
5. holes of at most `max_hole_px` pixels inside an instance are filled;
6. overlaps: a pixel claimed by several instances goes to the one with the highest soft score there; an instance
   left with less than `min_kept_fraction` of its pixels is a duplicate and is emptied.

Works in each instance's window (box plus `margin_px`), vectorised with OpenCV / numpy. Without depth and
colour this reduces to thresholding at `mask_prob` plus the hole and overlap steps.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from normpos_grasp.errors import InputError
from normpos_grasp.typing import BoolArray, Float32Array, FloatArray

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class MaskRefineOptions:
    """Settings of `refine_masks`.

    Attributes:
        edge_step_m: constant part of the depth step (metres) that separates neighbouring pixels into regions.
        edge_step_per_m2: range-squared part of the step (metres per metre^2 of depth), for stereo noise.
        grow_prob: lowest soft score (0..1) a pixel may have to be added to an instance.
        region_prob: mean soft score (0..1) of a depth region above which the whole region joins the instance.
        mask_prob: threshold (0..1) for pixels the depth cannot decide (no valid depth, edge pixels).
        max_hole_px: holes inside an instance up to this many pixels are filled (0 = none).
        margin_px: the window around each box in which masks may change (frame pixels).
        median_px: median filter size (pixels, 1, 3 or 5) applied to depth before the step test (1 = none).
        sure_prob: soft score (0..1) above which a pixel without depth counts as inside for sure.
        colour_px: size (pixels) of the neighbourhood whose sure inside / outside mean colours decide the pixels
            depth cannot (0 = no colour: those pixels take the plain `mask_prob` threshold).
        colour_checks_depth: colour also decides the pixels where the depth regions and the soft mask disagree
            (a region joined but the pixel's soft score is below `mask_prob`, or the reverse), as at contact lines
            of a part with the floor or with a part of nearly the same height, where depth shows no step.
        min_kept_fraction: an instance that keeps less than this share (0..1) of the pixels it claimed after the
            overlaps are resolved is emptied (a duplicate of higher-scoring instances; 0 = keep all).
    """

    edge_step_m: float = 0.002
    edge_step_per_m2: float = 0.003
    grow_prob: float = 0.15
    region_prob: float = 0.5
    mask_prob: float = 0.5
    max_hole_px: int = 150
    margin_px: int = 8
    median_px: int = 3
    sure_prob: float = 0.9
    colour_px: int = 9
    colour_checks_depth: bool = True
    min_kept_fraction: float = 0.5

    def __post_init__(self) -> None:
        if self.edge_step_m < 0 or self.edge_step_per_m2 < 0:
            raise InputError(f"edge steps must be >= 0, got {self.edge_step_m}, {self.edge_step_per_m2}")
        for name in ("grow_prob", "region_prob", "mask_prob"):
            v = getattr(self, name)
            if not 0.0 < v < 1.0:
                raise InputError(f"{name} must lie in (0, 1), got {v}")
        if not 0.0 <= self.min_kept_fraction <= 1.0:
            raise InputError(f"min_kept_fraction must lie in [0, 1], got {self.min_kept_fraction}")
        if self.max_hole_px < 0 or self.margin_px < 0:
            raise InputError(f"max_hole_px and margin_px must be >= 0, got {self.max_hole_px}, {self.margin_px}")
        if self.median_px not in (1, 3, 5):
            raise InputError(f"median_px must be 1, 3 or 5, got {self.median_px}")


@dataclass(frozen=True)
class SoftMask:
    """One instance's soft mask on a frame window: prob (h, w) float32 in [0, 1], its top-left frame pixel
    (x0, y0)."""

    prob: Float32Array
    x0: int
    y0: int


def far_edges(depth_m: FloatArray, options: MaskRefineOptions) -> tuple[BoolArray, BoolArray, Float32Array]:
    """(valid, edge, depth): valid (H, W) bool: valid depth (finite, > 0); edge (H, W) bool: valid pixels lying
    more than the range-relative step behind one of their valid 4-neighbours; depth (H, W) float32 metres, the
    filtered depth the test used (0 where invalid)."""
    d = np.asarray(depth_m, dtype=np.float32)
    valid = np.isfinite(d) & (d > 0)
    d = np.where(valid, d, 0.0).astype(np.float32)
    if options.median_px > 1:
        d = np.asarray(cv2.medianBlur(d, options.median_px), dtype=np.float32)
        valid &= d > 0
    far = np.where(valid, d, np.float32(np.inf))
    near = np.where(valid, d, np.float32(-np.inf))  # invalid neighbours never make a pixel an edge
    step = np.float32(options.edge_step_m) + np.float32(options.edge_step_per_m2) * d * d
    nb = np.full(d.shape, np.inf, np.float32)
    np.minimum(nb[1:], far[:-1], out=nb[1:])
    np.minimum(nb[:-1], far[1:], out=nb[:-1])
    np.minimum(nb[:, 1:], far[:, :-1], out=nb[:, 1:])
    np.minimum(nb[:, :-1], far[:, 1:], out=nb[:, :-1])
    edge = valid & (near - nb > step)
    return valid, edge, np.where(valid, d, np.float32(0.0))


def _continuing_label(
    labels: np.ndarray, depth: np.ndarray, ys: np.ndarray, xs: np.ndarray, options: MaskRefineOptions
) -> np.ndarray:
    """For the pixels (ys, xs): the label (> 0) of a 4-neighbour whose depth differs by at most the step, else 0."""
    h, w = labels.shape
    z = depth[ys, xs]
    step = options.edge_step_m + options.edge_step_per_m2 * z * z
    out = np.zeros(len(ys), labels.dtype)
    for ny, nx in (
        (ys, np.minimum(xs + 1, w - 1)),
        (ys, np.maximum(xs - 1, 0)),
        (np.minimum(ys + 1, h - 1), xs),
        (np.maximum(ys - 1, 0), xs),
    ):
        lab = labels[ny, nx]  # at the window border this is the pixel itself: an edge pixel, label 0
        ok = (out == 0) & (lab > 0) & (np.abs(depth[ny, nx] - z) <= step)
        out[ok] = lab[ok]
    return out


def _fill_holes(mask: np.ndarray, max_hole_px: int) -> np.ndarray:
    """Fill 4-connected background components of `mask` (uint8 0/1) that do not touch the border and have at most
    `max_hole_px` pixels."""
    inv = (mask == 0).astype(np.uint8)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(inv, connectivity=4)
    if n <= 1:
        return mask
    h, w = mask.shape
    x, y, bw, bh, area = stats[:, 0], stats[:, 1], stats[:, 2], stats[:, 3], stats[:, 4]
    inner = (x > 0) & (y > 0) & (x + bw < w) & (y + bh < h) & (area <= max_hole_px)
    inner[0] = False
    if not inner.any():
        return mask
    return (mask.astype(bool) | inner[labels]).astype(np.uint8)


def _colour_vote(
    rgb: np.ndarray, sure_in: np.ndarray, sure_out: np.ndarray, undecided: np.ndarray, keep: np.ndarray, size: int
) -> np.ndarray:
    """`keep` with the undecided pixels reassigned to the nearer (RGB distance) of the local mean colours of the
    sure-inside and sure-outside pixels within a `size` x `size` neighbourhood (the window's mean colour of a side
    where none of its pixels is that near); pixels where a side is missing altogether keep their value."""
    k = (size, size)
    ys, xs = np.nonzero(undecided)
    d = []
    for side in (sure_in, sure_out):
        m8 = side.view(np.uint8) if side.dtype == np.bool_ else side.astype(np.uint8)
        col = cv2.bitwise_and(rgb, rgb, mask=m8)
        cnt = cv2.boxFilter(m8, cv2.CV_32F, k, normalize=False, borderType=cv2.BORDER_CONSTANT)[ys, xs]
        tot = cv2.boxFilter(col, cv2.CV_32F, k, normalize=False, borderType=cv2.BORDER_CONSTANT)[ys, xs]
        lack = cnt < 0.5
        if lack.any():  # no sure pixel of this side nearby (wide holes): its mean over the window stands in
            cnt[lack] = cv2.countNonZero(m8)
            tot[lack] = cv2.sumElems(col)[:3]
        mean = tot / np.maximum(cnt, 1.0)[:, None]
        d.append(np.where(cnt > 0.5, ((mean - rgb[ys, xs]) ** 2).sum(1), np.nan))
    d_in, d_out = d
    ok = np.isfinite(d_in) & np.isfinite(d_out)
    if not ok.any():
        return keep
    ys, xs, d_in, d_out = ys[ok], xs[ok], d_in[ok], d_out[ok]
    out = keep.copy()
    out[ys, xs] = d_in < d_out
    return out


def refine_masks(
    soft: Sequence[SoftMask],
    depth_m: FloatArray | None,
    image_hw: tuple[int, int],
    options: MaskRefineOptions | None = None,
    rgb: np.ndarray | None = None,
) -> BoolArray:
    """Refined masks (N, H, W) bool of the N soft masks on a frame of `image_hw` (H, W); `depth_m` (H, W) metres
    (0 / NaN invalid) or None (then only thresholding, overlaps and holes); `rgb` (H, W, 3) uint8 or None: colour
    decides the pixels depth cannot (holes along part borders, depth-edge pixels)."""
    opts = options or MaskRefineOptions()
    h0, w0 = image_hw
    n = len(soft)
    out = np.zeros((n, h0, w0), dtype=bool)
    if n == 0:
        return out
    if rgb is not None and np.shape(rgb) != (h0, w0, 3):
        raise InputError(f"rgb must be (H, W, 3) = {(h0, w0, 3)}, got {np.shape(rgb)}")
    if depth_m is not None and np.shape(depth_m) != (h0, w0):
        raise InputError(f"depth must be (H, W) = {(h0, w0)}, got {np.shape(depth_m)}")
    probs: list[Float32Array] = []
    boxes: list[tuple[int, int, int, int]] = []
    for k, s in enumerate(soft):
        p = np.asarray(s.prob, dtype=np.float32)
        if p.ndim != 2:
            raise InputError(f"soft mask {k} must be (h, w), got {p.shape}")
        ya, xa = max(s.y0, 0), max(s.x0, 0)
        yb, xb = min(s.y0 + p.shape[0], h0), min(s.x0 + p.shape[1], w0)
        boxes.append((ya, max(yb, ya), xa, max(xb, xa)))
        probs.append(p[ya - s.y0 : yb - s.y0, xa - s.x0 : xb - s.x0])
    # everything below works on the union of the windows (uy0:uy1, ux0:ux1); window coordinates are relative to it
    live = [bx for bx in boxes if bx[1] > bx[0] and bx[3] > bx[2]]
    if not live:
        return out
    uy0, uy1 = min(b[0] for b in live), max(b[1] for b in live)
    ux0, ux1 = min(b[2] for b in live), max(b[3] for b in live)
    if depth_m is not None:
        pad = 3  # context for the median filter and the neighbour test at the union's border
        cy0, cx0 = max(uy0 - pad, 0), max(ux0 - pad, 0)
        cy1, cx1 = min(uy1 + pad, h0), min(ux1 + pad, w0)
        valid_c, edge_c, depth_c = far_edges(np.asarray(depth_m)[cy0:cy1, cx0:cx1], opts)
        valid = valid_c[uy0 - cy0 : uy1 - cy0, ux0 - cx0 : ux1 - cx0]
        edge = edge_c[uy0 - cy0 : uy1 - cy0, ux0 - cx0 : ux1 - cx0]
        depth = depth_c[uy0 - cy0 : uy1 - cy0, ux0 - cx0 : ux1 - cx0]
    else:
        valid = np.zeros((uy1 - uy0, ux1 - ux0), bool)
        edge = valid
        depth = np.zeros(valid.shape, np.float32)
    rgb_u = None if rgb is None else np.asarray(rgb)[uy0:uy1, ux0:ux1]
    best = np.full((uy1 - uy0, ux1 - ux0), -1.0, np.float32)  # highest soft score of a claiming instance so far
    owner = np.full((uy1 - uy0, ux1 - ux0), -1, np.int32)
    claimed = np.zeros(n, np.int64)
    for k, (ya, yb, xa, xb) in enumerate(boxes):
        if yb <= ya or xb <= xa:
            continue
        p = probs[k]
        ya, yb, xa, xb = ya - uy0, yb - uy0, xa - ux0, xb - ux0
        v, e, d = valid[ya:yb, xa:xb], edge[ya:yb, xa:xb], depth[ya:yb, xa:xb]
        plain = p > opts.mask_prob
        free = v & ~e & (p > opts.grow_prob)
        sure_in = ~v & (p >= opts.sure_prob)  # no depth, but the network is sure
        sure_out = p <= opts.grow_prob
        if free.any():
            nl, labels = cv2.connectedComponents(free.astype(np.uint8), connectivity=4)
            sums = np.bincount(labels.ravel(), weights=p.ravel(), minlength=nl)
            counts = np.bincount(labels.ravel(), minlength=nl)
            take = sums >= opts.region_prob * np.maximum(counts, 1)
            take[0] = False
            region = take[labels]
            sure_in |= region
            sure_out |= free & ~region
            # an edge pixel lies on the far side of a step: it joins the region it continues without a step
            ey, ex = np.nonzero(e & (p > opts.grow_prob))
            if len(ey):
                joined = _continuing_label(labels, d, ey, ex, opts)
                ok = joined > 0
                sure_in[ey[ok], ex[ok]] = take[joined[ok]]
                sure_out[ey[ok], ex[ok]] = ~take[joined[ok]]
        default = plain
        if opts.colour_checks_depth and rgb_u is not None and opts.colour_px > 0:
            # where depth and the soft mask disagree, colour has the last word (depth's vote if it cannot tell)
            doubt = (sure_in & ~plain) | (sure_out & plain & (p > opts.grow_prob))
            default = np.where(doubt, sure_in, plain)
            sure_in &= ~doubt
            sure_out &= ~doubt
        undecided = ~(sure_in | sure_out)  # no depth or a depth-edge pixel, in the band of the soft mask
        keep = sure_in
        if undecided.any():
            keep = keep | (undecided & default)
            if rgb_u is not None and opts.colour_px > 0:
                keep = _colour_vote(rgb_u[ya:yb, xa:xb], sure_in, sure_out, undecided, keep, opts.colour_px)
        if opts.max_hole_px > 0 and keep.any():
            keep = _fill_holes(keep.astype(np.uint8), opts.max_hole_px).astype(bool)
        claimed[k] = int(np.count_nonzero(keep))
        b, o = best[ya:yb, xa:xb], owner[ya:yb, xa:xb]
        score = np.where(keep, p, np.float32(-1.0))
        win = score > b
        b[win] = score[win]
        o[win] = k
    for k, (ya, yb, xa, xb) in enumerate(boxes):
        if yb > ya and xb > xa:
            out[k, ya:yb, xa:xb] = owner[ya - uy0 : yb - uy0, xa - ux0 : xb - ux0] == k
            # an instance left with a small part of what it claimed duplicates others: it goes
            if np.count_nonzero(out[k, ya:yb, xa:xb]) < opts.min_kept_fraction * claimed[k]:
                out[k, ya:yb, xa:xb] = False
    return out
