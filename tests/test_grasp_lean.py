"""Leaned grasps (`grasp.lean`, the planner's 'leaned' pass): a part by a bin wall whose top-down grasps the walls
block gets a copy leaned away from the wall that passes every check; copies only of blocked top-down grasps, slides
bounded by the part; the pass never runs where the first pass plans."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from test_grasp_plan import _independent_collisions

from normpos_grasp.cell import load_cell
from normpos_grasp.cell.config import CellConfig
from normpos_grasp.cell.limits import SafetyLimits
from normpos_grasp.geometry import make_pose, rotation_from_rotvec
from normpos_grasp.grasp import lean
from normpos_grasp.grasp.quality import judge
from normpos_grasp.planning import PlanOptions, plan_pick
from normpos_grasp.planning import plan as plan_module
from normpos_grasp.records.grasp import GraspCandidate
from normpos_grasp.records.template import Template, TemplateFit
from normpos_grasp.sim.parts import part_library_by_name

CELL = Path(__file__).resolve().parents[1] / "examples" / "cells" / "ur5e_bin_parallel.yaml"
FLOOR_Z = 0.01  # the example cell's inner bin floor; walls at x = 0.3 / 0.7, y = -0.15 / 0.15, 0.15 m high


@pytest.fixture(scope="module")
def cell() -> CellConfig:
    return load_cell(CELL)


def _by_wall(name: str, yaw: float, gap_m: float, wall: str) -> tuple[Template, np.ndarray]:
    """A default part lying on the bin floor turned by `yaw`, `gap_m` from the +x or +y wall."""
    part = part_library_by_name()[name]
    rot = rotation_from_rotvec([0.0, 0.0, yaw])
    verts = np.asarray(part.mesh.vertices) @ rot.T
    lo, hi = verts.min(axis=0), verts.max(axis=0)
    x = 0.7 - hi[0] - gap_m if wall == "x" else 0.5
    y = 0.15 - hi[1] - gap_m if wall == "y" else 0.0
    return part, make_pose(rot, [x, y, FLOOR_Z - lo[2]])


def _fit(part: Template, pose: np.ndarray) -> TemplateFit:
    return TemplateFit(part, pose, 1.0, 0.0, 1.0, 1.0, 0.0, True, instance_id=1)


@pytest.mark.parametrize(("name", "yaw", "gap", "wall"), [("bar", 0.4, 0.02, "y"), ("cube", 0.4, 0.01, "x")])
def test_a_part_by_the_wall_gets_a_leaned_grasp_that_passes_every_check(
    cell: CellConfig, name: str, yaw: float, gap: float, wall: str
) -> None:
    part, pose = _by_wall(name, yaw, gap, wall)
    fits = [_fit(part, pose)]
    before = plan_pick(fits, [], cell, PlanOptions(leans=None))
    assert before.status == "no_feasible_grasp" and before.counts.get("collision_cell", 0) > 0  # the wall
    assert before.planning_pass == ""  # no grasp, no pass
    plan = plan_pick(fits, [], cell, PlanOptions())
    assert plan.status == "ok" and plan.chosen is not None, plan.counts
    assert plan.planning_pass == "leaned"  # the plan says which pass found its grasp (simulate's picks.csv)
    c = plan.chosen.candidate
    assert any(f"@{way}" in c.grasp_id for way in ("lean", "spin", "slide")), c.grasp_id
    assert c.world_from_tcp[2, 2] < -np.cos(lean.LeanOptions().max_from_down_rad)  # from above
    # the grip mechanics hold it (contacts on the part, friction cones, load)
    mech = judge(c.scheme, part.mesh, part.mass_kg, pose, c.world_from_tcp, plan.tool)
    assert mech.ok and mech.success > 0.0
    # within the cell's caps, and clear of the bin per an independent world (trimesh + the kinematics' FK)
    assert plan.trajectory is not None
    SafetyLimits.from_cell(cell).check_trajectory(plan.trajectory.t, plan.trajectory.q)
    assert _independent_collisions(plan, cell, [(part.mesh, pose)], c.target) == []
    # the plan is the leaned pass's: it evaluated only copies (as the dual-tool 'turned' pass does)
    assert all(any(f"@{w}" in e.candidate.grasp_id for w in ("lean", "spin", "slide")) for e in plan.evaluations)


def _candidate(world_from_tcp: np.ndarray, target: int = 0, opening: float = 0.05) -> GraspCandidate:
    return GraspCandidate(target, "p", "g", "synthesized", "parallel", world_from_tcp, opening, 0.05, 0.05, 1.0)


def _down(x: float = 0.5, y: float = 0.0, z: float = 0.03) -> np.ndarray:
    """Straight down (TCP z), the jaws closing along world y (TCP x), the pads' width along world x (TCP y)."""
    return make_pose(np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]]), [x, y, z])


