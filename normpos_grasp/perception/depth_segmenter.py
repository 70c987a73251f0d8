"""Model-free instance segmentation from depth: remove support planes and walls, cut at depth jumps and concave
creases, merge pieces across continuous boundaries.

Steps, at a reduced resolution (every `stride`-th pixel) for speed, masks upsampled at the end:
1. median-filtered depth; normals from box-smoothed depth by the pinhole formula (one-sided next to depth jumps);
2. RANSAC the dominant plane (table, bin floor, belt) and remove it with everything behind it; further large planes
   parallel to it (a bin floor above the table, a belt) and walls (planes perpendicular to it, RANSAC on the pixels
   with upright normals, regions longer than any part) are removed too; rims and rails by a morphological opening;
3. mark edges: depth jumps relative to range, and concave creases ((n_i - n_j) . (p_i - p_j) < 0; convex edges
   inside one part, like a cube's rim, are not cut);
4. connected components, edge pixels given to the nearest one, leftover foreground as components of its own; merge
   of touching components across boundaries mostly free of depth jumps up to the size of the largest part (an
   L-bracket's legs); size, rim and wall filters; dropouts enclosed by one instance join it.
Labels are '' (assigned later by template fitting); scores are 1.0. See docs/segmentation.md.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage

from normpos_grasp.camera.model import RGBDFrame
from normpos_grasp.errors import InputError
from normpos_grasp.records.instance import Instance
from normpos_grasp.typing import FloatArray

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class DepthSegmenterOptions:
    """Settings of `DepthSegmenter`.

    Attributes:
        stride: work on every stride-th pixel (2: 640x480 -> 320x240).
        plane_tolerance_m: a point within this distance of a support plane belongs to it, metres.
        plane_noise_factor: adds this times the stereo RMS z^2 * 0.0026 / m to the plane tolerance.
        fit_tolerance_m: the tighter tolerance (plus the same noise term) with which planes are fitted (RANSAC and
            least-squares refinement), metres; it keeps a bin floor and the table just below it from being fitted
            as one tilted compromise plane.
        min_plane_fraction: a further plane (after the first) is removed only if it holds this fraction of the
            valid pixels; of its inliers only connected regions of at least min_plane_area_m2 (m^2, larger than
            any part face) are removed.
        support_area_m2: a further plane parallel to the first whose removed regions cover at least this area (m^2;
            a bin floor, a belt; not a rail top) is a floor: all its inliers and everything behind it are removed.
        plane_normal_deg: a pixel joins a further plane's inlier region only if its normal is within this angle of
            the plane's normal, degrees.
        ransac_iterations: plane hypotheses per RANSAC run; ransac_samples: points scored per hypothesis.
        depth_jump_m: neighbours (at working resolution) whose depths differ by more are separated, metres;
            depth_jump_rel: plus this fraction of the depth.
        crease_angle_deg: neighbours whose normals differ by more, at a concave crease, are separated, degrees.
        steep_faces: a depth step counts as a discontinuity only by how much it exceeds its neighbouring steps
            (keeps steep faces of one part together); False: by its size alone.
        normal_step: normals from central differences over +-normal_step working pixels.
        min_pixels: smallest instance, full-resolution pixels.
        min_fragment_pixels: smaller pieces between edges are not components of their own but join the nearest one
            (within 3 working pixels), full-resolution pixels.
        rim_width_m / rim_length_m / rim_elongation: components thinner than rim_width_m and longer than both
            rim_length_m and rim_elongation times their width are taken
            for wall rims or rails and dropped, metres.
        rim_open_m: before the edges, foreground pixels that an opening with a disk this wide removes are dropped
            where they form connected pieces longer than rim_length_m (rims, rails), metres; 0 turns it off.
        max_extent_m: components longer than this are static structure and dropped, metres.
        merge_max_extent_m: touching components whose shared boundary is mostly free of depth jumps are merged
            when the union is at most this long (the largest part), metres; 0 turns merging off.
        merge_max_jump_fraction: the largest fraction of boundary pixel pairs with a depth jump for a merge.
        max_walls: up to this many walls (planes perpendicular to the support plane, RANSAC on the pixels with
            upright normals) are removed where pixels within wall_tolerance_m (metres, plus the noise term) of them
            form a connected region at least wall_min_length_m long (metres, longer than any part); 0 turns it off.
        wall_angle_deg / max_wall_fraction: a component is dropped as a wall when more than max_wall_fraction of its
            pixels have normals more than wall_angle_deg (degrees) from the support plane's normal and it is at least
            wall_piece_min_length_m long (metres; a part seen from the side, like a bracket's standing leg, is shorter);
            max_wall_fraction 1.0 turns it off.
        seed: RNG seed of the RANSAC (a private generator; the global RNG is untouched).
    """

    stride: int = 2
    plane_tolerance_m: float = 0.003
    plane_noise_factor: float = 1.5
    fit_tolerance_m: float = 0.0012
    plane_normal_deg: float = 90.0
    min_plane_fraction: float = 0.05
    min_plane_area_m2: float = 0.012
    support_area_m2: float = 0.03
    ransac_iterations: int = 64
    ransac_samples: int = 1024
    depth_jump_m: float = 0.004
    depth_jump_rel: float = 0.003
    crease_angle_deg: float = 35.0
    steep_faces: bool = True
    normal_step: int = 2
    min_pixels: int = 250
    min_fragment_pixels: int = 150
    rim_width_m: float = 0.016
    rim_length_m: float = 0.12
    rim_elongation: float = 3.0
    rim_open_m: float = 0.012
    max_extent_m: float = 0.25
    merge_max_extent_m: float = 0.08
    merge_max_jump_fraction: float = 0.2
    max_walls: int = 4
    wall_tolerance_m: float = 0.004
    wall_min_length_m: float = 0.15
    wall_angle_deg: float = 60.0
    max_wall_fraction: float = 0.7
    wall_piece_min_length_m: float = 0.07
    seed: int = 0

    def __post_init__(self) -> None:
        if self.stride < 1 or self.ransac_iterations < 1 or self.ransac_samples < 3:
            raise InputError("stride, ransac_iterations must be >= 1 and ransac_samples >= 3")
        if self.plane_tolerance_m <= 0 or self.depth_jump_m <= 0 or not 0 < self.crease_angle_deg < 180:
            raise InputError("plane_tolerance_m and depth_jump_m must be > 0, crease_angle_deg in (0, 180)")


def _dots(points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """(S, I) dot products of (S, 3) points with (I, 3) normals, float32 (broadcast: no BLAS threads)."""
    p = np.asarray(points, np.float32)
    n = np.asarray(normals, np.float32)
    return p[:, 0:1] * n[None, :, 0] + p[:, 1:2] * n[None, :, 1] + p[:, 2:3] * n[None, :, 2]


def _fit_plane(points: FloatArray) -> tuple[FloatArray, float]:
    """Least-squares plane through (N, 3) points: unit normal n and offset d with n . p + d = 0."""
    pts = np.asarray(points, dtype=np.float64)
    c = pts.mean(axis=0)
    q = pts - c
    _, vecs = np.linalg.eigh(q.T @ q)  # 3x3 scatter matrix: its smallest eigenvector is the normal
    n = vecs[:, 0]
    return n, -float(n @ c)


def ransac_plane(
    points: np.ndarray, tolerance: np.ndarray | float, iterations: int, samples: int, rng: np.random.Generator
) -> tuple[FloatArray, float, int]:
    """Dominant plane of (N, 3) points: (unit normal towards the camera origin, offset d, inlier count on the
    scored subset). tolerance: scalar or (N,) per-point, metres."""
    n_pts = len(points)
    tol = np.broadcast_to(np.asarray(tolerance, dtype=np.float64), (n_pts,))
    idx = rng.integers(0, n_pts, size=min(samples, n_pts))
    sub, sub_tol = points[idx], tol[idx]
    tri = points[rng.integers(0, n_pts, size=(iterations, 3))]
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    norm = np.linalg.norm(normals, axis=1)
    ok = norm > 1e-12
    if not ok.any():
        return np.array([0.0, 0.0, -1.0]), 0.0, 0
    normals = normals[ok] / norm[ok, None]
    ds = -np.einsum("ij,ij->i", normals, tri[ok, 0])
    # (S, I) distances by broadcasting (no BLAS threads)
    dist = np.abs(_dots(sub, normals) + ds[None, :])  # (S, I)
    support = (dist < sub_tol[:, None]).sum(axis=0)
    best = int(np.argmax(support))
    n, d = normals[best], float(ds[best])
    inl = np.abs(sub @ n + d) < sub_tol
    if inl.sum() >= 3:
        n, d = _fit_plane(sub[inl])
    if d < 0:  # orient towards the camera origin: n . 0 + d > 0
        n, d = -n, -d
    return n, d, int((np.abs(sub @ n + d) < sub_tol).sum())


def refine_plane(
    points: np.ndarray, tolerance: np.ndarray, n: FloatArray, d: float, rounds: int = 2
) -> tuple[FloatArray, float]:
    """Least-squares refit of plane (n, d) on the (N, 3) `points` within `tolerance` (N,) metres of it (on an even
    subset of at most 6000 points), `rounds` times; the normal keeps its orientation towards the camera origin."""
    step = len(points) // 6000 + 1
    pts = np.asarray(points[::step], dtype=np.float64)
    tol = np.broadcast_to(np.asarray(tolerance, dtype=np.float64), (len(points),))[::step]
    for _ in range(rounds):
        inl = np.abs(pts[:, 0] * n[0] + pts[:, 1] * n[1] + pts[:, 2] * n[2] + d) < tol
        if inl.sum() < 3:
            break
        n, d = _fit_plane(pts[inl])
        if d < 0:
            n, d = -n, -d
    return n, d


def _remove_rims(fg: np.ndarray, z: np.ndarray, fx: float, width_m: float, length_m: float) -> np.ndarray:
    """`fg` (h, w) bool without its thin, long structures (wall rims, rails, grazing wall faces): pixels that a
    morphological opening with a disk `width_m` across removes, in connected pieces longer than `length_m` (bounding
    box diagonal, metres); z: (h, w) depth, metres; fx: focal length at this resolution, pixels."""
    zmed = float(np.median(z[fg]))
    k = max(3, int(round(width_m * fx / max(zmed, 1e-3))) | 1)
    opened = cv2.morphologyEx(fg.astype(np.uint8), cv2.MORPH_OPEN, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k)))
    thin = fg & (opened == 0)
    n, cc, stats, _ = cv2.connectedComponentsWithStats(thin.astype(np.uint8), connectivity=8)
    if n <= 1:
        return fg
    diag = np.hypot(stats[:, cv2.CC_STAT_WIDTH], stats[:, cv2.CC_STAT_HEIGHT]) * zmed / fx
    drop = np.zeros(n, bool)
    for c in np.flatnonzero(diag > length_m):
        if c == 0:
            continue
        x0, y0 = stats[c, cv2.CC_STAT_LEFT], stats[c, cv2.CC_STAT_TOP]
        sub = cc[y0 : y0 + stats[c, cv2.CC_STAT_HEIGHT], x0 : x0 + stats[c, cv2.CC_STAT_WIDTH]] == c
        ys, xs = np.nonzero(sub)
        (_, _), (rw, rh), _ = cv2.minAreaRect(np.column_stack([xs, ys]).astype(np.float32))
        drop[c] = min(rw, rh) * zmed / fx < 2.0 * width_m  # straight strips only, not chains around parts
    return fg & ~drop[cc]


def merge_continuous(
    lab: np.ndarray,
    jump_px: np.ndarray,
    z: np.ndarray,
    fx: float,
    max_extent_m: float,
    max_jump_fraction: float,
) -> np.ndarray:
    """Merge touching components of the (h, w) int32 label image `lab` whose shared boundary is mostly free of
    depth jumps (a crease inside one part, like the inner corner of an L-bracket or a face cut off at a steep
    view) when the union stays within `max_extent_m` (metres, the size of the largest part); z: (h, w) depth, metres;
    jump_px: (h, w) bool, pixels next to a depth jump;
    fx: focal length at this resolution, pixels. Returns a new label
    image (labels renumbered 1..K)."""
    n = int(lab.max())
    if n < 2:
        return lab
    pairs = []
    for axis in (0, 1):
        for off in (1, 2):
            a = lab[:-off] if axis == 0 else lab[:, :-off]
            b = lab[off:] if axis == 0 else lab[:, off:]
            ja = jump_px[:-off] if axis == 0 else jump_px[:, :-off]
            jb = jump_px[off:] if axis == 0 else jump_px[:, off:]
            m = (a != b) & (a > 0) & (b > 0)
            if m.any():
                jump = ja[m] | jb[m]
                lo, hi = np.minimum(a[m], b[m]), np.maximum(a[m], b[m])
                pairs.append(np.column_stack([lo, hi, jump]))
    if not pairs:
        return lab
    pr = np.concatenate(pairs)
    key = pr[:, 0].astype(np.int64) * (n + 1) + pr[:, 1]
    uniq, inv = np.unique(key, return_inverse=True)
    contact = np.bincount(inv)
    jumps = np.bincount(inv, weights=pr[:, 2])
    parent = np.arange(n + 1)

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = int(parent[i])
        return i

    objs = ndimage.find_objects(lab)
    order = np.argsort(-contact)
    for k in order:
        if contact[k] < 4 or jumps[k] > max_jump_fraction * contact[k]:
            continue
        i, j = find(int(uniq[k] // (n + 1))), find(int(uniq[k] % (n + 1)))
        if i == j:
            continue
        members = [c for c in range(1, n + 1) if find(c) in (i, j)]
        pts, zs = [], []
        for c in members:
            sl = objs[c - 1]
            if sl is None:
                continue
            ys, xs = np.nonzero(lab[sl] == c)
            pts.append(np.column_stack([xs + sl[1].start, ys + sl[0].start]))
            zs.append(z[sl][ys, xs])
        allp = np.concatenate(pts).astype(np.float32)
        (_, _), (rw, rh), _ = cv2.minAreaRect(allp)
        if max(rw, rh) * float(np.median(np.concatenate(zs))) / fx <= max_extent_m:
            parent[j] = i
    roots = np.array([find(c) for c in range(n + 1)])
    roots[0] = 0
    _, new = np.unique(roots, return_inverse=True)
    return new.astype(np.int32)[lab]


def fill_enclosed_holes(lab: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """`lab` (h, w) int32 labels with the invalid-depth regions (`valid` False) that are enclosed by one label only
    (dropouts on a part's surface, not shadows beside it) given that label; other invalid pixels become 0."""
    lab = np.where(valid, lab, 0).astype(np.int32)
    rows, cols = np.flatnonzero(lab.any(axis=1)), np.flatnonzero(lab.any(axis=0))
    if len(rows) == 0:
        return lab
    # only holes within the labels' bounding box can be enclosed; one pixel of margin
    y0, y1 = max(rows[0] - 1, 0), min(rows[-1] + 2, lab.shape[0])
    x0, x1 = max(cols[0] - 1, 0), min(cols[-1] + 2, lab.shape[1])
    out = lab.copy()
    out[y0:y1, x0:x1] = _fill_enclosed(lab[y0:y1, x0:x1], valid[y0:y1, x0:x1])
    return out


def _fill_enclosed(lab: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """`fill_enclosed_holes` on a crop: holes touching the crop's border are never enclosed."""
    holes = (~valid).astype(np.uint8)
    n, cc = cv2.connectedComponents(holes, connectivity=4)
    lab = np.where(valid, lab, 0).astype(np.int32)
    if n <= 1:
        return lab
    # every valid pixel next to a hole carries that hole's id; enclosed: the labels around it are all one label > 0
    ring_id = cv2.dilate(cc.astype(np.float32), np.ones((3, 3), np.uint8)).astype(np.int32)
    ring = valid & (ring_id > 0)
    ids = ring_id[ring]
    index = np.arange(n)
    lo = np.asarray(ndimage.minimum(lab[ring], ids, index), np.float64)
    hi = np.asarray(ndimage.maximum(lab[ring], ids, index), np.float64)
    lo = np.nan_to_num(lo, nan=-1.0).astype(np.int64)
    hi = np.nan_to_num(hi, nan=-2.0).astype(np.int64)
    border = np.unique(np.concatenate([cc[0], cc[-1], cc[:, 0], cc[:, -1]]))
    fill = np.where((lo == hi) & (lo > 0), lo, 0)
    fill[border] = 0
    fill[0] = 0
    return np.where(valid, lab, fill[cc]).astype(np.int32)


def _normals(
    zb: np.ndarray, k: int, jump_m: float, jump_rel: float, fx: float, fy: float, uu: np.ndarray, vv: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit normals (nx, ny, nz), each (h, w) float32, towards the camera, of the smoothed depth `zb` (h, w) metres:
    central differences over +-k pixels; where the two one-sided differences disagree by more than a depth jump
    (jump_m + jump_rel * z), the smaller one, so that a normal next to a depth jump is that of its own side.
    uu (w,), vv (h,): normalised image coordinates of the columns and rows."""
    zu = np.zeros_like(zb)
    zv = np.zeros_like(zb)
    for axis, out in ((1, zu), (0, zv)):
        c = (slice(None), slice(k, -k)) if axis == 1 else (slice(k, -k), slice(None))
        lo = (slice(None), slice(None, -2 * k)) if axis == 1 else (slice(None, -2 * k), slice(None))
        hi = (slice(None), slice(2 * k, None)) if axis == 1 else (slice(2 * k, None), slice(None))
        dl, dr = zb[c] - zb[lo], zb[hi] - zb[c]
        one = np.where(np.abs(dl) < np.abs(dr), dl, dr)
        jt = jump_m + jump_rel * zb[c]
        out[c] = np.where(np.abs(dl - dr) > jt, one, 0.5 * (dl + dr)) * np.float32(1.0 / k)
    nx = np.float32(fx) * zu
    ny = np.float32(fy) * zv
    nz = -(nx * uu[None, :] + ny * vv[:, None] + zb)
    inv = np.float32(1.0) / (np.sqrt(nx * nx + ny * ny + nz * nz) + np.float32(1e-12))
    return nx * inv, ny * inv, nz * inv


class DepthSegmenter:
    """A `Segmenter` that needs no model: plane removal + depth/normal edges + connected components."""

    def __init__(self, options: DepthSegmenterOptions | None = None) -> None:
        self.options = options or DepthSegmenterOptions()

    def segment(self, frame: RGBDFrame) -> list[Instance]:
        """Instances (label '') of the frame, largest first; [] when depth is all invalid or nothing stands out."""
        if not isinstance(frame, RGBDFrame):
            raise InputError(f"expected an RGBDFrame, got {type(frame).__name__}")
        labels, count = self.label_image(frame)
        out: list[Instance] = []
        if count == 0:
            return out
        sizes = np.bincount(labels.ravel(), minlength=count + 1)
        order = np.argsort(-sizes[1:], kind="stable") + 1
        boxes = ndimage.find_objects(labels, max_label=count)
        for k in order:
            sl = boxes[k - 1]
            if sizes[k] < self.options.min_pixels or sl is None:
                continue
            mask = np.zeros(labels.shape, bool)
            mask[sl] = labels[sl] == k
            out.append(Instance(mask=mask, label="", score=1.0, instance_id=len(out) + 1))
        return out

    def _foreground(
        self,
        zm: np.ndarray,
        valid: np.ndarray,
        xs_m: np.ndarray,
        ys_m: np.ndarray,
        nx: np.ndarray,
        ny: np.ndarray,
        nz: np.ndarray,
        fx: float,
        planes: list[tuple[FloatArray, float, float, bool]] | None = None,
        sample_step: int = 2,
    ) -> tuple[np.ndarray, FloatArray, float]:
        """(h, w) bool: valid pixels off the support planes; the first plane's unit normal (3,) and offset. The first
        (dominant) plane is removed with everything
        behind it; further planes parallel or perpendicular to it only in connected inlier regions of at least
        min_plane_area_m2. Planes are fitted on every `sample_step`-th pixel and applied to all; every removed further
        plane is appended to `planes` as (normal, offset, tolerance, removes-what-is-behind)."""
        o = self.options
        h, w = zm.shape
        rng = np.random.default_rng(o.seed)
        tol_img = o.plane_tolerance_m + o.plane_noise_factor * 0.0026 * zm * zm
        sub_valid = np.zeros_like(valid)
        sub_valid[::sample_step, ::sample_step] = valid[::sample_step, ::sample_step]
        sidx = np.flatnonzero(sub_valid)
        pts = np.column_stack([xs_m.reshape(-1)[sidx], ys_m.reshape(-1)[sidx], zm.reshape(-1)[sidx]])
        t_sub = tol_img.reshape(-1)[sidx]
        f_sub = t_sub - (o.plane_tolerance_m - o.fit_tolerance_m)

        def dist(n: FloatArray, d: float) -> np.ndarray:
            return (np.float32(n[0]) * xs_m + np.float32(n[1]) * ys_m + np.float32(n[2]) * zm) + np.float32(d)

        n1, d1, _ = ransac_plane(pts, f_sub, o.ransac_iterations, o.ransac_samples, rng)
        n1, d1 = refine_plane(pts, f_sub, n1, d1)
        removed = (dist(n1, d1) < tol_img) | ~valid  # on the first plane or behind it
        removed_sub = removed.reshape(-1)[sidx]
        n_sub = len(sidx)
        cos_plane = np.float32(np.cos(np.radians(o.plane_normal_deg)))
        px_area = (zm / fx) ** 2  # m^2 seen by each working pixel (fronto-parallel)
        for _ in range(3):
            rest = np.flatnonzero(~removed_sub)
            if len(rest) < o.min_plane_fraction * n_sub:
                break
            n, d, _ = ransac_plane(pts[rest], f_sub[rest], o.ransac_iterations, o.ransac_samples, rng)
            n, d = refine_plane(pts[rest], f_sub[rest], n, d)
            cosang = abs(float(n @ n1))
            if cosang >= 0.95:
                # nearly parallel to the first: taken exactly parallel (a floor above the table, a belt, a rail top),
                # its offset the mean over its inliers, so that no tilted compromise of two levels is removed
                prest = pts[rest].astype(np.float64)
                inl = np.abs(prest @ n + d) < f_sub[rest]
                if inl.sum() >= 3:
                    h1 = prest[inl] @ n1
                    d_par = -float(np.median(h1))
                    near_par = np.abs(prest @ n1 + d_par) < f_sub[rest]
                    n, d, cosang = n1, -float(np.mean(prest[near_par] @ n1)) if near_par.any() else d_par, 1.0
            on_plane = (np.abs(dist(n, d)) < tol_img) & ~removed
            frac = np.count_nonzero(on_plane.reshape(-1)[sidx]) / n_sub
            if frac < o.min_plane_fraction or 0.2 < cosang < 0.95:
                break
            # remove only connected inlier regions larger than any part face (tops of parts at one height are not
            # a support surface), of inliers whose normal agrees with the plane's (a curved part touching a rail at
            # the rail's height does not join the rail's region)
            agree = np.abs(nx * np.float32(n[0]) + ny * np.float32(n[1]) + nz * np.float32(n[2])) > cos_plane
            ncc, cc = cv2.connectedComponents((on_plane & agree).astype(np.uint8), connectivity=8)
            area = np.bincount(cc.reshape(-1), weights=px_area.reshape(-1), minlength=ncc)
            big = area >= o.min_plane_area_m2
            big[0] = False
            if not big[1:].any():
                break
            removed |= big[cc]
            floor = cosang >= 0.95 and area[big].sum() >= o.support_area_m2
            if floor:
                # a floor (bin floor above the table, belt): everything on it or behind it goes, also where it shows
                # through a ring's hole or between parts in small pieces
                removed |= dist(n, d) < tol_img
            if planes is not None:
                planes.append((n, d, o.plane_tolerance_m, floor))
            removed_sub = removed.reshape(-1)[sidx]
        return ~removed, n1, d1

    def _remove_walls(
        self,
        fg: np.ndarray,
        zm: np.ndarray,
        xs_m: np.ndarray,
        ys_m: np.ndarray,
        nx: np.ndarray,
        ny: np.ndarray,
        nz: np.ndarray,
        fx: float,
        support_n: FloatArray,
        planes: list[tuple[FloatArray, float, float, bool]] | None = None,
    ) -> np.ndarray:
        """`fg` (h, w) bool without walls: planes perpendicular to the support plane (normal `support_n` (3,)),
        found by RANSAC among the foreground pixels whose normals are upright (more than wall_angle_deg from
        support_n), removed where a connected region of pixels within the plane tolerance is at least
        wall_min_length_m long (longer than any part)."""
        o = self.options
        rng = np.random.default_rng(o.seed + 1)
        n1 = np.asarray(support_n, dtype=np.float64)
        cos_up = np.float32(np.cos(np.radians(o.wall_angle_deg)))
        up = fg & (np.abs(nx * np.float32(n1[0]) + ny * np.float32(n1[1]) + nz * np.float32(n1[2])) < cos_up)
        tol_img = o.wall_tolerance_m + o.plane_noise_factor * 0.0026 * zm * zm
        z_far = float(zm[fg].max())
        fg = fg.copy()
        for _ in range(o.max_walls):
            sel = np.zeros_like(up)
            sel[::2, ::2] = up[::2, ::2]
            idx = np.flatnonzero(sel)
            if len(idx) < 50:
                break
            pts = np.column_stack([xs_m.reshape(-1)[idx], ys_m.reshape(-1)[idx], zm.reshape(-1)[idx]]).astype(
                np.float64
            )
            tol = tol_img.reshape(-1)[idx]
            # half the RANSAC budget: a wall hypothesis is two points and the known direction (support normal)
            sub = rng.integers(0, len(idx), size=min(o.ransac_samples // 2, len(idx)))
            pair = rng.integers(0, len(idx), size=(max(o.ransac_iterations // 2, 1), 2))
            normals = np.cross(pts[pair[:, 1]] - pts[pair[:, 0]], n1[None, :])
            norm = np.linalg.norm(normals, axis=1)
            good = norm > 1e-6
            if not good.any():
                break
            normals = normals[good] / norm[good, None]
            ds = -np.sum(normals * pts[pair[good, 0]], axis=1)
            ps = pts[sub]
            dist = np.abs(_dots(ps, normals) + ds[None, :])
            best = int(np.argmax((dist < tol[sub, None]).sum(axis=0)))
            n, d = normals[best], float(ds[best])
            near = fg & (
                np.abs(xs_m * np.float32(n[0]) + ys_m * np.float32(n[1]) + zm * np.float32(n[2]) + d) < tol_img
            )
            ncc, cc, stats, _ = cv2.connectedComponentsWithStats(near.astype(np.uint8), connectivity=8)
            removed_any = False
            # a region whose bounding box diagonal at the farthest depth is shorter than a wall cannot be one
            diag = np.hypot(stats[:, cv2.CC_STAT_WIDTH], stats[:, cv2.CC_STAT_HEIGHT]) * z_far / fx
            for c in np.flatnonzero((diag >= o.wall_min_length_m) & (stats[:, cv2.CC_STAT_AREA] >= 20)):
                if c == 0:
                    continue
                x0, y0 = stats[c, cv2.CC_STAT_LEFT], stats[c, cv2.CC_STAT_TOP]
                sl = (
                    slice(y0, y0 + stats[c, cv2.CC_STAT_HEIGHT]),
                    slice(x0, x0 + stats[c, cv2.CC_STAT_WIDTH]),
                )
                yy, xx = np.nonzero(cc[sl] == c)
                (_, _), (rw, rh), _ = cv2.minAreaRect(np.column_stack([xx, yy]).astype(np.float32))
                if max(rw, rh) * float(np.median(zm[sl][yy, xx])) / fx >= o.wall_min_length_m:
                    region = cc[sl] == c
                    fg[sl] &= ~region
                    up[sl] &= ~region
                    removed_any = True
            if not removed_any:
                break
            if planes is not None:
                planes.append((n, d, o.wall_tolerance_m, False))
        return fg

    def _part_like(
        self, lab: np.ndarray, zm: np.ndarray, fx: float, min_px: int, upright: np.ndarray | None = None
    ) -> np.ndarray:
        """(lab.max() + 1,) bool over the labels of `lab` (h, w): may be a part (at least `min_px` pixels, at most
        max_extent_m long, not thin and long like a wall rim or rail, not mostly `upright` (h, w) bool pixels);
        zm: depth, metres; fx: focal length, pixels."""
        o = self.options
        ok = np.zeros(int(lab.max()) + 1, bool)
        for comp0, sl in enumerate(ndimage.find_objects(lab)):
            if sl is None:
                continue
            ys, xs = np.nonzero(lab[sl] == comp0 + 1)
            if len(ys) < min_px:
                continue
            m_per_px = float(np.median(zm[sl][ys, xs])) / fx
            (_, _), (rw, rh), _ = cv2.minAreaRect(np.column_stack([xs, ys]).astype(np.float32))
            short, long_ = sorted((rw * m_per_px, rh * m_per_px))
            ok[comp0 + 1] = not (
                long_ > o.max_extent_m
                or (short < o.rim_width_m and long_ > max(o.rim_length_m, o.rim_elongation * short))
            )
            if upright is not None and ok[comp0 + 1] and long_ >= o.wall_piece_min_length_m:
                # a long piece made of faces standing upright on the support plane is a wall, not a part
                ok[comp0 + 1] = np.count_nonzero(upright[sl][ys, xs]) < o.max_wall_fraction * len(ys)
        return ok

    def label_image(self, frame: RGBDFrame) -> tuple[np.ndarray, int]:
        """(H, W) int32 label image at frame resolution (0 = background) and the number of labels."""
        o = self.options
        depth_full = np.asarray(frame.depth_m, dtype=np.float32)
        h0, w0 = depth_full.shape
        s = o.stride
        z = np.ascontiguousarray(depth_full[::s, ::s])
        z = np.where(np.isfinite(z) & (z > 0), z, np.float32(0.0)).astype(np.float32)
        valid = z > 0
        if valid.sum() < 10:
            return np.zeros((h0, w0), np.int32), 0
        h, w = z.shape
        cam = frame.camera
        fx, fy = cam.fx / s, cam.fy / s
        cx, cy = (cam.cx + 0.5) / s - 0.5, (cam.cy + 0.5) / s - 0.5
        # fill holes (normalised 7x7 box average of valid neighbours) so that normals next to dropouts are sane
        num = cv2.boxFilter(z, -1, (7, 7), normalize=False)
        den = cv2.boxFilter(valid.astype(np.float32), -1, (7, 7), normalize=False)
        zf = np.where(valid, z, np.where(den > 0, num / np.maximum(den, 1.0), 0.0)).astype(np.float32)
        zm = cv2.medianBlur(zf, 5)
        zm = np.where(zm > 0, zm, zf)
        uu = (np.arange(w, dtype=np.float32) - cx) / fx
        vv = (np.arange(h, dtype=np.float32) - cy) / fy
        xs_m, ys_m = uu[None, :] * zm, vv[:, None] * zm  # camera points (xs_m, ys_m, zm), metres

        # 1. normals from box-smoothed depth: n ~ (fx z_u, fy z_v, -(fx x z_u + fy y z_v + z)) for the pinhole
        # model (x, y: normalised image coordinates; z_u, z_v: depth derivatives per working pixel), towards the camera
        zb = cv2.boxFilter(zm, -1, (3, 3))
        zb = np.where(zm > 0, zb, zm)
        k = o.normal_step
        nx, ny, nz = _normals(zb, k, o.depth_jump_m, o.depth_jump_rel, fx, fy, uu, vv)
        xb, yb = uu[None, :] * zb, vv[:, None] * zb

        # 2. support planes
        # planes and walls are found on every second working pixel (a quarter of the work); the dominant plane is
        # then applied exactly, the further planes and walls by their upsampled coarse regions
        c = (slice(None, None, 2), slice(None, None, 2))
        zc, xc, yc = zm[c], xs_m[c], ys_m[c]
        nc = (nx[c], ny[c], nz[c])
        planes: list[tuple[FloatArray, float, float, bool]] = []
        fg_c, support_n, support_d = self._foreground(zc, valid[c], xc, yc, *nc, fx / 2, planes, 1)
        if o.max_walls > 0 and fg_c.any():
            fg_c = self._remove_walls(fg_c, zc, xc, yc, *nc, fx / 2, support_n, planes)
        noise = o.plane_noise_factor * 0.0026 * zm * zm

        def signed(n: FloatArray, d: float) -> np.ndarray:
            return (np.float32(n[0]) * xs_m + np.float32(n[1]) * ys_m + np.float32(n[2]) * zm) + np.float32(d)

        fg = valid & ~(signed(support_n, support_d) < o.plane_tolerance_m + noise)
        extra_c = ~fg_c & fg[c]
        if extra_c.any() and planes:
            # near the coarse regions of the further planes and walls, their inliers at working resolution
            near_c = cv2.dilate(extra_c.astype(np.uint8), np.ones((3, 3), np.uint8))
            near = cv2.resize(near_c, (w, h), interpolation=cv2.INTER_NEAREST).astype(bool)
            hit = np.zeros((h, w), bool)
            for n, d, tol, behind in planes:
                dist = signed(n, d)
                hit |= (dist < tol + noise) if behind else (np.abs(dist) < tol + noise)
            fg &= ~(near & hit)
        if o.rim_open_m > 0 and fg.any():
            fg = _remove_rims(fg, zm, fx, o.rim_open_m, o.rim_length_m)

        # 3. edges
        edge = np.zeros((h, w), bool)
        jump_px = np.zeros((h, w), bool)
        jump_thr = o.depth_jump_m + o.depth_jump_rel * zm
        cos_thr = np.float32(np.cos(np.radians(o.crease_angle_deg)))
        gap = 2 * k + 4  # normals compared across supports that do not overlap, with the smoothing's width between
        for axis in (0, 1):
            a = (slice(None, -1), slice(None)) if axis == 0 else (slice(None), slice(None, -1))
            b = (slice(1, None), slice(None)) if axis == 0 else (slice(None), slice(1, None))
            step = np.abs(np.diff(zm, axis=axis))
            # a step is a discontinuity when the neighbouring steps do not explain it (steep faces have runs of
            # similar steps, an occluding border has one isolated step)
            pad = ((1, 1), (0, 0)) if axis == 0 else ((0, 0), (1, 1))
            sp = np.pad(step, pad, mode="edge")
            around = np.maximum(sp[:-2], sp[2:]) if axis == 0 else np.maximum(sp[:, :-2], sp[:, 2:])
            jump = (step - around > jump_thr[a]) if o.steep_faces else (step > jump_thr[a])
            jump &= valid[a] & valid[b]
            jump_px[a] |= jump
            jump_px[b] |= jump
            a = (slice(None, -gap), slice(None)) if axis == 0 else (slice(None), slice(None, -gap))
            b = (slice(gap, None), slice(None)) if axis == 0 else (slice(None), slice(gap, None))
            cos = nx[a] * nx[b] + ny[a] * ny[b] + nz[a] * nz[b]
            concave = (nx[a] - nx[b]) * (xb[a] - xb[b]) + (ny[a] - ny[b]) * (yb[a] - yb[b])
            concave += (nz[a] - nz[b]) * (zb[a] - zb[b])
            crease = (cos < cos_thr) & (concave < 0) & valid[a] & valid[b]
            for off in range(k + 1, gap - k):  # the pixels between the two supports
                m = (
                    (slice(off, off + crease.shape[0]), slice(None))
                    if axis == 0
                    else (slice(None), slice(off, off + crease.shape[1]))
                )
                edge[m] |= crease
        edge |= jump_px
        core = fg & ~edge

        # 4. components
        min_px = max(1, int(np.ceil(o.min_pixels / (s * s) * 0.5)))
        frag_px = max(1, int(np.ceil(o.min_fragment_pixels / (s * s) * 0.5)))
        count, lab, stats, _ = cv2.connectedComponentsWithStats(core.astype(np.uint8), connectivity=4)
        keep = np.zeros(count, bool)
        keep[1:] = stats[1:, cv2.CC_STAT_AREA] >= frag_px
        lab = np.where(keep[lab], lab, 0).astype(np.int32)
        if not keep.any():
            return np.zeros((h0, w0), np.int32), 0
        # give edge pixels (and dropped small bits) of the foreground to the nearest kept component within 3 px
        seeds = (lab == 0).astype(np.uint8)
        dist, nearest = cv2.distanceTransformWithLabels(seeds, cv2.DIST_L2, 3, labelType=cv2.DIST_LABEL_PIXEL)
        ys, xs = np.nonzero(lab)
        pix_label = np.zeros(int(nearest.max()) + 1, np.int32)
        pix_label[nearest[ys, xs]] = lab[ys, xs]
        grow = fg & (lab == 0) & (dist <= 3.0)
        lab[grow] = pix_label[nearest[grow]]
        # foreground left over (all edge: a thin steep leg, a grazing face) becomes components of its own, for the
        # merge to join to a neighbour across a boundary without depth jumps
        left = fg & (lab == 0)
        if left.any():
            nleft, llab, lstats, _ = cv2.connectedComponentsWithStats(left.astype(np.uint8), connectivity=8)
            big = np.zeros(nleft, bool)
            big[1:] = lstats[1:, cv2.CC_STAT_AREA] >= frag_px
            if big.any():
                ids = np.zeros(nleft, np.int32)
                ids[big] = np.arange(1, int(big.sum()) + 1, dtype=np.int32) + int(lab.max())
                lab = np.where(left, ids[llab], lab).astype(np.int32)

        if o.merge_max_extent_m > 0:
            lab = merge_continuous(
                lab,
                jump_px,
                zm,
                fx,
                o.merge_max_extent_m,
                o.merge_max_jump_fraction,
            )

        # size / shape filters in metres
        cos_up = np.float32(np.cos(np.radians(o.wall_angle_deg)))
        upright = np.abs(nx * np.float32(support_n[0]) + ny * np.float32(support_n[1]) + nz * np.float32(support_n[2]))
        upright = upright < cos_up
        ok = self._part_like(lab, zm, fx, min_px, upright)
        keep_ids = np.flatnonzero(ok)
        final = np.zeros(int(lab.max()) + 1, np.int32)
        final[keep_ids] = np.arange(1, len(keep_ids) + 1, dtype=np.int32)
        next_id = len(keep_ids)
        lab = final[lab]
        if next_id == 0:
            return np.zeros((h0, w0), np.int32), 0
        lab = fill_enclosed_holes(lab, valid)
        up = cv2.resize(lab, (w0, h0), interpolation=cv2.INTER_NEAREST) if s > 1 else lab
        # full-resolution dropouts: kept inside a label only where the working-resolution label covers them and some
        # neighbour within the working pixel is valid or the dropout is enclosed (filled above)
        return up.astype(np.int32), next_id
