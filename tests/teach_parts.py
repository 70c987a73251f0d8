"""Parts the project does not ship, built with trimesh for the teach tests and benchmarks (millimetres).

A flanged bushing (revolved profile), a T-profile and a thin bracket (extruded profiles) and a hex nut (hexagonal
prism with a round hole); `asymmetric_block` has no symmetry at all. Each is a closed, outward-oriented solid.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import trimesh


def _extrude(profile: list[tuple[float, float]], triangles: list[tuple[int, int, int]], length: float) -> Any:
    """Extrude a simple polygon (y, z) with its triangulation along x over `length` (centred)."""
    p = np.asarray(profile, dtype=np.float64)
    k = len(p)
    verts = np.vstack([np.column_stack([np.full(k, -length / 2), p]), np.column_stack([np.full(k, length / 2), p])])
    faces = [(a, c, b) for a, b, c in triangles] + [(a + k, b + k, c + k) for a, b, c in triangles]
    for i in range(k):
        j = (i + 1) % k
        faces += [(i, j, j + k), (i, j + k, i + k)]
    mesh = trimesh.Trimesh(verts, np.asarray(faces), process=True)
    mesh.fix_normals()
    return mesh


def t_profile() -> trimesh.Trimesh:
    """T-profile 60 long: flange 30 x 5, web 6 thick, 25 high."""
    prof = [(-15, 0), (15, 0), (15, 5), (3, 5), (3, 25), (-3, 25), (-3, 5), (-15, 5)]
    tris = [(0, 1, 2), (0, 2, 3), (0, 3, 6), (0, 6, 7), (6, 3, 4), (6, 4, 5)]
    return _extrude(prof, tris, 60.0)


def thin_bracket() -> trimesh.Trimesh:
    """L bracket 30 wide: legs 50 and 25, 3 thick."""
    prof = [(0, 0), (50, 0), (50, 3), (3, 3), (3, 25), (0, 25)]
    tris = [(0, 1, 2), (0, 2, 3), (0, 3, 4), (0, 4, 5)]
    return _extrude(prof, tris, 30.0)


def flanged_bushing() -> trimesh.Trimesh:
    """Bushing: bore 12, body 20 across and 20 long, flange 32 across and 4 thick."""
    profile = np.array([[6, -10], [16, -10], [16, -6], [10, -6], [10, 10], [6, 10], [6, -10]], dtype=np.float64)
    mesh = trimesh.creation.revolve(profile, sections=48)
    mesh.merge_vertices()
    mesh.fix_normals()
    return mesh


def hex_nut() -> trimesh.Trimesh:
    """Hex nut: 24 across corners, 10 thick, round bore 12 (36 points around both)."""
    n = 36
    ang = np.linspace(0, 2 * np.pi, n, endpoint=False)
    # a regular hexagon in polar form (corner radius 12): r = R cos(30 deg) / cos(angle to the nearest side normal)
    side = (ang + np.pi / 6) % (np.pi / 3) - np.pi / 6
    r_out = 12.0 * np.cos(np.pi / 6) / np.cos(side)
    outer = np.column_stack([r_out * np.cos(ang), r_out * np.sin(ang)])
    inner = np.column_stack([6.0 * np.cos(ang), 6.0 * np.sin(ang)])
    verts, faces = [], []
    for z in (-5.0, 5.0):
        verts += [(x, y, z) for x, y in outer] + [(x, y, z) for x, y in inner]
    o0, i0, o1, i1 = 0, n, 2 * n, 3 * n
    for a in range(n):
        b = (a + 1) % n
        faces += [(o1 + a, o1 + b, i1 + b), (o1 + a, i1 + b, i1 + a)]  # top ring
        faces += [(o0 + a, i0 + b, o0 + b), (o0 + a, i0 + a, i0 + b)]  # bottom ring
        faces += [(o0 + a, o0 + b, o1 + b), (o0 + a, o1 + b, o1 + a)]  # outer wall
        faces += [(i0 + a, i1 + b, i0 + b), (i0 + a, i1 + a, i1 + b)]  # bore
    mesh = trimesh.Trimesh(np.asarray(verts), np.asarray(faces), process=True)
    mesh.fix_normals()
    return mesh


def asymmetric_block() -> trimesh.Trimesh:
    """A 40 long prism whose 30 x 20 profile has a slanted corner and a step: no rotation symmetry."""
    prof = [(0, 0), (30, 0), (30, 12), (22, 20), (8, 20), (8, 14), (0, 14)]
    tris = [(0, 1, 2), (0, 2, 3), (0, 3, 4), (0, 4, 5), (0, 5, 6)]
    return _extrude(prof, tris, 40.0)


PARTS = {
    "flanged_bushing": flanged_bushing,
    "t_profile": t_profile,
    "hex_nut": hex_nut,
    "thin_bracket": thin_bracket,
}


def write_part(name: str, folder: Path, units: str = "mm") -> Path:
    """Write part `name` as an STL in `units` ('mm' as built, 'm' scaled) into `folder`; returns the file."""
    mesh = PARTS.get(name, asymmetric_block)()
    if units == "m":
        mesh.apply_scale(1e-3)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{name}.stl"
    mesh.export(str(path))
    return path