def _wall_at(x_wall: float):  # type: ignore[no-untyped-def]
    """blocked(): a stand-in for the tool's boxes against a wall at world x >= x_wall: a 75 mm wide body whose
    bottom is 49 mm behind the TCP (the 2F-85's palm) overlaps the wall."""

    def blocked(poses: np.ndarray, openings: np.ndarray) -> np.ndarray:
        corners = np.array([[sx * 0.0625, sy * 0.0375, -0.049, 1.0] for sx in (-1, 1) for sy in (-1, 1)])
        world = np.einsum("nij,kj->nki", poses, corners)[..., :3]
        return world[..., 0].max(axis=1) >= x_wall

    return blocked


def test_copies_only_of_blocked_top_down_grasps() -> None:
    blocked = _wall_at(0.53)
    down = _candidate(_down())  # palm reaches x = 0.5375: blocked
    side = _candidate(make_pose(rotation_from_rotvec([0.0, -np.pi / 2, 0.0]), [0.5, 0.0, 0.03]))  # approach -x
    assert blocked(np.stack([side.world_from_tcp]), np.array([0.05]))[0]  # blocked too, but a side grasp
    free = _candidate(_down(x=0.4))  # palm reaches x = 0.4375: clear
    points = {0: np.array([[0.48, -0.04, 0.01], [0.52, 0.04, 0.05]])}
    copies = lean.wall_leans([down, side, free], blocked, None, None, points)
    assert copies and any("@lean" in c.grasp_id for c in copies)
    assert all(c.grasp_id.startswith("g@") for c in copies)
    sources = {id(c) for c in (down, side, free)}
    assert not any(id(c) in sources for c in copies)
    for c in copies:  # each a copy of `down`: from above, clear of the wall, the jaws closing along the same line
        assert -c.world_from_tcp[2, 2] >= np.cos(lean.LeanOptions().max_from_down_rad)
        assert not blocked(np.stack([c.world_from_tcp]), np.array([c.opening_m]))[0]
        assert abs(abs(c.world_from_tcp[:3, 0] @ down.world_from_tcp[:3, 0]) - 1.0) < 1e-9
    assert lean.wall_leans([side], blocked, None, None, points) == []  # side grasps get no copies
    assert lean.wall_leans([free], blocked, None, None, points) == []  # nor grasps the cell does not block


def test_slides_stay_over_the_part() -> None:
    # a wall that blocks unless the TCP moves along its y axis by more than 15 mm (slides only: no lean clears it)
    def blocked(poses: np.ndarray, openings: np.ndarray) -> np.ndarray:
        return (np.abs(poses[:, 0, 3] - 0.5) < 0.015) | (np.abs(poses[:, 2, 2] + 1.0) > 1e-9)

    c = _candidate(_down())
    slides = lean.LeanOptions(slides_m=(0.01, 0.02, 0.03))  # off by default (LeanOptions: slid bars slipped)
    # the part 70 mm long along the slide (world x): 20 and 30 mm slides keep the TCP 5 mm inside it, both ways
    long_part = {0: np.array([[0.465, -0.02, 0.01], [0.535, 0.02, 0.05]])}
    copies = lean.wall_leans([c], blocked, None, slides, long_part)
    slid = sorted(round(float(k.world_from_tcp[0, 3]) - 0.5, 6) for k in copies)
    assert slid == [-0.03, -0.02, 0.02, 0.03] and all("@slide" in k.grasp_id for k in copies)
    # a part 40 mm long: no slide leaves the TCP 5 mm inside it, so no copy
    short_part = {0: np.array([[0.48, -0.02, 0.01], [0.52, 0.02, 0.05]])}
    assert lean.wall_leans([c], blocked, None, slides, short_part) == []
    assert lean.wall_leans([c], blocked, None, slides) == []  # without the part's points: no slides
    assert lean.wall_leans([c], blocked, None, None, long_part) == []  # the default slides nothing


def test_the_leaned_pass_does_not_run_where_the_first_pass_plans(
    cell: CellConfig, monkeypatch: pytest.MonkeyPatch
) -> None:
    part, pose = _by_wall("bar", 0.4, 0.02, "y")
    free = _fit(part, make_pose(pose[:3, :3], [0.5, 0.0, pose[2, 3]]))  # the same part mid-bin
    calls = []
    real = plan_module.wall_leans

    def counted(*args, **kwargs):  # type: ignore[no-untyped-def]
        calls.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(plan_module, "wall_leans", counted)
    plan = plan_pick([free], [], cell, PlanOptions())
    assert plan.status == "ok" and not calls and plan.planning_pass == "first"
    without = plan_pick([free], [], cell, PlanOptions(leans=None))
    doc, doc_without = plan.to_json(), without.to_json()
    doc.pop("timing_ms"), doc_without.pop("timing_ms")
    assert doc == doc_without  # the same plan, less its clock
    plan_pick([_fit(part, pose)], [], cell, PlanOptions())  # by the wall: the first pass finds nothing
    assert calls
