"""Per-template data the fitter reuses: surface samples with normals, KD-tree, distance grid, descriptors.

Built once per mesh and cached in memory (per `Template` object, weakly, and per mesh) so fitting many instances
costs nothing extra, and on disk (`prepare`, `cache_dirs`) so a fresh process's first fit pays no preparation.
"""

from __future__ import annotations

import hashlib
import logging
import os
import threading
import time
import weakref
import zipfile
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt
from scipy.spatial import cKDTree

from normpos_grasp.atomic import atomic_open
from normpos_grasp.records.template import Template

if TYPE_CHECKING:
    import trimesh
from normpos_grasp.typing import FloatArray, IntArray

logger = logging.getLogger(__name__)

_CACHE: weakref.WeakKeyDictionary[Template, PreparedTemplate] = weakref.WeakKeyDictionary()
_LOCK = threading.Lock()
#: prepared arrays by `cache_key` (templates with the same mesh share them), most recent last
_BY_KEY: OrderedDict[str, dict[str, np.ndarray]] = OrderedDict()
_MAX_SHARED = 32

N_SAMPLES = 4000
GRID = 48
#: distance-grid cells whose centre lies within this many cells of the surface keep exact-nearest candidates
CANDIDATE_CELLS = 1.5
_SEED = 12345
_HULL_POINTS = 600  # hull vertices kept for the diameter
_VOXEL_DIV = 18.0  # descriptor voxel = diameter / this
_FPFH_RADIUS = 2.5  # descriptor radius, voxels
#: version of the stored layout (`_LAYOUT`) and of the preparation's method; bump when either changes
FORMAT_VERSION = 2
CACHE_ENV = "NORMPOS_GRASP_CACHE_DIR"
CACHE_FOLDER = ".prepared"


