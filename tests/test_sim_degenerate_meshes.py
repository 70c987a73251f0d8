"""Collision pieces MuJoCo accepts for any user mesh: flat and thin pieces thickened, pieces without area dropped;
the example l_bracket, a 2 mm sheet-metal bracket and a 0.2 mm shim build scenes that settle, and their grasp
validation models compile."""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np
import pytest
import trimesh
from scipy.spatial import ConvexHull

import normpos_grasp.sim  # noqa: F401  (sets MUJOCO_GL=egl before mujoco loads)
from normpos_grasp.errors import MeshError
from normpos_grasp.records.template import Template
from normpos_grasp.sim.physics import collision_pieces
from normpos_grasp.sim.physics_decompose import MIN_THICKNESS_M, collision_hull, collision_hulls
from normpos_grasp.sim.scene import SceneOptions, compose_scene, convex_pieces
from normpos_grasp.templates.library import load_library

ROOT = Path(__file__).resolve().parents[1]


def _compiles(points: np.ndarray) -> None:
    """MuJoCo compiles a free body colliding through a mesh of these points (raises ValueError otherwise)."""
    xml = (
        '<mujoco><asset><mesh name="m" vertex="' + " ".join(f"{x:.12g}" for x in points.reshape(-1)) + '"/></asset>'
        '<worldbody><body><freejoint/><geom type="mesh" mesh="m" mass="0.1"/></body></worldbody></mujoco>'
    )
    mujoco.MjModel.from_xml_string(xml)


def _sheet_l(thickness_mm: float, leg_a: float = 40.0, leg_b: float = 30.0, length: float = 50.0) -> trimesh.Trimesh:
    """An L profile (legs `leg_a` x `leg_b`, `thickness_mm` thick, mm) extruded `length` mm along z, placed off
    the origin and turned, as a CAD export might come."""
    t = thickness_mm
    profile = np.array([[0, 0], [leg_a, 0], [leg_a, t], [t, t], [t, leg_b], [0, leg_b]], dtype=np.float64)
    k = len(profile)
    verts = np.vstack([np.column_stack([profile, np.zeros(k)]), np.column_stack([profile, np.full(k, length)])])
    faces = []
    for a, b, c in [(0, 1, 2), (0, 2, 3), (0, 3, 4), (0, 4, 5)]:
        faces += [(a, c, b), (a + k, b + k, c + k)]
    for i in range(k):
        j = (i + 1) % k
        faces += [(i, j, j + k), (i, j + k, i + k)]
    mesh = trimesh.Trimesh(verts, np.asarray(faces), process=True)
    mesh.fix_normals()
    rot = trimesh.transformations.rotation_matrix(0.7, [1.0, 2.0, 0.5])
    mesh.apply_transform(rot)
    mesh.apply_translation([13.0, -7.0, 4.0])
    return mesh


def _library(tmp_path: Path, parts: dict[str, tuple[trimesh.Trimesh, str]]) -> list[Template]:
    """Templates written as a user would (STL in mm + template.yaml) and loaded through the library."""
    for name, (mesh, shape) in parts.items():
        folder = tmp_path / name
        folder.mkdir()
        mesh.export(folder / "mesh.stl")
        (folder / "template.yaml").write_text(
            f"name: {name}\nmesh: mesh.stl\nunits: mm\nshape: {shape}\nmass_kg: 0.03\nmaterial: steel\n"
        )
    return list(load_library(tmp_path))


