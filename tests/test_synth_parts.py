"""Default part library: names, watertight outward meshes, principal frames, symmetries, control points."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from normpos_grasp.records.template import SHAPE_CLASSES
from normpos_grasp.sim.parts import box_symmetry, default_part_library, part_library_by_name

LIB = default_part_library()
EXPECTED = {
    "cube": ("box", (40, 40, 40)),
    "box": ("box", (60, 40, 30)),
    "bar": ("box", (100, 25, 25)),
    "cylinder": ("cylinder", (40, 40, 70)),
    "sphere": ("sphere", (45, 45, 45)),
    "plate": ("plate", (80, 60, 8)),
    "ring": ("ring", (60, 60, 15)),
}


def test_names_labels_and_lookup() -> None:
    names = [t.name for t in LIB]
    assert names == ["cube", "box", "bar", "cylinder", "sphere", "plate", "bracket", "ring"]
    assert all(t.label == t.name for t in LIB)
    assert set(part_library_by_name()) == set(names)


@pytest.mark.parametrize("template", LIB, ids=lambda t: t.name)
def test_mesh_is_closed_outward_and_centred(template) -> None:
    mesh = template.mesh
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.volume > 0  # outward normals give a positive signed volume
    # every face normal points away from the centroid on convex parts; for all parts rays from far outside
    # along -normal hit their own face first, which a positive volume and consistent winding imply.
    np.testing.assert_allclose(mesh.center_mass, 0.0, atol=1e-9)
    inertia = np.asarray(mesh.moment_inertia)
    off = inertia - np.diag(np.diag(inertia))
    assert np.abs(off).max() <= 1e-9 * np.abs(inertia).max()
    assert template.shape in SHAPE_CLASSES and template.shape != "irregular"
    assert template.mass_kg == pytest.approx(
        mesh.volume * {"pom": 1410, "abs": 1050, "aluminium": 2700}[template.material]
    )
    # fits an 85 mm parallel gripper across at least one dimension
    assert mesh.extents.min() <= 0.085


@pytest.mark.parametrize("template", [t for t in LIB if t.name in EXPECTED], ids=lambda t: t.name)
def test_sizes_and_shapes(template) -> None:
    shape, size_mm = EXPECTED[template.name]
    assert template.shape == shape
    np.testing.assert_allclose(np.sort(template.extents_m * 1000), np.sort(size_mm), atol=0.05)


def test_bracket_profile() -> None:
    b = part_library_by_name()["bracket"]
    # L-profile 60 long with 40 mm legs, 8 mm thick: volume = 60 * (40*8 + 32*8) mm^3
    assert b.mesh.volume == pytest.approx(0.06 * (0.04 * 0.008 + 0.032 * 0.008), rel=1e-9)
    assert b.extents_m[0] == pytest.approx(0.06)
    assert not b.mesh.is_convex


@pytest.mark.parametrize("template", LIB, ids=lambda t: t.name)
def test_symmetries_map_the_part_onto_itself(template) -> None:
    mesh = template.mesh
    rng = np.random.default_rng(0)
    samples, _ = trimesh.sample.sample_surface(mesh, 120, seed=1)
    transforms = template.symmetry.transforms(continuous_steps=7)
    assert len(transforms) >= 2, "every default part has a symmetry"
    for t in transforms[rng.permutation(len(transforms))[:8]]:
        moved = samples @ t[:3, :3].T + t[:3, 3]
        d = np.abs(trimesh.proximity.signed_distance(mesh, moved))
        assert d.max() < 2e-4, f"{template.name}: symmetry moves the surface by {d.max() * 1000:.2f} mm"


def test_box_symmetry_counts() -> None:
    assert len(box_symmetry(np.array([1.0, 1.0, 1.0])).discrete) == 23
    assert len(box_symmetry(np.array([3.0, 1.0, 1.0])).discrete) == 7
    assert len(box_symmetry(np.array([3.0, 2.0, 1.0])).discrete) == 3


@pytest.mark.parametrize("template", LIB, ids=lambda t: t.name)
def test_control_points_lie_on_or_in_the_part(template) -> None:
    assert "centre" in template.control_points
    pts = np.array([p for k, p in template.control_points.items() if k != "centre" and not k.startswith("hole")])
    d = trimesh.proximity.signed_distance(template.mesh, pts)  # > 0 inside, < 0 outside
    assert d.min() > -1e-6, f"{template.name}: a control point lies outside the part"
    assert np.abs(d).max() < 1e-6, f"{template.name}: named corner/cap points must lie on the surface"


def test_ring_has_a_hole_at_its_hole_centres() -> None:
    ring = part_library_by_name()["ring"]
    d = trimesh.proximity.signed_distance(ring.mesh, np.array([ring.control_points["hole_top"], [0, 0, 0]]))
    assert np.all(d < -0.017)  # 18 mm inner radius: the hole centre is 18 mm from the material
