"""Per-template data the fitter reuses: surface samples with normals, KD-tree, distance grid, descriptors.

Built once per `Template` object and cached (weakly) so fitting many instances costs nothing extra.
"""

from __future__ import annotations

import threading
import weakref
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt
from scipy.spatial import cKDTree

from normpos_grasp.records.template import Template

if TYPE_CHECKING:
    import trimesh
from normpos_grasp.typing import FloatArray, IntArray

_CACHE: weakref.WeakKeyDictionary[Template, PreparedTemplate] = weakref.WeakKeyDictionary()
_LOCK = threading.Lock()

N_SAMPLES = 4000
GRID = 48
#: distance-grid cells whose centre lies within this many cells of the surface keep exact-nearest candidates
CANDIDATE_CELLS = 1.5


@dataclass(frozen=True, eq=False)
class PreparedTemplate:
    """Cached template geometry (object frame, metres).

    samples / normals: (S, 3) surface points and outward unit normals. tree: cKDTree on samples.
    centroid (3,): area centroid. axes (3, 3): principal axes as columns, eigenvalues descending.
    diameter: metres. spacing: mean sample spacing, metres. grid_origin (3,), grid_cell: distance-grid frame;
    grid_index: (G, G, G) nearest sample per cell. sym: (M, 4, 4) symmetry transforms incl. identity.
    desc_idx: (F,) sample indices with FPFH descriptors `desc` (F, 33); desc_tree on them.
    grid / kd: the distance grids (with per-cell exact-nearest candidates) and flat KD-trees (all samples,
    then per normal bin) in the layout of `kernels` (compiled correspondences).
    """

    samples: FloatArray
    normals: FloatArray
    tree: cKDTree
    centroid: FloatArray
    axes: FloatArray
    eigvals: FloatArray
    diameter: float
    spacing: float
    grid_origin: FloatArray
    grid_cell: float
    grid_index: npt.NDArray[np.int32]
    grid_index_bins: npt.NDArray[np.int32]
    bin_trees: tuple[tuple[cKDTree | None, IntArray], ...]
    sym: FloatArray
    desc_idx: IntArray
    desc: FloatArray
    desc_tree: cKDTree
    voxel: float
    grid: tuple[np.ndarray, ...]
    kd: tuple[np.ndarray, ...]

    def grid_lookup(self, points: FloatArray) -> tuple[IntArray, FloatArray]:
        """(P, 3) object-frame points -> nearest-sample index (P,) and a bool-as-float inside-grid flag (P,)."""
        ijk = np.floor((points - self.grid_origin) / self.grid_cell).astype(np.int64)
        g = self.grid_index.shape[0]
        inside = np.all((ijk >= 0) & (ijk < g), axis=-1)
        ijk = np.clip(ijk, 0, g - 1)
        idx = self.grid_index[ijk[..., 0], ijk[..., 1], ijk[..., 2]].astype(np.int64)
        return idx, inside.astype(np.float64)

    def grid_lookup_binned(self, points: FloatArray, bins: IntArray) -> tuple[IntArray, FloatArray]:
        """Like `grid_lookup` but the nearest sample whose normal falls in `bins` (P,) (see `normal_bins`)."""
        ijk = np.floor((points - self.grid_origin) / self.grid_cell).astype(np.int64)
        g = self.grid_index.shape[0]
        inside = np.all((ijk >= 0) & (ijk < g), axis=-1)
        ijk = np.clip(ijk, 0, g - 1)
        idx = self.grid_index_bins[bins, ijk[..., 0], ijk[..., 1], ijk[..., 2]].astype(np.int64)
        return idx, (inside & (idx >= 0)).astype(np.float64)

    def nearest_binned(self, points: FloatArray, bins: IntArray) -> tuple[FloatArray, IntArray]:
        """Exact nearest sample with a normal in the same bin: distances (P,) (inf if none), indices (P,)."""
        dist = np.full(len(points), np.inf)
        idx = np.zeros(len(points), dtype=np.int64)
        for b, (tree, members) in enumerate(self.bin_trees):
            sel = np.flatnonzero(bins == b)
            if tree is None or len(sel) == 0:
                continue
            d, i = tree.query(points[sel])
            dist[sel] = d
            idx[sel] = members[i]
        return dist, idx


def normal_bins(normals: FloatArray) -> IntArray:
    """(P,) bin 0..5 of each normal: dominant axis and sign (+x, -x, +y, -y, +z, -z)."""
    ax = np.argmax(np.abs(normals), axis=-1)
    sign = np.take_along_axis(normals, ax[..., None], axis=-1)[..., 0] < 0
    return (2 * ax + sign).astype(np.int64)


def prepare(template: Template) -> PreparedTemplate:
    """The cached `PreparedTemplate` of `template` (built on first use, about 0.1-0.3 s)."""
    with _LOCK:
        hit = _CACHE.get(template)
    if hit is not None:
        return hit
    prepared = _build(template)
    with _LOCK:
        _CACHE[template] = prepared
    return prepared


