"""The suction bin example cell and the geometric rule of a suction-friendly part (issue 17: "suction cell on
suction-friendly parts"): a patch of the template where the tool's cup, widened by the fit's margin, seals and holds
the part's weight and payload torque, and a mass within the cup's payload."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import trimesh

from normpos_grasp.cell import resolve_cell
from normpos_grasp.grasp.quality import QualityOptions, cup_payload_kg, suction_friendliness
from normpos_grasp.sim.parts import default_part_library

CUP_30 = replace(QualityOptions(), cup_diameter_m=0.03)


def _part(name: str) -> tuple[trimesh.Trimesh, float]:
    t = next(p for p in default_part_library() if p.name == name)
    return t.mesh, float(t.mass_kg)


def test_suction_bin_cell_is_the_bin_cell_with_a_30_mm_cup() -> None:
    cell = resolve_cell("ur5e_bin_suction")  # packaged name
    parallel = resolve_cell("ur5e_bin_parallel")
    assert cell.tool.kind == "suction" and cell.tool.cup_diameter_m == pytest.approx(0.03)
    assert cell.bin is not None and np.allclose(cell.bin.inner_size, parallel.bin.inner_size)
    assert np.allclose(cell.tool.flange_from_tcp[:3, 3], [0.0, 0.0, 0.18])


def test_payload_is_the_vacuum_over_the_load_factor() -> None:
    # 60 kPa x pi (15 mm)^2 x 0.8 = 33.9 N; carried with 2 g of acceleration: 1.73 kg
    assert cup_payload_kg(CUP_30) == pytest.approx(60e3 * np.pi * 0.015**2 * 0.8 / (9.81 * 2.0))
    mesh, _ = _part("cube")
    heavy = suction_friendliness(mesh, 2.0, CUP_30)
    assert not heavy.friendly and heavy.reason == "payload"


def test_a_cube_has_a_patch_on_every_face_and_lands_with_one_up() -> None:
    mesh, mass = _part("cube")
    verdict = suction_friendliness(mesh, mass, CUP_30)
    assert verdict.friendly and verdict.reason == "" and verdict.share == pytest.approx(1.0)
    # every face centre of the 40 mm cube seals a 34 mm footprint; all six face directions carry a patch
    faces = np.round(verdict.normals).astype(int)
    assert {tuple(f) for f in faces} >= {(1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1)}
    assert np.all(np.abs(verdict.patches).max(axis=1) == pytest.approx(0.02, abs=1e-6))  # on the surface
    # a 40 mm cup (44 mm with the margin) finds no patch on the same cube
    big = suction_friendliness(mesh, mass, replace(CUP_30, cup_diameter_m=0.04))
    assert not big.friendly and big.reason == "no_patch"


@pytest.mark.parametrize("name", ["sphere", "ring"])
def test_curved_or_narrow_parts_have_no_patch(name: str) -> None:
    # a 45 mm sphere sags 7.8 mm under the 34 mm footprint (4 mm allowed); the ring's annulus is 12 mm wide
    mesh, mass = _part(name)
    verdict = suction_friendliness(mesh, mass, CUP_30)
    assert not verdict.friendly and verdict.reason == "no_patch" and len(verdict.patches) == 0


def test_a_lying_cylinder_keeps_its_caps_only() -> None:
    mesh, mass = _part("cylinder")  # 40 mm diameter, 70 mm long: the caps seal, the side (20 mm radius) does not
    verdict = suction_friendliness(mesh, mass, CUP_30)
    assert verdict.friendly and len(verdict.patches) >= 1
    axis = np.argmax(mesh.extents)
    assert np.all(np.abs(verdict.normals[:, axis]) > 0.99)  # every patch on a cap
    assert verdict.share < 0.5  # mostly it rests on its side, no patch facing up
    strict = suction_friendliness(mesh, mass, CUP_30, min_share=0.95)
    assert not strict.friendly and strict.reason == "resting"


def test_payload_torque_about_the_cup_rules_out_far_patches() -> None:
    # a 200 x 40 x 10 mm slab of 0.5 kg: with the cup at the centre the moment is zero; the end patches (90 mm
    # from the centre of mass) carry 0.5 x 9.81 x 2 x 0.09 = 0.88 N m against F_vac r / 4 = 0.13 N m
    slab = trimesh.creation.box((0.2, 0.04, 0.01))
    verdict = suction_friendliness(slab, 0.5, CUP_30)
    assert verdict.friendly
    assert np.abs(verdict.patches[:, 0]).max() < 0.03  # only patches near the centre of mass


def _down_at(x: float, z: float) -> np.ndarray:
    g = np.eye(4)
    g[:3, :3] = np.diag([1.0, -1.0, -1.0])  # approach straight down
    g[:3, 3] = [x, 0.0, z]
    return g


def test_measured_seal_judges_the_surface_not_the_depth_noise() -> None:
    from normpos_grasp.grasp.quality import measured_seal

    # a D435 at 0.9 m: points 1.4 mm apart, 1.5 mm RMS depth noise; a 60 x 40 mm flat top at z = 40 mm
    rng = np.random.default_rng(7)
    xs, ys = np.meshgrid(np.arange(-0.03, 0.03, 0.0014), np.arange(-0.02, 0.02, 0.0014))
    x, y = xs.ravel() + 0.5, ys.ravel()
    flat = np.stack([x, y, 0.04 + rng.normal(0.0, 0.0015, x.size)], axis=1)
    under = np.hypot(x - 0.5, y) <= 0.017
    spread = np.percentile(flat[under, 2], 95) - np.percentile(flat[under, 2], 5)
    assert spread > 0.004  # the raw points' spread alone would refuse this flat top
    assert measured_seal(flat, _down_at(0.5, 0.04), CUP_30)
    # the same top tilted 10 degrees: it rises 6 mm across the 34 mm footprint
    tilted = flat.copy()
    tilted[:, 2] += np.tan(np.radians(10.0)) * (x - 0.5)
    assert not measured_seal(tilted, _down_at(0.5, 0.04), CUP_30)
    # a 40 mm cylinder on its side with the same noise: 17 mm off the crest it has dropped 9.5 mm
    side = np.stack([x, y, 0.02 + np.sqrt(np.clip(0.02**2 - y**2, 0.0, None)) + rng.normal(0, 0.0015, x.size)], axis=1)
    assert not measured_seal(side, _down_at(0.5, 0.04), CUP_30)


def test_measured_seal_refuses_a_face_narrower_than_the_footprint() -> None:
    from normpos_grasp.grasp.quality import measured_seal

    # a box on its 30 mm side: the top is 60 x 30 mm, and the camera sees the top rows of a side face at y = 15 mm
    rng = np.random.default_rng(8)
    xs, ys = np.meshgrid(np.arange(-0.03, 0.03, 0.0014), np.arange(-0.015, 0.015, 0.0014))
    top = np.stack([xs.ravel() + 0.5, ys.ravel(), np.full(xs.size, 0.04)], axis=1)
    xs, zs = np.meshgrid(np.arange(-0.03, 0.03, 0.0014), np.arange(0.0, 0.01, 0.0014))
    wall = np.stack([xs.ravel() + 0.5, np.full(xs.size, 0.015), 0.04 - zs.ravel()], axis=1)
    pts = np.concatenate([top, wall])
    pts[:, 2] += rng.normal(0.0, 0.001, len(pts))
    assert not measured_seal(pts, _down_at(0.5, 0.04), CUP_30)  # 34 mm footprint on a 30 mm face
    small = replace(CUP_30, cup_diameter_m=0.02)
    assert measured_seal(pts, _down_at(0.5, 0.04), small)  # a 24 mm footprint fits the face
