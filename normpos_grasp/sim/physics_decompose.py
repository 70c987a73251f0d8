"""Approximate convex decomposition of template meshes for physics: recursive plane splits (no external solver).

A watertight mesh whose volume is close to its hull's is returned as its hull. Otherwise the solid is split
recursively by planes (candidate planes along its principal and frame axes at several positions, the one
with the smallest sum of the two halves' hull volumes wins, as in V-HACD) until every piece fills its hull
to within `DecompositionOptions.min_fill`. Pieces are clipped exactly: every piece carries its triangles
plus planar fan caps closing each cut, so its volume is exact (signed-volume sums stay valid for caps of
any shape, holes included) and its hull is the hull of the clipped surface vertices.

`collision_hulls` makes any list of pieces one that MuJoCo's mesh compiler accepts (its convex hull of a flat
point set fails with "mesh has coplanar vertices"): duplicates merged, pieces without area dropped, flat or thin
pieces thickened to a minimum thickness.
"""

from __future__ import annotations

import hashlib
import logging
from dataclasses import dataclass

import numpy as np
from scipy.spatial import ConvexHull, QhullError

from normpos_grasp.errors import MeshError
from normpos_grasp.typing import BoolArray, FloatArray

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class DecompositionOptions:
    """Settings of the recursive plane-split decomposition.

    min_fill: a piece whose volume / hull volume is at least this stays whole (0..1).
    max_pieces: upper bound on the number of convex pieces.
    max_depth: recursion depth limit.
    positions: relative positions (0..1 along a piece's extent) tried for each candidate plane.
    min_piece_fraction: candidate splits leaving a side with less than this share of the piece's volume are skipped.
    """

    min_fill: float = 0.9
    max_pieces: int = 24
    max_depth: int = 10
    positions: tuple[float, ...] = (0.2, 0.35, 0.5, 0.65, 0.8)
    min_piece_fraction: float = 0.02


@dataclass(frozen=True, eq=False)
class ConvexPiece:
    """One convex piece: `vertices` (K, 3) hull vertices in the mesh frame (metres); `volume_m3` the solid's
    volume inside this piece; `hull_volume_m3` its hull's volume."""

    vertices: FloatArray
    volume_m3: float
    hull_volume_m3: float


@dataclass(frozen=True, eq=False)
class _Piece:
    tris: FloatArray  # (M, 3, 3) closed triangle chain (surface + caps)
    real: BoolArray  # (M,) True for triangles of the original surface
    planes: tuple[tuple[FloatArray, float], ...] = ()  # the cell: normal . x <= offset for each


_CACHE: dict[str, tuple[ConvexPiece, ...]] = {}

#: thinnest collision piece handed to MuJoCo, m (thinner pieces are thickened to it, symmetrically)
MIN_THICKNESS_M = 1e-3


