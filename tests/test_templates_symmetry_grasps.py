"""Grasps carried through a template's symmetries: a cube with one annotated top grasp keeps a top-down grasp in
every one of its 24 equivalent poses; images that coincide are dropped; images stay on the part's surface;
cylinders flip; the example cube in a bin gets a feasible plan whichever face is up."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from normpos_grasp.cell import load_cell
from normpos_grasp.geometry import make_pose, rotation_from_rotvec
from normpos_grasp.grasp.candidates import CandidateOptions, candidates_for_object, object_grasps, symmetry_group
from normpos_grasp.planning import PlanOptions, plan_pick
from normpos_grasp.records.template import GraspAnnotation, Symmetry, Template, TemplateFit
from normpos_grasp.sim.parts import default_part_library
from normpos_grasp.templates.library import load_library

ROOT = Path(__file__).resolve().parents[1]
DOWN = np.deg2rad(5.0)


def _rot(axis: list[float], deg: float, point: np.ndarray | None = None) -> np.ndarray:
    r = rotation_from_rotvec(np.asarray(axis, dtype=np.float64) * np.deg2rad(deg))
    p = np.zeros(3) if point is None else point
    return make_pose(r, p - r @ p)


def _cube(centre: np.ndarray | None = None, symmetric: bool = True) -> Template:
    """A 40 mm cube (centred at `centre`, object frame) with one top pinch and one top suction grasp."""
    c = np.zeros(3) if centre is None else centre
    mesh = trimesh.creation.box((0.04, 0.04, 0.04))
    mesh.apply_translation(c)
    top = make_pose(np.diag([1.0, -1.0, -1.0]), c + [0.0, 0.0, 0.02])
    grasps = (GraspAnnotation("top", "parallel", top, opening_m=0.05), GraspAnnotation("cup", "suction", top))
    gens = (_rot([0, 0, 1], 90, c), _rot([1, 0, 0], 90, c))
    return Template("cube", "cube", mesh, symmetry=Symmetry(discrete=gens if symmetric else ()), grasps=grasps)


def _top_down(template: Template, world_from_object: np.ndarray, kind: str, opts: CandidateOptions) -> list:
    cands = candidates_for_object(0, template, world_from_object, kind, opts)
    return [c for c in cands if np.arccos(np.clip(-c.world_from_tcp[2, 2], -1, 1)) < DOWN]


def test_generators_close_to_the_cube_group() -> None:
    group = symmetry_group(_cube().symmetry)
    assert group.shape == (24, 4, 4)
    np.testing.assert_allclose(group[0], np.eye(4))
    for g in group:  # proper rotations, pairwise distinct, closed under products
        np.testing.assert_allclose(g[:3, :3] @ g[:3, :3].T, np.eye(3), atol=1e-9)
        assert np.linalg.det(g[:3, :3]) == pytest.approx(1.0)
    flat = group.reshape(24, -1)
    assert np.min(np.linalg.norm(flat[:, None] - flat[None], axis=-1) + 10 * np.eye(24)) > 0.5
    prods = np.einsum("aij,bjk->abik", group, group).reshape(-1, 16)
    assert np.all(np.min(np.linalg.norm(prods[:, None] - flat[None], axis=-1), axis=1) < 1e-9)


@pytest.mark.parametrize("kind", ["parallel", "suction"])
def test_cube_keeps_a_top_down_grasp_in_every_equivalent_pose(kind: str) -> None:
    cube = _cube()
    group = symmetry_group(cube.symmetry)
    lift = make_pose(rotation_from_rotvec([0.0, 0.0, 0.4]), [0.5, 0.05, 0.03])
    on = CandidateOptions()
    off = CandidateOptions(symmetric=False)
    with_sym = [len(_top_down(cube, lift @ g, kind, on)) for g in group]
    without = [len(_top_down(cube, lift @ g, kind, off)) for g in group]
    assert min(with_sym) >= 1  # upside-down, on its side, turned: always a top-down grasp
    assert sum(n > 0 for n in without) == 4  # only the 4 poses with the annotated face up had one
    for g in group:  # and that grasp sits on the top face's centre
        best = _top_down(cube, lift @ g, kind, on)[0]
        np.testing.assert_allclose(best.world_from_tcp[:3, 3], lift[:3, 3] + [0, 0, 0.02], atol=1e-9)


def test_images_that_coincide_are_dropped() -> None:
    cube = _cube()
    par = object_grasps(cube, ("parallel",), CandidateOptions())
    cup = object_grasps(cube, ("suction",), CandidateOptions())
    # a pinch on each of 6 faces closing along each of 2 lines (jaws closing along x or -x are the same grasp);
    # a round cup on each of 6 faces (its turn about the approach does not matter)
    assert len(par) == 12 and len(cup) == 6
    assert par[0][2] == "top" and all(gid.startswith("top@s") for *_, gid, _ in par[1:])
    for grasps in (par, cup):
        poses = np.stack([p for *_, p in grasps])
        d = np.linalg.norm(poses[:, None, :3, 3] - poses[None, :, :3, 3], axis=-1)
        same_axis = np.einsum("ai,bi->ab", poses[:, :3, 2], poses[:, :3, 2]) > 0.99
        if grasps is par:
            same_axis &= np.abs(np.einsum("ai,bi->ab", poses[:, :3, 0], poses[:, :3, 0])) > 0.99
        assert not np.any((d < 1e-3) & same_axis & ~np.eye(len(poses), dtype=bool))


def test_images_stay_on_the_surface_for_an_off_centre_frame() -> None:
    """Symmetries about a point off the origin (translations in the 4x4s, as BOP stores them)."""
    centre = np.array([0.1, -0.03, 0.02])
    cube = _cube(centre)
    grasps = object_grasps(cube, ("parallel",), CandidateOptions())
    assert len(grasps) == 12
    pts = np.stack([p[:3, 3] for *_, p in grasps])
    dist = np.abs(trimesh.proximity.signed_distance(cube.mesh, pts))
    assert dist.max() < 1e-9
    for *_, p in grasps:  # each approaches into the cube: along the inward face normal
        np.testing.assert_allclose(p[:3, 2], -(p[:3, 3] - centre) / 0.02, atol=1e-9)


def test_cylinder_flip_and_continuous_axis() -> None:
    """A cap grasp on a cylinder (continuous axis z, flip about x): the other cap gets it too."""
    mesh = trimesh.creation.cylinder(0.02, 0.06, sections=48)
    cap = make_pose(np.diag([1.0, -1.0, -1.0]), [0.0, 0.0, 0.03])
    cyl = Template(
        "cyl",
        "cyl",
        mesh,
        shape="cylinder",
        symmetry=Symmetry(continuous=((np.array([0.0, 0.0, 1.0]), np.zeros(3)),), discrete=(_rot([1, 0, 0], 180),)),
        grasps=(GraspAnnotation("cap", "parallel", cap, opening_m=0.05),),
    )
    grasps = object_grasps(cyl, ("parallel",), CandidateOptions(symmetry_steps=4))
    z = sorted({round(float(p[2, 3]), 6) for *_, p in grasps})
    assert z == [-0.03, 0.03]
    assert len(grasps) == 4  # 2 caps x 2 closing lines (90 deg apart; 180 deg turns are the same pinch)
    upside_down = make_pose(rotation_from_rotvec([np.pi, 0.0, 0.0]), [0.5, 0.0, 0.04])
    assert _top_down(cyl, upside_down, "parallel", CandidateOptions())
    assert not _top_down(cyl, upside_down, "parallel", CandidateOptions(symmetric=False))


def test_synthesized_grasps_of_symmetric_parts_are_not_duplicated() -> None:
    """Box synthesis covers every face already: its symmetric images are all dropped as duplicates."""
    lib = {t.name: t for t in default_part_library()}
    for name in ("cube", "box", "plate", "sphere"):
        t = lib[name]
        assert t.symmetry.is_symmetric
        for kind in ("parallel", "suction"):
            with_sym = object_grasps(t, (kind,), CandidateOptions())
            without = object_grasps(t, (kind,), CandidateOptions(symmetric=False))
            assert len(with_sym) == len(without), (name, kind)
    # random antipodal samples on the bracket: its half-turn adds images, each an exact image of a sample
    b = lib["bracket"]
    flip = symmetry_group(b.symmetry)[1]
    with_sym = object_grasps(b, ("parallel",), CandidateOptions())
    base = {gid: p for _, _, gid, p in object_grasps(b, ("parallel",), CandidateOptions(symmetric=False))}
    extra = [(gid, p) for _, _, gid, p in with_sym if "@s" in gid]
    assert extra and len(with_sym) == len(base) + len(extra)
    for gid, p in extra:
        np.testing.assert_allclose(p, flip @ base[gid.split("@s")[0]], atol=1e-12)


def test_example_cube_upside_down_in_the_bin_is_planned() -> None:
    """The example cube_40mm (annotated top grasps only), lying on each of its faces in the example bin cell."""
    cube = load_library(ROOT / "examples" / "templates" / "cube_40mm").get("cube_40mm")
    cell = load_cell(ROOT / "examples" / "cells" / "ur5e_bin_parallel.yaml")
    floor = make_pose(None, [0.5, 0.0, 0.01 + 0.02])
    faces = [np.eye(4), _rot([1, 0, 0], 180), _rot([1, 0, 0], 90), _rot([0, 1, 0], -90)]
    for face in faces:
        fit = TemplateFit(cube, floor @ face, 1.0, 0.0, 1.0, 1.0, 0.0, True, instance_id=1)
        plan = plan_pick([fit], [], cell, PlanOptions())
        assert plan.status == "ok"
        approach = plan.chosen.candidate.world_from_tcp[:3, 2]
        assert approach[2] < -np.cos(DOWN)  # straight down onto the face that is up
    bare = PlanOptions(candidates=CandidateOptions(symmetric=False))
    upside = TemplateFit(cube, floor @ faces[1], 1.0, 0.0, 1.0, 1.0, 0.0, True, instance_id=1)
    assert plan_pick([upside], [], cell, bare).status != "ok"
