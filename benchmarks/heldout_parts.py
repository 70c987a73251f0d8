"""Held-out test parts the project does not ship (nuts, thin plates, brackets, profiles, short cylinders), metres.

Built here with trimesh from polygons (own ear clipping, no shapely); symmetries written out as the discrete groups
(or the continuous axis) each shape has. Used by benchmarks/bench_cad.py and the cad detector tests.
"""

from __future__ import annotations

import numpy as np
import trimesh

from normpos_grasp.records.template import Symmetry, Template
from normpos_grasp.sim.parts import box_symmetry


def _rot(axis: str, deg: float) -> np.ndarray:
    a = np.deg2rad(deg)
    c, s = np.cos(a), np.sin(a)
    m = np.eye(4)
    i, j = {"x": (1, 2), "y": (2, 0), "z": (0, 1)}[axis]
    m[i, i], m[i, j], m[j, i], m[j, j] = c, -s, s, c
    return m


def _earclip(poly: np.ndarray) -> list[tuple[int, int, int]]:
    """Triangles of a simple counter-clockwise polygon (K, 2) by ear clipping."""
    idx = list(range(len(poly)))
    tris: list[tuple[int, int, int]] = []

    def cross(o: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
        return float((a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0]))

    while len(idx) > 3:
        for k in range(len(idx)):
            i0, i1, i2 = idx[k - 1], idx[k], idx[(k + 1) % len(idx)]
            a, b, c = poly[i0], poly[i1], poly[i2]
            if cross(a, b, c) <= 1e-12:
                continue
            inside = False
            for j in idx:
                if j in (i0, i1, i2):
                    continue
                p = poly[j]
                if cross(a, b, p) >= 0 and cross(b, c, p) >= 0 and cross(c, a, p) >= 0:
                    inside = True
                    break
            if not inside:
                tris.append((i0, i1, i2))
                idx.pop(k)
                break
        else:
            raise ValueError("polygon is not simple or not counter-clockwise")
    tris.append((idx[0], idx[1], idx[2]))
    return tris


def _extrude(poly: np.ndarray, length: float) -> trimesh.Trimesh:
    """Prism of the counter-clockwise polygon (K, 2) in the (x, y) plane over z in [-length/2, length/2]."""
    k = len(poly)
    tris = _earclip(poly)
    v = np.vstack([np.column_stack([poly, np.full(k, -length / 2)]), np.column_stack([poly, np.full(k, length / 2)])])
    faces = [(a, c, b) for a, b, c in tris] + [(a + k, b + k, c + k) for a, b, c in tris]
    for i in range(k):
        j = (i + 1) % k
        faces += [(i, j, j + k), (i, j + k, i + k)]
    return _closed(trimesh.Trimesh(v, np.asarray(faces), process=True))


def _ring_prism(outer: np.ndarray, inner: np.ndarray, length: float) -> trimesh.Trimesh:
    """Prism between two counter-clockwise loops with the same point count (a nut: hexagon around a hole)."""
    n = len(outer)
    lo, hi = -length / 2, length / 2
    v = np.vstack(
        [
            np.column_stack([outer, np.full(n, lo)]),
            np.column_stack([outer, np.full(n, hi)]),
            np.column_stack([inner, np.full(n, lo)]),
            np.column_stack([inner, np.full(n, hi)]),
        ]
    )
    o0, o1, i0, i1 = 0, n, 2 * n, 3 * n
    faces = []
    for a in range(n):
        b = (a + 1) % n
        faces += [(o0 + a, o0 + b, o1 + b), (o0 + a, o1 + b, o1 + a)]  # outer wall
        faces += [(i0 + a, i1 + b, i0 + b), (i0 + a, i1 + a, i1 + b)]  # hole wall
        faces += [(o1 + a, o1 + b, i1 + b), (o1 + a, i1 + b, i1 + a)]  # top
        faces += [(o0 + a, i0 + b, o0 + b), (o0 + a, i0 + a, i0 + b)]  # bottom
    return _closed(trimesh.Trimesh(v, np.asarray(faces), process=True))


