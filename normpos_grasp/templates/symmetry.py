"""Symmetries of a part found from its geometry, in the BOP convention (continuous axes + discrete transforms).

Method: the mesh is centred at its centre of mass (every proper symmetry fixes it). Candidate rotation axes
through the centre are the principal axes of inertia, the normals of the large flat facets, and the directions to
the vertices, edge midpoints and face centres (deduplicated up to sign). A rotation R is a symmetry when the
surface maps onto itself: every one of `n_probe` surface samples, rotated, lies within `tol` of the surface (the
distance is measured to the exact surface with the project's nearest-point kernel), and the same holds for the
inverse. An axis is continuous when rotations by several unrelated angles all pass; otherwise its order is the
largest n in `orders` whose 2 pi / n rotation passes. The discrete set is the group the found rotations generate
(identity excluded); for a part with one continuous axis only one half-turn flip perpendicular to it is kept,
and a part with three continuous axes (a sphere) keeps those three (what `Symmetry.transforms` expects).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from normpos_grasp.errors import TemplateError
from normpos_grasp.geometry.transforms import make_pose, rotation_from_rotvec
from normpos_grasp.records.template import Symmetry
from normpos_grasp.templates.library import group_closure
from normpos_grasp.typing import FloatArray

if TYPE_CHECKING:
    import trimesh

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class SymmetryOptions:
    """Settings of `detect_symmetry`.

    tol_rel: a rotated surface sample must lie within tol_rel x diameter (and at least `tol_min_m`) of the surface.
    tol_min_m: floor of the tolerance, metres. n_probe: surface samples tested per rotation.
    orders: discrete orders tried per axis, largest first. continuous_angles_deg: the angles an axis must pass to
    count as continuous. max_candidates: most candidate axes tested. seed: sampling seed.
    """

    tol_rel: float = 0.004
    tol_min_m: float = 2e-4
    n_probe: int = 400
    orders: tuple[int, ...] = (12, 8, 6, 5, 4, 3, 2)
    continuous_angles_deg: tuple[float, ...] = (23.0, 71.0, 137.0)
    max_candidates: int = 400
    seed: int = 0


@dataclass(frozen=True, eq=False)
class SymmetryReport:
    """What `detect_symmetry` found.

    symmetry: the BOP-style symmetry (object frame, through `centre`). axes: (axis (3,), order) per symmetry
    axis found, order 0 for continuous. centre: (3,) the centre of mass the axes pass through, metres.
    tol_m: the surface tolerance used. summary: one line for people ('continuous about z, 2-fold flip ...').
    """

    symmetry: Symmetry
    axes: tuple[tuple[FloatArray, int], ...]
    centre: FloatArray
    tol_m: float
    summary: str


def _unique_dirs(dirs: FloatArray, cos_tol: float = np.cos(np.deg2rad(1.0))) -> list[FloatArray]:
    """Unit directions of `dirs` (K, 3), first of each bundle within 1 degree (up to sign) kept, order kept."""
    d = np.asarray(dirs, dtype=np.float64)
    n = np.linalg.norm(d, axis=1)
    d = d[n > 1e-9] / n[n > 1e-9, None]
    out: list[FloatArray] = []
    kept = np.zeros((0, 3))
    for v in d:
        if len(kept) and np.max(np.abs(kept @ v)) > cos_tol:
            continue
        out.append(v)
        kept = np.vstack([kept, v])
    return out


def _candidates(mesh: trimesh.Trimesh, centre: FloatArray, limit: int) -> list[FloatArray]:
    """Candidate axes (unit vectors), the likeliest first: principal axes, large facet normals, then directions."""
    v = np.asarray(mesh.vertices, dtype=np.float64) - centre
    inertia = np.asarray(mesh.moment_inertia, dtype=np.float64)
    _, vecs = np.linalg.eigh(inertia)
    dirs = [vecs[:, i] for i in range(3)]
    try:
        facets = list(mesh.facets)
        areas = np.asarray(mesh.facets_area, dtype=np.float64)
        normals = np.asarray(mesh.facets_normal, dtype=np.float64)
        order = np.argsort(-areas)[:40]
        dirs.extend(normals[i] for i in order if len(facets))
    except (AttributeError, IndexError, ValueError):  # trimesh without facet data for this mesh
        pass
    dirs.extend(np.asarray(mesh.face_normals, dtype=np.float64)[: min(len(mesh.faces), 200)])
    edges = np.asarray(mesh.edges_unique, dtype=np.int64)
    mids = (v[edges[:, 0]] + v[edges[:, 1]]) / 2.0
    tri_centres = np.asarray(mesh.triangles_center, dtype=np.float64) - centre
    rng = np.random.default_rng(0)
    for pts in (v, mids, tri_centres):
        if len(pts) > 300:
            pts = pts[rng.choice(len(pts), 300, replace=False)]
        dirs.extend(pts)
    # directions perpendicular to each principal axis through the others' plane (flips of prisms)
    return _unique_dirs(np.asarray(dirs))[:limit]


class _Surface:
    """Exact point-to-surface distances of one mesh (trimesh's nearest-point query on a triangle tree)."""

    def __init__(self, mesh: trimesh.Trimesh) -> None:
        from trimesh.proximity import ProximityQuery

        self.mesh = mesh
        self.query = ProximityQuery(mesh)

    def max_distance(self, points: FloatArray) -> float:
        _, dist, _ = self.query.on_surface(points)
        return float(np.max(dist))


def sample_surface(mesh: trimesh.Trimesh, n: int, rng: np.random.Generator) -> FloatArray:
    """(n, 3) area-weighted surface samples drawn with `rng` (not the global RNG)."""
    tris = np.asarray(mesh.triangles, dtype=np.float64)
    areas = np.asarray(mesh.area_faces, dtype=np.float64)
    idx = rng.choice(len(areas), size=n, p=areas / areas.sum())
    uv = rng.random((n, 2))
    flip = uv.sum(axis=1) > 1
    uv[flip] = 1 - uv[flip]
    t = tris[idx]
    return t[:, 0] + uv[:, :1] * (t[:, 1] - t[:, 0]) + uv[:, 1:] * (t[:, 2] - t[:, 0])


def _rotation(axis: FloatArray, angle: float) -> FloatArray:
    return rotation_from_rotvec(np.asarray(axis, dtype=np.float64) * angle)


def detect_symmetry(mesh: trimesh.Trimesh, options: SymmetryOptions | None = None) -> SymmetryReport:
    """Symmetries of the closed `mesh` (metres, any frame): see the module docstring.

    Raises:
        TemplateError: the mesh has no volume (open or degenerate), so it has no centre of mass.
    """
    opts = options or SymmetryOptions()
    if not mesh.is_watertight or float(mesh.volume) <= 0:
        raise TemplateError("symmetry detection needs a closed, outward-oriented mesh (positive volume)")
    centre = np.asarray(mesh.center_mass, dtype=np.float64)
    local = mesh.copy()
    local.apply_translation(-centre)
    diameter = float(np.linalg.norm(local.extents))
    tol = max(opts.tol_rel * diameter, opts.tol_min_m)
    rng = np.random.default_rng(opts.seed)
    probe = sample_surface(local, opts.n_probe, rng)
    probe = np.vstack([probe, np.asarray(local.vertices, dtype=np.float64)[: opts.n_probe]])
    surface = _Surface(local)
    # a cheap pre-test: nearest dense surface samples (KD-tree), loose by a few sample spacings, before the exact one
    from scipy.spatial import cKDTree

    dense = sample_surface(local, 20000, rng)
    tree = cKDTree(dense)
    spacing = float(np.sqrt(float(local.area) / len(dense)))
    quick = probe[:: max(1, len(probe) // 24)]
    coarse = probe[:: max(1, len(probe) // 150)]

    def maps_onto(rot: FloatArray) -> bool:
        bound = tol + 3.0 * spacing
        for pts in (quick, coarse):
            for r in (rot, rot.T):
                if not np.all(np.isfinite(tree.query(pts @ r.T, distance_upper_bound=bound)[0])):
                    return False
        return surface.max_distance(probe @ rot.T) <= tol and surface.max_distance(probe @ rot) <= tol

    found: list[tuple[FloatArray, int]] = []
    for axis in _candidates(local, np.zeros(3), opts.max_candidates):
        if any(abs(float(axis @ a)) > np.cos(np.deg2rad(1.0)) for a, _ in found):
            continue
        continuous = [a for a, n in found if n == 0]
        if len(continuous) >= 2:  # every rotation is a symmetry (a sphere): nothing more to learn
            break
        flipped = continuous and any(abs(float(a @ continuous[0])) < 1e-3 for a, n in found if n)
        if flipped and abs(float(axis @ continuous[0])) < 0.999:
            continue  # a continuous axis and a flip across it: every other flip is a product of the two
        if all(maps_onto(_rotation(axis, np.deg2rad(a))) for a in opts.continuous_angles_deg):
            found.append((axis, 0))
            continue
        for n in opts.orders:
            if maps_onto(_rotation(axis, 2 * np.pi / n)):
                found.append((axis, n))
                break
    symmetry = _as_symmetry(found)
    report = SymmetryReport(symmetry, tuple(found), centre, tol, _summary(found))
    logger.info("symmetry: %s (tolerance %.2g m)", report.summary, tol)
    return report


def _as_symmetry(found: list[tuple[FloatArray, int]]) -> Symmetry:
    """BOP-style Symmetry (axes through the origin) of the found axes."""
    continuous = [a for a, n in found if n == 0]
    if len(continuous) >= 2:  # every rotation: a sphere (three axes, as the built-in sphere)
        return Symmetry(continuous=tuple((np.eye(3)[i], np.zeros(3)) for i in range(3)))
    if continuous:
        c = continuous[0]
        flips = [a for a, n in found if n != 0 and n % 2 == 0 and abs(float(a @ c)) < 1e-3]
        disc = (make_pose(2.0 * np.outer(flips[0], flips[0]) - np.eye(3)),) if flips else ()
        return Symmetry(continuous=((c, np.zeros(3)),), discrete=disc)
    gens = [make_pose(_rotation(a, 2 * np.pi / n)) for a, n in found]
    group = group_closure(gens, "the detected symmetries")
    return Symmetry(discrete=tuple(np.round(g, 12) for g in group))


def _axis_name(a: FloatArray) -> str:
    for i, name in enumerate("xyz"):
        if abs(abs(float(a[i])) - 1.0) < 1e-6:
            return name
    return "[" + ", ".join(f"{x:.3f}" for x in a) + "]"


def _summary(found: list[tuple[FloatArray, int]]) -> str:
    """'continuous about z; 2-fold about x' style, with axes of one order off the frame axes counted."""
    if not found:
        return "none (asymmetric)"
    parts = []
    for n in sorted({k for _, k in found}, key=lambda k: (k != 0, -k)):
        axes = [a for a, k in found if k == n]
        kind = "continuous" if n == 0 else f"{n}-fold"
        named = [_axis_name(a) for a in axes if len(_axis_name(a)) == 1]
        others = len(axes) - len(named)
        where = ", ".join(named + ([f"{others} other axes" if others > 1 else "1 other axis"] if others else []))
        parts.append(f"{kind} about {where}")
    return "; ".join(parts)


def group_size(symmetry: Symmetry) -> int:
    """Number of discrete symmetry transforms including the identity (0 marks a continuous symmetry)."""
    return 0 if symmetry.continuous else len(symmetry.discrete) + 1
