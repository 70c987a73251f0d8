"""Default part library: procedural, watertight CAD parts (metres) for synthetic cells and demos.

Every part is built by code (no files), centred at its centroid with its axes along its principal
directions, and carries its shape class, symmetries, named control points and a mass from a density.
All parts fit an 85 mm parallel gripper across at least one dimension.
"""

from __future__ import annotations

import itertools
import logging
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from normpos_grasp.errors import MeshError
from normpos_grasp.geometry.transforms import make_pose
from normpos_grasp.records.template import Symmetry, Template
from normpos_grasp.typing import FloatArray

if TYPE_CHECKING:
    import trimesh

logger = logging.getLogger(__name__)

#: Material densities, kg/m^3.
DENSITIES: dict[str, float] = {"pom": 1410.0, "aluminium": 2700.0, "abs": 1050.0, "steel": 7850.0}

#: Display colours (RGBA in [0, 1]) per part name; used by the renderer.
PART_COLORS: dict[str, tuple[float, float, float, float]] = {
    "cube": (0.85, 0.25, 0.2, 1.0),
    "box": (0.2, 0.55, 0.85, 1.0),
    "bar": (0.9, 0.75, 0.15, 1.0),
    "cylinder": (0.25, 0.7, 0.3, 1.0),
    "sphere": (0.8, 0.4, 0.75, 1.0),
    "plate": (0.7, 0.72, 0.75, 1.0),
    "bracket": (0.95, 0.5, 0.1, 1.0),
    "ring": (0.35, 0.35, 0.8, 1.0),
}


# -- mesh builders ---------------------------------------------------------------------------
def _finish(mesh: trimesh.Trimesh, name: str) -> trimesh.Trimesh:
    """Merge vertices, orient faces outward and check the mesh is a closed, positive-volume solid."""
    mesh.merge_vertices()
    mesh.remove_unreferenced_vertices()
    mesh.fix_normals()
    if not mesh.is_watertight or not mesh.is_winding_consistent or mesh.volume <= 0:
        raise MeshError(
            f"procedural part {name!r} is not a closed outward-oriented solid "
            f"(watertight={mesh.is_watertight}, volume={mesh.volume:.3g} m^3)"
        )
    return mesh


def _box_mesh(extents: FloatArray) -> trimesh.Trimesh:
    import trimesh

    return trimesh.creation.box(extents=np.asarray(extents, dtype=np.float64))


def _prism_mesh(profile: FloatArray, triangles: list[tuple[int, int, int]], length: float) -> trimesh.Trimesh:
    """Extrude a simple polygon `profile` (K, 2) in the (y, z) plane along x over `length` (centred)."""
    import trimesh

    k = len(profile)
    lo = np.column_stack([np.full(k, -length / 2), profile])
    hi = np.column_stack([np.full(k, length / 2), profile])
    vertices = np.vstack([lo, hi])
    faces: list[tuple[int, int, int]] = []
    for a, b, c in triangles:
        faces.append((a, c, b))  # cap at -x
        faces.append((a + k, b + k, c + k))  # cap at +x
    for i in range(k):
        j = (i + 1) % k
        faces.append((i, j, j + k))
        faces.append((i, j + k, i + k))
    return trimesh.Trimesh(vertices=vertices, faces=np.asarray(faces), process=True)


# -- symmetry helpers ------------------------------------------------------------------------
def _proper_cube_rotations() -> list[FloatArray]:
    """The 24 signed permutation matrices with det +1 (rotation group of the cube)."""
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            r = np.zeros((3, 3))
            for row, (col, s) in enumerate(zip(perm, signs, strict=True)):
                r[row, col] = s
            if np.linalg.det(r) > 0:
                out.append(r)
    return out


def box_symmetry(extents: FloatArray, tol: float = 1e-9) -> Symmetry:
    """Discrete symmetries of a box with (3,) `extents` centred at the origin (identity excluded)."""
    e = np.asarray(extents, dtype=np.float64)
    discrete = []
    for r in _proper_cube_rotations():
        if np.allclose(r, np.eye(3)):
            continue
        if np.allclose(np.abs(r) @ e, e, atol=tol):
            discrete.append(make_pose(r))
    return Symmetry(discrete=tuple(discrete))