def collision_hull(points: FloatArray, min_thickness_m: float = MIN_THICKNESS_M) -> FloatArray | None:
    """(K, 3) points of one convex collision piece (metres) that MuJoCo's convex hull accepts, or None to drop it.

    Duplicate points (within 1e-9 m) are merged. A piece spanning no area (fewer than 3 points, all on one line or
    at one point) is dropped. A piece thinner than `min_thickness_m` across its thinnest principal direction
    (flat, all points on one plane, included) is thickened symmetrically to `min_thickness_m` along it, so its
    hull has volume and its mid-surface stays where it was.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    if len(pts) < 3:
        return None
    pts = np.unique(np.round(pts, 9), axis=0)
    if len(pts) < 3:
        return None
    centre = pts.mean(axis=0)
    _, sv, vt = np.linalg.svd(pts - centre, full_matrices=False)
    size = float(np.ptp(pts @ vt[0]))
    if size <= 0.0 or np.ptp(pts @ vt[1]) <= 1e-9 * max(size, 1e-3):  # a point or a line: no area
        return None
    normal = vt[2]
    width = float(np.ptp(pts @ normal))
    if width < min_thickness_m:
        half = 0.5 * (min_thickness_m - width)
        pts = np.concatenate([pts + half * normal, pts - half * normal])
    if _hull(pts) is None:  # still no usable hull (numerically degenerate): drop it
        return None
    return pts


def collision_hulls(
    pieces: list[FloatArray] | tuple[FloatArray, ...], min_thickness_m: float = MIN_THICKNESS_M
) -> list[FloatArray]:
    """`collision_hull` of each piece, dropped ones left out (see there). Raises MeshError when none is left."""
    out = [h for h in (collision_hull(p, min_thickness_m) for p in pieces) if h is not None]
    if len(out) < len(pieces):
        logger.debug("dropped %d collision pieces without area", len(pieces) - len(out))
    if not out:
        raise MeshError("collision geometry: every convex piece is degenerate (no area); the mesh is degenerate")
    return out


def convex_decomposition(
    vertices: FloatArray, faces: np.ndarray, options: DecompositionOptions | None = None
) -> tuple[ConvexPiece, ...]:
    """Split a closed triangle mesh ((V, 3) vertices in metres, (F, 3) faces) into convex pieces.

    Results are cached by mesh content and options (templates are decomposed once per process).
    Raises MeshError for an empty, degenerate or open mesh (volume <= 0).
    """
    opts = options or DecompositionOptions()
    v = np.ascontiguousarray(vertices, dtype=np.float64)
    f = np.ascontiguousarray(faces, dtype=np.int64)
    if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3 or len(f) < 4:
        raise MeshError(f"convex decomposition: expected (V, 3) vertices and (F>=4, 3) faces, got {v.shape}, {f.shape}")
    key = hashlib.sha1(v.tobytes() + f.tobytes() + repr(opts).encode()).hexdigest()
    if key in _CACHE:
        return _CACHE[key]
    tris = v[f]
    volume = _chain_volume(tris)
    if not np.isfinite(volume) or volume <= 0.0:
        raise MeshError(
            f"convex decomposition: mesh volume is {volume:.3g} m^3; expected a closed, outward-oriented mesh "
            "(repair it with trimesh: fix_normals / fill_holes)"
        )
    root = _Piece(tris, np.ones(len(tris), dtype=bool))
    leaves = _split([root], opts, volume, tris)
    pieces = []
    for leaf in leaves:
        pts = _piece_points(leaf, tris)
        hull = _hull(pts)
        if hull is None:
            continue
        pieces.append(ConvexPiece(pts[hull.vertices].copy(), _chain_volume(leaf.tris), float(hull.volume)))
    if not pieces:
        raise MeshError("convex decomposition: no piece with volume was found; the mesh is degenerate")
    result = tuple(pieces)
    _CACHE[key] = result
    logger.debug("decomposed mesh (%d faces) into %d convex pieces", len(f), len(result))
    return result


def _split(leaves: list[_Piece], opts: DecompositionOptions, total_volume: float, solid: FloatArray) -> list[_Piece]:
    """Split the piece with the most missing volume first until all fill their hulls or limits are hit."""
    done: list[_Piece] = []
    todo: list[tuple[float, float, float, int, _Piece]] = []  # (missing, volume, hull volume, depth, piece)

    def push(piece: _Piece, depth: int) -> None:
        vol = _chain_volume(piece.tris)
        hull = _hull(_piece_points(piece, solid))
        hv = float(hull.volume) if hull is not None else 0.0
        todo.append((hv - vol, vol, hv, depth, piece))

    for leaf in leaves:
        push(leaf, 0)
    while todo:
        k = int(np.argmax([t[0] for t in todo]))
        missing, vol, hv, depth, piece = todo.pop(k)
        fill = vol / hv if hv > 0 else 1.0
        if (
            fill >= opts.min_fill
            or depth >= opts.max_depth
            or len(done) + len(todo) + 2 > opts.max_pieces
            or missing < 1e-3 * total_volume
        ):
            done.append(piece)
            continue
        halves = _best_split(piece, vol, opts, solid)
        if halves is None:
            done.append(piece)
            continue
        for h in halves:
            push(h, depth + 1)
    return done


def _best_split(
    piece: _Piece, volume: float, opts: DecompositionOptions, solid: FloatArray
) -> tuple[_Piece, _Piece] | None:
    pts = piece.tris[piece.real].reshape(-1, 3)
    centre = pts.mean(axis=0)
    _, _, vt = np.linalg.svd(pts - centre, full_matrices=False)
    axes = [vt[0], vt[1], vt[2], np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), np.array([0, 0, 1.0])]
    uniq: list[FloatArray] = []
    for a in axes:
        a = a / np.linalg.norm(a)
        if all(abs(float(a @ u)) < 0.999 for u in uniq):
            uniq.append(a)
    best: tuple[float, _Piece, _Piece] | None = None
    for axis in uniq:
        s = pts @ axis
        lo, hi = float(s.min()), float(s.max())
        if hi - lo < 1e-6:
            continue
        for t in opts.positions:
            offset = _off_vertices(piece.tris @ axis, lo + t * (hi - lo), 1e-7 * (hi - lo))
            left = _clip(piece, axis, offset)
            right = _clip(piece, -axis, -offset)
            vl, vr = _chain_volume(left.tris), _chain_volume(right.tris)
            if min(vl, vr) < opts.min_piece_fraction * volume:
                continue
            hl, hr = _hull(_piece_points(left, solid)), _hull(_piece_points(right, solid))
            if hl is None or hr is None:
                continue
            cost = float(hl.volume + hr.volume)
            if best is None or cost < best[0] - 1e-12:
                best = (cost, left, right)
    if best is None:
        return None
    return best[1], best[2]


def _clip(piece: _Piece, normal: FloatArray, offset: float) -> _Piece:
    """Keep the part of the closed chain with normal . x <= offset and close the cut with a fan cap."""
    tris, real = piece.tris, piece.real
    d = tris @ normal - offset  # (M, 3)
    inside = d <= 0.0
    n_in = inside.sum(axis=1)
    out_tris: list[FloatArray] = [tris[n_in == 3]]
    out_real: list[BoolArray] = [real[n_in == 3]]
    segs: list[FloatArray] = []
    for count in (1, 2):
        sel = np.nonzero(n_in == count)[0]
        if len(sel) == 0:
            continue
        t, dd, ins, r = tris[sel], d[sel], inside[sel], real[sel]
        # rotate each triangle's vertex order (keeping orientation) so the odd vertex comes first
        odd = ins if count == 1 else ~ins
        first = np.argmax(odd, axis=1)
        idx = (first[:, None] + np.arange(3)[None, :]) % 3
        t = np.take_along_axis(t, idx[:, :, None], axis=1)
        dd = np.take_along_axis(dd, idx, axis=1)
        a, b, c = t[:, 0], t[:, 1], t[:, 2]
        da, db, dc = dd[:, 0:1], dd[:, 1:2], dd[:, 2:3]
        ab = a + (b - a) * (da / (da - db))
        ac = a + (c - a) * (da / (da - dc))
        if count == 1:  # a inside: triangle (a, ab, ac); cut edge ab -> ac
            out_tris.append(np.stack([a, ab, ac], axis=1))
            out_real.append(r)
            segs.append(np.stack([ab, ac], axis=1))
        else:  # b, c inside, a outside: polygon (ab, b, c, ac); cut edge ac -> ab
            out_tris.append(np.stack([ab, b, c], axis=1))
            out_tris.append(np.stack([ab, c, ac], axis=1))
            out_real.extend([r, r])
            segs.append(np.stack([ac, ab], axis=1))
    if segs:
        seg = np.concatenate(segs)
        apex = seg.reshape(-1, 3).mean(axis=0)
        apex = apex - (apex @ normal - offset) * normal  # on the plane
        caps = np.stack([np.broadcast_to(apex, seg[:, 0].shape), seg[:, 1], seg[:, 0]], axis=1)
        out_tris.append(caps)
        out_real.append(np.zeros(len(caps), dtype=bool))
    return _Piece(np.concatenate(out_tris), np.concatenate(out_real), (*piece.planes, (normal, offset)))


def _piece_points(piece: _Piece, solid: FloatArray) -> FloatArray:
    """(K, 3) points whose hull is the piece's hull: the clipped surface vertices plus the corners where three
    cut planes meet inside the material (such corners lie on no surface triangle)."""
    real = np.unique(piece.tris[piece.real].reshape(-1, 3), axis=0)
    planes = piece.planes
    if len(planes) < 3:
        return real
    idx = np.array(
        [(i, j, k) for i in range(len(planes)) for j in range(i + 1, len(planes)) for k in range(j + 1, len(planes))]
    )
    normals = np.stack([p[0] for p in planes])
    offsets = np.array([p[1] for p in planes])
    mats = normals[idx]  # (T, 3, 3)
    ok = np.abs(np.linalg.det(mats)) > 1e-9
    if not ok.any():
        return real
    pts = np.linalg.solve(mats[ok], offsets[idx[ok]][..., None])[..., 0]
    pts = pts[np.all(pts @ normals.T <= offsets + 1e-9, axis=1)]
    if len(pts) == 0:
        return real
    inside = _winding_number(pts, solid) > 0.5
    return np.concatenate([real, pts[inside]])


def _winding_number(points: FloatArray, tris: FloatArray) -> FloatArray:
    """(P,) generalised winding number of (P, 3) points w.r.t. the closed triangle set (M, 3, 3)."""
    out = np.empty(len(points))
    for start in range(0, len(points), 256):
        q = points[start : start + 256]
        a = tris[None, :, 0] - q[:, None]
        b = tris[None, :, 1] - q[:, None]
        c = tris[None, :, 2] - q[:, None]
        la, lb, lc = (np.linalg.norm(x, axis=-1) for x in (a, b, c))
        det = np.einsum("pmi,pmi->pm", a, np.cross(b, c))
        den = (
            la * lb * lc
            + np.einsum("pmi,pmi->pm", a, b) * lc
            + np.einsum("pmi,pmi->pm", b, c) * la
            + np.einsum("pmi,pmi->pm", c, a) * lb
        )
        out[start : start + 256] = np.arctan2(det, den).sum(axis=1) / (2.0 * np.pi)
    return out


def _off_vertices(dist: FloatArray, offset: float, step: float) -> float:
    """Nudge a plane offset so that no vertex lies on the plane (a vertex exactly on it would close a cut twice)."""
    for _ in range(100):
        if not np.any(np.abs(dist - offset) < 0.5 * step):
            break
        offset += step
    return offset


def _chain_volume(tris: FloatArray) -> float:
    """Signed volume enclosed by a closed triangle chain (M, 3, 3), m^3."""
    if len(tris) == 0:
        return 0.0
    return float(np.einsum("ij,ij->i", tris[:, 0], np.cross(tris[:, 1], tris[:, 2])).sum() / 6.0)


def _hull(points: FloatArray) -> ConvexHull | None:
    if len(points) < 4:
        return None
    try:
        hull = ConvexHull(points)
    except QhullError:
        return None
    return hull if hull.volume > 1e-12 else None