def _closed(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    mesh.merge_vertices()
    mesh.fix_normals()
    if not mesh.is_watertight or mesh.volume <= 0:
        raise ValueError("held-out part mesh is not a closed solid")
    return mesh


def _template(name: str, mesh: trimesh.Trimesh, sym: Symmetry, shape: str) -> Template:
    return Template(
        name=name,
        label=name,
        mesh=mesh,
        control_points={},
        symmetry=sym,
        shape=shape,
        mass_kg=float(mesh.volume * 2700.0),
        material="aluminium",
        source="benchmarks/heldout_parts.py (held out)",
    )


def _hexagon(across_flats: float, per_side: int) -> np.ndarray:
    r = across_flats / np.sqrt(3.0)
    corners = np.array([[r * np.cos(np.pi / 3 * k), r * np.sin(np.pi / 3 * k)] for k in range(6)])
    pts = []
    for k in range(6):
        a, b = corners[k], corners[(k + 1) % 6]
        for s in range(per_side):
            pts.append(a + (b - a) * s / per_side)
    return np.array(pts)


def _dihedral(n: int) -> Symmetry:
    """Rotations by 360/n about z and half turns about the n in-plane axes 180/n apart (a prism of an n-gon),
    identity excluded. Rz(a) Rx(pi) is the half turn about the in-plane axis at a / 2: a runs over 360 k / n (before
    this fix it ran over 180 k / n, so for the hexagon three half turns were none of the prism's and three were
    missing: the fit then called a true flip of a nut a rival 13 mm away and rejected the nut as ambiguous)."""
    out = [_rot("z", 360.0 * k / n) for k in range(1, n)]
    out += [_rot("z", 360.0 * k / n) @ _rot("x", 180.0) for k in range(n)]
    return Symmetry(discrete=tuple(out))


def heldout_library() -> list[Template]:
    """The eight held-out parts: hex nut, square plate, strip plate, U channel, I profile, puck, hex standoff,
    unequal L angle."""
    nut_outer = _hexagon(0.024, 4)
    ang = np.arctan2(nut_outer[:, 1], nut_outer[:, 0])
    nut_inner = 0.0065 * np.column_stack([np.cos(ang), np.sin(ang)])
    nut = _template("nut_m12", _ring_prism(nut_outer, nut_inner, 0.011), _dihedral(6), "ring")
    sq = _template(
        "plate_sq50", trimesh.creation.box(extents=(0.05, 0.05, 0.003)), box_symmetry(np.array([0.05, 0.05, 0.003])),
        "plate",
    )
    strip = _template(
        "plate_strip", trimesh.creation.box(extents=(0.07, 0.03, 0.004)), box_symmetry(np.array([0.07, 0.03, 0.004])),
        "plate",
    )
    w, hh, t = 0.04, 0.025, 0.004
    u = np.array([[-w / 2, 0], [w / 2, 0], [w / 2, hh], [w / 2 - t, hh], [w / 2 - t, t], [-w / 2 + t, t],
                  [-w / 2 + t, hh], [-w / 2, hh]]) - [0, hh / 2]  # fmt: skip
    channel = _template("u_channel", _extrude(u, 0.05), Symmetry(discrete=(_rot("y", 180.0),)), "bracket")
    b, hi, tf, tw = 0.03, 0.03, 0.004, 0.004
    ip = np.array([[-b / 2, -hi / 2], [b / 2, -hi / 2], [b / 2, -hi / 2 + tf], [tw / 2, -hi / 2 + tf],
                   [tw / 2, hi / 2 - tf], [b / 2, hi / 2 - tf], [b / 2, hi / 2], [-b / 2, hi / 2],
                   [-b / 2, hi / 2 - tf], [-tw / 2, hi / 2 - tf], [-tw / 2, -hi / 2 + tf],
                   [-b / 2, -hi / 2 + tf]])  # fmt: skip
    profile = _template(
        "i_profile", _extrude(ip, 0.08), Symmetry(discrete=(_rot("x", 180.0), _rot("y", 180.0), _rot("z", 180.0))),
        "bracket",
    )
    puck = _template(
        "puck",
        trimesh.creation.cylinder(radius=0.018, height=0.01, sections=64),
        Symmetry(continuous=((np.array([0.0, 0.0, 1.0]), np.zeros(3)),), discrete=(_rot("x", 180.0),)),
        "cylinder",
    )
    standoff = _template("hex_standoff", _extrude(_hexagon(0.014, 1), 0.05), _dihedral(6), "cylinder")
    la, lb, tt = 0.05, 0.03, 0.004
    lp = np.array([[0, 0], [la, 0], [la, tt], [tt, tt], [tt, lb], [0, lb]]) - [la / 3, lb / 3]
    angle = _template("l_angle", _extrude(lp, 0.025), Symmetry(), "bracket")
    return [nut, sq, strip, channel, profile, puck, standoff, angle]