def _flip_about(axis: FloatArray) -> FloatArray:
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    return make_pose(2.0 * np.outer(a, a) - np.eye(3))


def _axis_symmetry(axis: FloatArray, flip_axis: FloatArray) -> Symmetry:
    """Continuous rotation about `axis` through the origin plus a half-turn flip about `flip_axis`."""
    return Symmetry(
        continuous=((np.asarray(axis, dtype=np.float64), np.zeros(3)),),
        discrete=(_flip_about(flip_axis),),
    )


# -- part constructors -----------------------------------------------------------------------
def _box_part(name: str, extents_m: tuple[float, float, float], material: str, shape: str) -> Template:
    e = np.asarray(extents_m, dtype=np.float64)
    mesh = _finish(_box_mesh(e), name)
    half = e / 2
    points: dict[str, FloatArray] = {}
    for sx, sy, sz in itertools.product((-1, 1), repeat=3):
        key = "corner_" + "".join("p" if s > 0 else "m" for s in (sx, sy, sz))
        points[key] = np.array([sx, sy, sz]) * half
    for i, axis in enumerate("xyz"):
        for s, tag in ((1, "p"), (-1, "m")):
            c = np.zeros(3)
            c[i] = s * half[i]
            points[f"face_{tag}{axis}"] = c
    points["centre"] = np.zeros(3)
    return _template(name, mesh, points, box_symmetry(e), shape, material)


def _cylinder_part(name: str, diameter_m: float, height_m: float, material: str) -> Template:
    import trimesh

    r, h = diameter_m / 2, height_m
    mesh = _finish(trimesh.creation.cylinder(radius=r, height=h, sections=64), name)
    points = {
        "cap_top": np.array([0.0, 0.0, h / 2]),
        "cap_bottom": np.array([0.0, 0.0, -h / 2]),
        "rim_top_px": np.array([r, 0.0, h / 2]),
        "rim_bottom_px": np.array([r, 0.0, -h / 2]),
        "centre": np.zeros(3),
    }
    return _template(
        name, mesh, points, _axis_symmetry(np.array([0, 0, 1.0]), np.array([1.0, 0, 0])), "cylinder", material
    )


def _sphere_part(name: str, diameter_m: float, material: str) -> Template:
    import trimesh

    r = diameter_m / 2
    mesh = _finish(trimesh.creation.icosphere(subdivisions=4, radius=r), name)
    points = {
        "centre": np.zeros(3),
        "pole_top": np.array([0.0, 0.0, r]),
        "pole_bottom": np.array([0.0, 0.0, -r]),
    }
    sym = Symmetry(continuous=tuple((np.eye(3)[i], np.zeros(3)) for i in range(3)))
    return _template(name, mesh, points, sym, "sphere", material)


def _ring_part(name: str, outer_d_m: float, inner_d_m: float, height_m: float, material: str) -> Template:
    import trimesh

    ro, ri, h = outer_d_m / 2, inner_d_m / 2, height_m
    mesh = _finish(trimesh.creation.annulus(r_min=ri, r_max=ro, height=h, sections=64), name)
    points = {
        "hole_top": np.array([0.0, 0.0, h / 2]),
        "hole_bottom": np.array([0.0, 0.0, -h / 2]),
        "rim_outer_px": np.array([ro, 0.0, h / 2]),
        "rim_inner_px": np.array([ri, 0.0, h / 2]),
        "centre": np.zeros(3),
    }
    return _template(name, mesh, points, _axis_symmetry(np.array([0, 0, 1.0]), np.array([1.0, 0, 0])), "ring", material)