def test_flat_piece_is_thickened_and_compiles() -> None:
    square = np.array([[0, 0, 0], [0.03, 0, 0], [0.03, 0.02, 0], [0, 0.02, 0], [0.015, 0.01, 0]], dtype=np.float64)
    with pytest.raises(ValueError, match="coplanar"):
        _compiles(square)
    hull = collision_hull(square)
    assert hull is not None
    assert np.ptp(hull[:, 2]) == pytest.approx(MIN_THICKNESS_M)  # thickened across the plane, symmetrically
    assert hull[:, 2].mean() == pytest.approx(0.0, abs=1e-12)
    np.testing.assert_allclose(np.ptp(hull[:, :2], axis=0), [0.03, 0.02])  # in-plane size kept
    _compiles(hull)
    tilted = square @ trimesh.transformations.rotation_matrix(1.1, [1, 1, 0])[:3, :3].T
    tilted_hull = collision_hull(tilted + 1e-7 * np.random.default_rng(0).standard_normal(tilted.shape))
    assert tilted_hull is not None and ConvexHull(tilted_hull).volume == pytest.approx(6e-4 * MIN_THICKNESS_M, 1e-3)
    _compiles(tilted_hull)


def test_thick_piece_is_unchanged_and_lines_are_dropped() -> None:
    cube = np.asarray(trimesh.creation.box((0.02, 0.02, 0.02)).vertices)
    hull = collision_hull(cube)
    assert hull is not None
    np.testing.assert_allclose(np.sort(hull, axis=0), np.sort(cube, axis=0))
    line = np.outer(np.linspace(0, 0.05, 6), [1.0, 2.0, 3.0])
    assert collision_hull(line) is None
    assert collision_hull(np.zeros((5, 3))) is None
    assert collision_hull(cube[:2]) is None
    assert len(collision_hulls([cube, line, cube + 0.1])) == 2
    with pytest.raises(MeshError, match="degenerate"):
        collision_hulls([line])


def test_example_l_bracket_scene_builds_and_settles() -> None:
    bracket = load_library(ROOT / "examples" / "templates" / "l_bracket").get("l_bracket")
    pieces = convex_pieces(bracket)
    assert len(pieces) >= 2 and all(kind == "mesh" for kind, _ in pieces)
    hull_volume = sum(ConvexHull(p).volume for _, p in pieces)
    assert hull_volume == pytest.approx(bracket.mesh.volume, rel=0.05)  # the legs, not the L's hull
    layout = compose_scene(SceneOptions(count=4, seed=1), [bracket])
    assert layout.n_parts == 4
    assert layout.max_penetration_m < 1e-3
    for k in range(layout.n_parts):  # at rest inside the bin
        assert layout.part_mesh_world(k).vertices[:, 2].min() >= layout.options.bin_floor_thickness_m - 1e-3


def test_thin_user_parts_build_scenes_and_grasp_models(tmp_path: Path) -> None:
    sheet = _sheet_l(2.0)
    shim = trimesh.creation.box((40.0, 20.0, 0.2))
    shim.apply_translation([5.0, 3.0, 1.0])
    lib = _library(
        tmp_path,
        {
            "sheet_bracket": (sheet, "bracket"),
            "sheet_irregular": (sheet.copy(), "irregular"),
            "shim": (shim, "irregular"),
        },
    )
    for t in lib:
        pieces = convex_pieces(t)
        assert pieces and all(kind == "mesh" for kind, _ in pieces)
        for _, data in pieces:
            _compiles(np.asarray(data))
            normal = np.linalg.svd(data - data.mean(axis=0))[2][2]
            assert np.ptp(data @ normal) >= MIN_THICKNESS_M - 1e-9  # the shim (0.2 mm) is thickened to 1 mm
        for kind, data in collision_pieces(t):  # grasp validation's geometry of the same part
            if kind == "mesh":
                _compiles(np.asarray(data))
        if t.name.startswith("sheet"):  # the two 2 mm legs, not the L's hull
            volume = sum(ConvexHull(d).volume for k, d in pieces if k == "mesh")
            assert volume < 1.3 * t.mesh.volume
        layout = compose_scene(SceneOptions(count=3, seed=2), [t])
        assert layout.n_parts == 3, t.name
        assert np.all(np.isfinite(layout.world_from_object))
        for k in range(layout.n_parts):
            assert layout.part_mesh_world(k).vertices[:, 2].min() >= layout.options.bin_floor_thickness_m - 2e-3