@dataclass(frozen=True, eq=False)
class PreparedTemplate:
    """Cached template geometry (object frame, metres).

    samples / normals: (S, 3) surface points and outward unit normals. tree: cKDTree on samples.
    centroid (3,): area centroid. axes (3, 3): principal axes of the surface as columns, eigenvalues descending
    (exact area moments, `surface_axes`).
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


def prepare(template: Template, *, persist: bool = True) -> PreparedTemplate:
    """The cached `PreparedTemplate` of `template`.

    In memory it is kept per template object and per mesh (templates with the same mesh share it). On disk
    (`persist`) it is stored once and loaded in later processes (`cache_dirs`; ~0.05 s instead of 0.5-2 s of
    preparation): an npz of plain arrays keyed by `cache_key` (mesh bytes, preparation parameters, format
    version), validated on load and rebuilt when it is missing, stale or damaged.
    """
    with _LOCK:
        hit = _CACHE.get(template)
    if hit is not None:
        return hit
    key = cache_key(template)
    with _LOCK:
        arrays = _BY_KEY.get(key)
    if arrays is None:
        arrays = _load_or_build(template, key) if persist else _compute(template.mesh)
        with _LOCK:
            _BY_KEY[key] = arrays
            while len(_BY_KEY) > _MAX_SHARED:
                _BY_KEY.pop(next(iter(_BY_KEY)))
    elif persist:
        _store_own(template, key, arrays)
    prepared = _assemble(arrays, template.symmetry.transforms(continuous_steps=12))
    with _LOCK:
        _CACHE[template] = prepared
    return prepared


def cache_key(template: Template) -> str:
    """sha256 (hex) of the template's mesh bytes (float64 vertices, int64 faces), the preparation parameters and
    `FORMAT_VERSION`: what the stored preparation depends on (the symmetry is applied after loading)."""
    from normpos_grasp.templates.kernels import LEAF_SIZE

    mesh = template.mesh
    h = hashlib.sha256()
    params = (
        FORMAT_VERSION,
        N_SAMPLES,
        GRID,
        CANDIDATE_CELLS,
        _SEED,
        _HULL_POINTS,
        _VOXEL_DIV,
        _FPFH_RADIUS,
        LEAF_SIZE,
    )
    h.update(repr(params).encode())
    h.update(np.ascontiguousarray(mesh.vertices, dtype=np.float64).tobytes())
    h.update(np.ascontiguousarray(mesh.faces, dtype=np.int64).tobytes())
    return h.hexdigest()


def cache_dirs(template: Template) -> list[Path]:
    """Folders where the template's preparation is looked up and stored, in order: `.prepared` inside the
    template's folder (its `source`: a template folder, or the folder of a BOP model file), then the user cache
    (`$NORMPOS_GRASP_CACHE_DIR`, else `$XDG_CACHE_HOME/normpos-grasp/prepared`, else
    `~/.cache/normpos-grasp/prepared`). `NORMPOS_GRASP_CACHE_DIR=off` turns the disk cache off."""
    env = os.environ.get(CACHE_ENV, "")
    if env.lower() in ("off", "0", "none"):
        return []
    out: list[Path] = []
    if template.source:
        src = Path(template.source)
        folder = src if src.is_dir() else (src.parent if src.is_file() else None)
        if folder is not None:
            out.append(folder / CACHE_FOLDER)
    if env:
        out.append(Path(env))
        return out
    base = os.environ.get("XDG_CACHE_HOME", "")
    if not base:
        try:
            base = str(Path.home() / ".cache")
        except RuntimeError:  # no home directory: the template folder only
            return out
    out.append(Path(base) / "normpos-grasp" / "prepared")
    return out


def _load_or_build(template: Template, key: str) -> dict[str, np.ndarray]:
    dirs = cache_dirs(template)
    name = f"{key[:40]}.npz"
    for folder in dirs:
        path = folder / name
        if not path.is_file():
            continue
        arrays = _load(path, key)
        if arrays is not None:
            logger.debug("template '%s': preparation loaded from %s", template.name, path)
            return arrays
    t0 = time.perf_counter()
    arrays = _compute(template.mesh)
    logger.debug("template '%s' prepared in %.2f s", template.name, time.perf_counter() - t0)
    for folder in dirs:
        if _store(folder / name, key, arrays):
            break
    return arrays


def _store_own(template: Template, key: str, arrays: dict[str, np.ndarray]) -> None:
    """A mesh prepared before in this process (shared by key) is also stored in this template's own folder when
    the file is missing there (the same part taught into a second library in one process)."""
    dirs = cache_dirs(template)
    if template.source and dirs and dirs[0].name == CACHE_FOLDER:
        path = dirs[0] / f"{key[:40]}.npz"
        if not path.is_file():
            _store(path, key, arrays)


def _load(path: Path, key: str) -> dict[str, np.ndarray] | None:
    """The arrays stored at `path` when they are this key's and well-formed (shapes, dtypes, index ranges); None
    (logged) otherwise."""
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {k: data[k] for k in data.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        logger.info("ignoring damaged template preparation %s: %s", path, exc)
        return None
    stored = arrays.pop("key", None)
    if stored is None or stored.shape != () or str(stored) != key:
        logger.info("ignoring template preparation %s: made for another mesh or format", path)
        return None
    problem = _invalid(arrays)
    if problem:
        logger.info("ignoring template preparation %s: %s", path, problem)
        return None
    return arrays


def _store(path: Path, key: str, arrays: dict[str, np.ndarray]) -> bool:
    """Write `arrays` (and `key`) to `path` atomically (temporary file + rename); False when the folder is not
    writable."""
    try:
        fresh = not path.parent.exists()
        path.parent.mkdir(parents=True, exist_ok=True)
        if fresh and path.parent.name == CACHE_FOLDER:  # keep the cache out of version control
            (path.parent / ".gitignore").write_text("*\n")
        with atomic_open(path, "wb") as f:
            payload: dict[str, Any] = {"key": np.array(key), **arrays}
            np.savez_compressed(f, allow_pickle=False, **payload)
    except OSError as exc:
        logger.debug("cannot store the template preparation in %s: %s", path.parent, exc)
        return False
    return True


def _invalid(a: dict[str, np.ndarray]) -> str:
    """'' when the arrays have the names, dtypes and shapes `_compute` gives and their indices are in range;
    otherwise what is wrong."""
    if set(a) != set(_LAYOUT):
        return f"arrays {sorted(set(a) ^ set(_LAYOUT))} missing or unexpected"
    n = a["samples"].shape[0] if a["samples"].ndim == 2 else -1
    g = GRID
    dims = {"S": n, "G": g, "F": a["desc_idx"].shape[0] if a["desc_idx"].ndim == 1 else -1}
    for name, (dtype, shape) in _LAYOUT.items():
        arr = a[name]
        if arr.dtype != np.dtype(dtype):
            return f"{name} has dtype {arr.dtype}, expected {dtype}"
        want = tuple(dims.get(d, d) if isinstance(d, str) else d for d in shape)
        if arr.ndim != len(want) or any(w not in (-1, s) for w, s in zip(want, arr.shape, strict=True)):
            return f"{name} has shape {arr.shape}, expected {want}"
        if arr.dtype.kind == "f" and not np.all(np.isfinite(arr)):
            return f"{name} holds non-finite values"
    if n < 4:
        return "too few samples"
    if a["cand_start"].shape != (g**3 + 1,) or a["cand_start"][-1] != len(a["cand_idx"]):
        return "candidate ranges do not match the candidate list"
    if np.any(np.diff(a["cand_start"]) < 0):
        return "candidate ranges are not increasing"
    ranges = {"cells": -1, "cand_idx": 0, "desc_idx": 0, "kd_perm": 0, "sbins": 0}
    for name, lo in ranges.items():
        arr = a[name]
        hi = 6 if name == "sbins" else n - 1
        if arr.size and (int(arr.min()) < lo or int(arr.max()) > hi):
            return f"{name} indices out of range"
    return ""


#: name -> (dtype, shape) of the stored arrays; 'S' samples, 'F' descriptors, 'G' grid size, -1 any length
_LAYOUT: dict[str, tuple[str, tuple[int | str, ...]]] = {
    "samples": ("float64", ("S", 3)),
    "normals": ("float64", ("S", 3)),
    "centroid": ("float64", (3,)),
    "axes": ("float64", (3, 3)),
    "eigvals": ("float64", (3,)),
    "scalars": ("float64", (5,)),  # diameter, spacing, grid cell, grid pad, voxel (m)
    "grid_origin": ("float64", (3,)),
    "cells": ("int16" if N_SAMPLES < 2**15 else "int32", ("G", "G", "G", 8)),
    "cand_start": ("int64", (-1,)),
    "cand_idx": ("int32", (-1,)),
    "cell_dist": ("float64", (GRID**3,)),
    "sbins": ("int64", ("S",)),
    "desc_idx": ("int64", ("F",)),
    "desc": ("float64", ("F", 33)),
    "kd_dim": ("int64", (-1,)),
    "kd_split": ("float64", (-1,)),
    "kd_left": ("int64", (-1,)),
    "kd_right": ("int64", (-1,)),
    "kd_start": ("int64", (-1,)),
    "kd_end": ("int64", (-1,)),
    "kd_perm": ("int64", (-1,)),
    "kd_roots": ("int64", (7,)),
}
_KD = ("kd_dim", "kd_split", "kd_left", "kd_right", "kd_start", "kd_end", "kd_perm", "kd_roots")


def _build(template: Template) -> PreparedTemplate:
    """A fresh `PreparedTemplate` (no caches)."""
    return _assemble(_compute(template.mesh), template.symmetry.transforms(continuous_steps=12))


def _assemble(a: dict[str, np.ndarray], sym: FloatArray) -> PreparedTemplate:
    """The `PreparedTemplate` of stored arrays `a` (`_compute`) and symmetry transforms `sym` (M, 4, 4): the
    search trees are rebuilt from the samples (milliseconds)."""
    samples, normals, cells = a["samples"], a["normals"], a["cells"]
    diameter, spacing, cell, pad, voxel = (float(x) for x in a["scalars"])
    sbins = a["sbins"]
    bin_trees: list[tuple[cKDTree | None, IntArray]] = []
    for b in range(6):
        members = np.flatnonzero(sbins == b)
        bin_trees.append((cKDTree(samples[members]) if len(members) else None, members))
    desc = a["desc"]
    return PreparedTemplate(
        samples=samples,
        normals=normals,
        tree=cKDTree(samples),
        centroid=a["centroid"],
        axes=a["axes"],
        eigvals=a["eigvals"],
        diameter=diameter,
        spacing=spacing,
        grid_origin=a["grid_origin"],
        grid_cell=cell,
        grid_index=cells[..., 0].astype(np.int32),
        grid_index_bins=np.ascontiguousarray(np.moveaxis(cells[..., 1:7], -1, 0)).astype(np.int32),
        bin_trees=tuple(bin_trees),
        sym=sym,
        desc_idx=a["desc_idx"],
        desc=desc,
        desc_tree=cKDTree(desc),
        voxel=voxel,
        grid=(a["grid_origin"], np.array([cell, pad]), cells, a["cand_start"], a["cand_idx"], a["cell_dist"], sbins),
        kd=tuple(a[k] for k in _KD),
    )


def _compute(mesh: trimesh.Trimesh) -> dict[str, np.ndarray]:
    """The preparation's arrays (see `_LAYOUT`): surface samples, distance grids, descriptors, flat KD-trees;
    about 0.5-1 s on one core."""
    from normpos_grasp.templates.features import fpfh, voxel_downsample
    from normpos_grasp.templates.kernels import build_kdtrees

    rng = np.random.default_rng(_SEED)
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
    centroid = (area[:, None] * np.asarray(mesh.triangles_center)).sum(0) / area.sum()
    eigvals, axes = surface_axes(mesh)
    hull = np.asarray(mesh.convex_hull.vertices, dtype=np.float64)
    if len(hull) > _HULL_POINTS:
        hull = hull[rng.choice(len(hull), _HULL_POINTS, replace=False)]
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
    cells = np.full((GRID, GRID, GRID, 8), -1, dtype=np.int16 if N_SAMPLES < 2**15 else np.int32)
    cells[..., 0] = grid_index
    groups = [np.arange(len(samples))]
    for b in range(6):
        members = np.flatnonzero(sbins == b)
        groups.append(members)
        if len(members):
            _, bi = cKDTree(samples[members]).query(flat)
            cells[..., 1 + b] = members[np.asarray(bi)].reshape(GRID, GRID, GRID)
    kd = build_kdtrees(samples, groups)
    voxel = diameter / _VOXEL_DIV
    keep = voxel_downsample(samples, voxel)
    desc = fpfh(samples[keep], normals[keep], voxel * _FPFH_RADIUS)
    out = {
        "samples": samples,
        "normals": normals,
        "centroid": centroid,
        "axes": axes,
        "eigvals": eigvals,
        "scalars": np.array([diameter, spacing, cell, pad, voxel]),
        "grid_origin": np.asarray(origin, dtype=np.float64),
        "cells": cells,
        "cand_start": cand_start,
        "cand_idx": np.asarray(cand_idx, dtype=np.int32),
        "cell_dist": np.asarray(gdist, dtype=np.float64),
        "sbins": sbins.astype(np.int64),
        "desc_idx": np.asarray(keep, dtype=np.int64),
        "desc": np.asarray(desc, dtype=np.float64),
    }
    out.update({name: np.asarray(arr) for name, arr in zip(_KD, kd, strict=True)})
    return {k: np.ascontiguousarray(v, dtype=_LAYOUT[k][0]) for k, v in out.items()}


def surface_axes(mesh: trimesh.Trimesh) -> tuple[FloatArray, FloatArray]:
    """Eigenvalues (3,) descending (m^2) and principal axes (3, 3) as columns (right-handed) of the surface's
    exact area-weighted second moments about its area centroid.

    Exact, not from random samples: a mirror-symmetric part (a T-profile, a bracket) whose two moments are close
    got axes turned by 10-15 degrees from sampled moments, which turned the PCA hypotheses and the flip variants
    away from its faces; exact moments keep a symmetric part's axes on its symmetry planes."""
    tri = np.asarray(mesh.triangles, dtype=np.float64)
    area = np.asarray(mesh.area_faces, dtype=np.float64)
    total = float(area.sum())
    corner_sum = tri.sum(axis=1)
    # integral of x x^T over a triangle: area / 12 * (sum of v v^T over its corners + s s^T), s the corner sum
    second = (np.einsum("f,fki,fkj->ij", area, tri, tri) + np.einsum("f,fi,fj->ij", area, corner_sum, corner_sum)) / (
        12.0 * total
    )
    centre = (area[:, None] * corner_sum).sum(axis=0) / (3.0 * total)
    eigvals, axes = np.linalg.eigh(second - np.outer(centre, centre))
    order = np.argsort(eigvals)[::-1]
    axes = np.ascontiguousarray(axes[:, order])
    if np.linalg.det(axes) < 0:
        axes[:, 2] *= -1
    return eigvals[order], axes


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