def _bracket_part(name: str, length_m: float, leg_m: float, thickness_m: float, material: str) -> Template:
    a, t = leg_m, thickness_m
    profile = np.array([[0, 0], [a, 0], [a, t], [t, t], [t, a], [0, a]], dtype=np.float64)
    tris = [(0, 1, 2), (0, 2, 3), (0, 3, 4), (0, 4, 5)]
    raw = _prism_mesh(profile, tris, length_m)
    raw = _finish(raw, name)
    centroid = np.asarray(raw.center_mass, dtype=np.float64)
    # principal frame by construction: x along the extrusion, z along the L's bisector (towards the heel),
    # y across it; for equal legs these are the principal axes, and the half-turn about z is a symmetry.
    z = np.array([0.0, -1.0, -1.0]) / np.sqrt(2.0)
    x = np.array([1.0, 0.0, 0.0])
    y = np.cross(z, x)
    object_from_raw = np.linalg.inv(make_pose(np.column_stack([x, y, z]), centroid))
    mesh = raw.copy()
    mesh.apply_transform(object_from_raw)
    mesh = _finish(mesh, name)
    corner_names = ["heel", "toe_y", "toe_y_in", "inner", "toe_z_in", "toe_z"]
    points: dict[str, FloatArray] = {}
    for end, xs in (("m", -length_m / 2), ("p", length_m / 2)):
        for cname, (py, pz) in zip(corner_names, profile, strict=True):
            p = np.array([xs, py, pz, 1.0])
            points[f"{cname}_{end}x"] = (object_from_raw @ p)[:3]
    points["centre"] = np.zeros(3)
    sym = Symmetry(discrete=(_flip_about(np.array([0.0, 0.0, 1.0])),))
    return _template(name, mesh, points, sym, "bracket", material)


def _template(
    name: str, mesh: trimesh.Trimesh, points: dict[str, FloatArray], symmetry: Symmetry, shape: str, material: str
) -> Template:
    density = DENSITIES[material]
    return Template(
        name=name,
        label=name,
        mesh=mesh,
        control_points={k: np.asarray(v, dtype=np.float64) for k, v in points.items()},
        symmetry=symmetry,
        shape=shape,
        mass_kg=float(mesh.volume * density),
        material=material,
        source="normpos_grasp.sim.parts (procedural)",
    )


#: BOP obj_id of each built-in part (fixed: synth, estimate and every dataset use these)
BUILTIN_OBJ_IDS: dict[str, int] = {
    name: i + 1 for i, name in enumerate(("cube", "box", "bar", "cylinder", "sphere", "plate", "bracket", "ring"))
}


def default_part_library() -> list[Template]:
    """The eight default parts (metres): cube, box, bar, cylinder, sphere, plate, bracket, ring (obj_id 1..8).

    Sizes: cube 40 mm; box 60x40x30; bar 100x25x25; cylinder d40 h70; sphere d45; plate 80x60x8;
    bracket L-profile 60 long, legs 40x40, 8 thick; ring OD 60, ID 36, h 15.
    """
    parts = [
        _box_part("cube", (0.04, 0.04, 0.04), "pom", "box"),
        _box_part("box", (0.06, 0.04, 0.03), "abs", "box"),
        _box_part("bar", (0.10, 0.025, 0.025), "aluminium", "box"),
        _cylinder_part("cylinder", 0.04, 0.07, "pom"),
        _sphere_part("sphere", 0.045, "pom"),
        _box_part("plate", (0.08, 0.06, 0.008), "aluminium", "plate"),
        _bracket_part("bracket", 0.06, 0.04, 0.008, "aluminium"),
        _ring_part("ring", 0.06, 0.036, 0.015, "aluminium"),
    ]
    # stable BOP object ids: a part keeps its id in every dataset, whichever parts a run draws
    return [replace(t, obj_id=BUILTIN_OBJ_IDS[t.name]) for t in parts]


def part_library_by_name(library: list[Template] | None = None) -> dict[str, Template]:
    """name -> Template for `library` (default: `default_part_library()`)."""
    parts = default_part_library() if library is None else library
    return {t.name: t for t in parts}
