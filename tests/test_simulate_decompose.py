"""Convex decomposition for physics and the suction seal check."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

from normpos_grasp.errors import MeshError
from normpos_grasp.geometry.transforms import make_pose, rotation_from_rotvec
from normpos_grasp.sim.physics_decompose import DecompositionOptions, convex_decomposition
from normpos_grasp.sim.physics_suction import SealOptions, check_seal, vacuum_force_n


def _inside_any_hull(point: np.ndarray, pieces) -> bool:
    from scipy.spatial import Delaunay

    return any(Delaunay(p.vertices).find_simplex(point[None])[0] >= 0 for p in pieces)


def test_ring_is_split_and_keeps_its_hole() -> None:
    ring = trimesh.creation.annulus(r_min=0.018, r_max=0.03, height=0.015, sections=48)
    pieces = convex_decomposition(ring.vertices, ring.faces)
    assert len(pieces) >= 6
    assert sum(p.volume_m3 for p in pieces) == pytest.approx(ring.volume, rel=1e-9)  # exact clipping
    assert sum(p.hull_volume_m3 for p in pieces) < 1.15 * ring.volume
    assert not _inside_any_hull(np.zeros(3), pieces)  # the hole is free
    assert not _inside_any_hull(np.array([0.012, 0.0, 0.0]), pieces)
    assert _inside_any_hull(np.array([0.024, 0.0, 0.0]), pieces)  # the wall is solid


def test_l_bracket_is_split_into_convex_legs() -> None:
    # an L profile (legs 40 mm, 8 mm thick) extruded 60 mm along x, as a closed prism
    profile = np.array([[0, 0], [0.04, 0], [0.04, 0.008], [0.008, 0.008], [0.008, 0.04], [0, 0.04]])
    verts = np.vstack([np.column_stack([np.full(6, -0.03), profile]), np.column_stack([np.full(6, 0.03), profile])])
    faces = [(0, 2, 1), (0, 3, 2), (0, 4, 3), (0, 5, 4), (6, 7, 8), (6, 8, 9), (6, 9, 10), (6, 10, 11)]
    for i in range(6):
        j = (i + 1) % 6
        faces += [(i, j, j + 6), (i, j + 6, i + 6)]
    bracket = trimesh.Trimesh(verts, np.array(faces))
    bracket.fix_normals()
    assert bracket.is_watertight and bracket.volume > 0
    pieces = convex_decomposition(bracket.vertices, bracket.faces)
    assert 2 <= len(pieces) <= 4
    assert sum(p.volume_m3 for p in pieces) == pytest.approx(bracket.volume, rel=1e-9)
    assert all(p.volume_m3 / p.hull_volume_m3 > 0.9 for p in pieces)
    assert not _inside_any_hull(np.array([0.0, 0.03, 0.03]), pieces)  # the inside of the L is free


@settings(max_examples=15, deadline=None)
@given(
    ext=st.tuples(*[st.floats(0.005, 0.1)] * 3),
    rotvec=st.tuples(*[st.floats(-3.0, 3.0)] * 3),
)
def test_convex_meshes_stay_whole(ext, rotvec) -> None:
    box = trimesh.creation.box(extents=ext)
    box.apply_transform(make_pose(rotation_from_rotvec(rotvec), [0.01, -0.02, 0.03]))
    pieces = convex_decomposition(box.vertices, box.faces)
    assert len(pieces) == 1
    assert pieces[0].volume_m3 == pytest.approx(box.volume, rel=1e-9)


def test_open_or_inverted_mesh_is_rejected() -> None:
    box = trimesh.creation.box(extents=(0.02, 0.02, 0.02))
    with pytest.raises(MeshError):
        convex_decomposition(box.vertices, box.faces[:, ::-1])  # inside out
    with pytest.raises(MeshError):
        convex_decomposition(box.vertices, box.faces[:2])


def test_piece_limit_is_respected() -> None:
    ring = trimesh.creation.annulus(r_min=0.018, r_max=0.03, height=0.015, sections=32)
    pieces = convex_decomposition(ring.vertices, ring.faces, DecompositionOptions(max_pieces=4))
    assert len(pieces) <= 4
    assert sum(p.volume_m3 for p in pieces) == pytest.approx(ring.volume, rel=1e-9)


def _down(position) -> np.ndarray:
    return make_pose(np.diag([1.0, -1.0, -1.0]), position)


def test_seal_on_flat_face_edge_hole_and_curvature() -> None:
    box = trimesh.creation.box(extents=(0.06, 0.04, 0.03))
    flat = check_seal(box, _down([0.0, 0.0, 0.015]), 0.03)
    assert flat.sealed and flat.height_spread_m < 1e-9 and abs(flat.contact_depth_m) < 1e-9
    edge = check_seal(box, _down([0.025, 0.0, 0.015]), 0.03)
    assert not edge.sealed and edge.reason == "edge"
    ring = trimesh.creation.annulus(r_min=0.01, r_max=0.03, height=0.01, sections=64)
    hole = check_seal(ring, _down([0.0, 0.0, 0.005]), 0.03)
    assert not hole.sealed and hole.reason == "hole"
    small = trimesh.creation.icosphere(subdivisions=4, radius=0.012)
    curved = check_seal(small, _down([0.0, 0.0, 0.012]), 0.03)
    assert not curved.sealed and curved.reason in ("not_flat", "edge", "tilted")
    big = trimesh.creation.icosphere(subdivisions=4, radius=0.2)
    assert check_seal(big, _down([0.0, 0.0, 0.2]), 0.03).sealed
    tilted = check_seal(
        box, _down([0.0, 0.0, 0.015]) @ make_pose(rotation_from_rotvec([0.6, 0, 0])), 0.02, SealOptions(flatness_m=0.05)
    )
    assert not tilted.sealed and tilted.reason == "tilted"
    assert vacuum_force_n(0.03, 60.0, 1.0) == pytest.approx(60e3 * np.pi * 0.015**2)