def _build(template: Template) -> PreparedTemplate:
    from normpos_grasp.templates.features import fpfh, voxel_downsample

    mesh = template.mesh
    rng = np.random.default_rng(12345)
    area = np.asarray(mesh.area_faces, dtype=np.float64)
    probs = area / area.sum()
    face = rng.choice(len(area), size=N_SAMPLES, p=probs)
    tri = np.asarray(mesh.triangles, dtype=np.float64)[face]
    r1 = np.sqrt(rng.random(N_SAMPLES))[:, None]
    r2 = rng.random(N_SAMPLES)[:, None]
    samples = (1 - r1) * tri[:, 0] + r1 * (1 - r2) * tri[:, 1] + r1 * r2 * tri[:, 2]
    normals = np.asarray(mesh.face_normals, dtype=np.float64)[face]
    if not mesh.is_winding_consistent:
        normals = _orient_outward(mesh, samples, normals)
    # replace random sampling by a well-spread subset (farthest-point-like via voxel thinning)
    centroid = (area[:, None] * np.asarray(mesh.triangles_center)).sum(0) / area.sum()
    cov = np.cov((samples - centroid).T)
    eigvals, axes = np.linalg.eigh(cov)
    order = np.argsort(eigvals)[::-1]
    eigvals = eigvals[order]
    axes = axes[:, order]
    if np.linalg.det(axes) < 0:
        axes[:, 2] *= -1
    hull = np.asarray(mesh.convex_hull.vertices, dtype=np.float64)
    if len(hull) > 600:
        hull = hull[rng.choice(len(hull), 600, replace=False)]
    diameter = float(np.max(np.linalg.norm(hull[:, None] - hull[None], axis=-1)))
    spacing = float(np.sqrt(area.sum() / N_SAMPLES))
    tree = cKDTree(samples)
    lo = samples.min(0)
    hi = samples.max(0)
    pad = 0.35 * diameter
    cell = float(np.max(hi - lo + 2 * pad) / GRID)
    origin = lo - pad
    centers = origin + (np.stack(np.meshgrid(*[np.arange(GRID)] * 3, indexing="ij"), -1) + 0.5) * cell
    flat = centers.reshape(-1, 3)
    gdist, gidx = tree.query(flat)
    grid_index = np.asarray(gidx, dtype=np.int32).reshape(GRID, GRID, GRID)
    # exact-nearest candidates of cells near the surface: a point in a cell whose centre lies d_c from its
    # nearest sample is at most d_c + h from that sample (h: half the cell diagonal), so its nearest sample
    # lies within d_c + 2 h of the centre
    near = np.flatnonzero(gdist <= CANDIDATE_CELLS * cell)
    balls = tree.query_ball_point(flat[near], gdist[near] + np.sqrt(3.0) * cell * (1.0 + 1e-9), return_sorted=False)
    counts = np.zeros(GRID**3, dtype=np.int64)
    counts[near] = [len(b) for b in balls]
    cand_start = np.zeros(GRID**3 + 1, dtype=np.int64)
    np.cumsum(counts, out=cand_start[1:])
    cand_idx = np.concatenate([np.asarray(b, dtype=np.int32) for b in balls]) if len(near) else np.zeros(0, np.int32)
    sbins = normal_bins(normals)
    bin_grids = np.full((6, GRID, GRID, GRID), -1, dtype=np.int32)
    bin_trees: list[tuple[cKDTree | None, IntArray]] = []
    for b in range(6):
        members = np.flatnonzero(sbins == b)
        if len(members) == 0:
            bin_trees.append((None, members))
            continue
        btree = cKDTree(samples[members])
        _, bi = btree.query(flat)
        bin_grids[b] = members[np.asarray(bi)].reshape(GRID, GRID, GRID)
        bin_trees.append((btree, members))
    from normpos_grasp.templates.kernels import build_kdtrees

    cells = np.full((GRID, GRID, GRID, 8), -1, dtype=np.int16 if N_SAMPLES < 2**15 else np.int32)
    cells[..., 0] = grid_index
    cells[..., 1:7] = np.moveaxis(bin_grids, 0, -1)

    kd = build_kdtrees(samples, [np.arange(len(samples))] + [m for _, m in bin_trees])
    voxel = diameter / 18.0
    keep = voxel_downsample(samples, voxel)
    desc = fpfh(samples[keep], normals[keep], voxel * 2.5)
    return PreparedTemplate(
        samples=samples,
        normals=normals,
        tree=tree,
        centroid=centroid,
        axes=axes,
        eigvals=eigvals,
        diameter=diameter,
        spacing=spacing,
        grid_origin=origin,
        grid_cell=cell,
        grid_index=grid_index,
        grid_index_bins=bin_grids,
        bin_trees=tuple(bin_trees),
        sym=template.symmetry.transforms(continuous_steps=12),
        desc_idx=keep,
        desc=desc,
        desc_tree=cKDTree(desc),
        voxel=voxel,
        grid=(
            np.asarray(origin, dtype=np.float64),
            np.array([cell, pad]),
            cells,
            cand_start,
            cand_idx,
            np.asarray(gdist, dtype=np.float64),
            sbins.astype(np.int64),
        ),
        kd=kd,
    )


def _orient_outward(mesh: trimesh.Trimesh, points: FloatArray, normals: FloatArray) -> FloatArray:
    """Flip normals that point into the solid: a ray along an outward normal leaves a closed mesh after an
    even number of crossings (used when the face winding is inconsistent)."""
    eps = 1e-6 * max(float(mesh.scale), 1e-9)
    origins = points + normals * eps
    _, ray_idx, _ = mesh.ray.intersects_location(origins, normals, multiple_hits=True)
    hits = np.bincount(np.asarray(ray_idx, dtype=np.int64), minlength=len(points))
    out = normals.copy()
    out[hits % 2 == 1] *= -1.0
    return out
