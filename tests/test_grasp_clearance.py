"""Grasp depth adapted to the clearance below the part, tilted pinches next to walls, openings near the stroke,
ring pinches across the outer diameter: hand-built bin scenes whose answer is known."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from normpos_grasp.cell import load_cell
from normpos_grasp.cell.config import CellConfig
from normpos_grasp.geometry import make_pose, rotation_from_rotvec
from normpos_grasp.grasp.synthesis import synthesize
from normpos_grasp.planning import PlanOptions, plan_pick
from normpos_grasp.planning.evaluate import EvaluationOptions
from normpos_grasp.records.template import Template, TemplateFit

EXAMPLES = Path(__file__).resolve().parents[1] / "examples" / "cells"
FLOOR_Z = 0.01  # inner bin floor of the example UR5e cell (bin centre (0.5, 0), inner 0.40 x 0.30 m)


@pytest.fixture(scope="module")
def bin_cell() -> CellConfig:
    return load_cell(EXAMPLES / "ur5e_bin_parallel.yaml")


def _fit(template: Template, pose: np.ndarray, iid: int = 1) -> TemplateFit:
    return TemplateFit(template, pose, 1.0, 0.0, 1.0, 1.0, 0.0, True, instance_id=iid)


def _tip_lowest_z(cell: CellConfig, world_from_tcp: np.ndarray, opening: float) -> float:
    """Lowest world z of the finger boxes (independent corner computation)."""
    low = np.inf
    for shape, pose in cell.tool.posed_shapes(opening):
        if not shape.moves:
            continue
        half = np.asarray(shape.size) / 2.0
        corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * half
        world = (world_from_tcp @ pose)[:3, :3] @ corners.T + (world_from_tcp @ pose)[:3, 3:4]
        low = min(low, float(world[2].min()))
    return low


def test_flat_bar_fingertips_stop_above_the_floor(bin_cell: CellConfig) -> None:
    """A 25 mm bar lying flat: the nominal top-down pinch would push the 2F-85 tips into the floor; the planner
    raises it so the tips keep the margin, and the jaws still reach down the bar's sides."""
    bar = Template("bar", "bar", trimesh.creation.box((0.1, 0.025, 0.025)), shape="box")
    pose = make_pose(None, [0.5, 0.0, FLOOR_Z + 0.0125])
    opts = EvaluationOptions(max_feasible=0, max_feasible_per_target=0)
    plan = plan_pick([_fit(bar, pose)], [], bin_cell, PlanOptions(evaluation=opts))
    assert plan.status == "ok" and plan.chosen is not None
    feasible = [e for e in plan.evaluations if e.feasible]
    assert feasible
    for e in feasible:
        c = e.candidate
        low = _tip_lowest_z(bin_cell, c.world_from_tcp, c.opening_m)
        # the margin is kept along the approach: straight down it is vertical, tilted a little less
        assert low >= FLOOR_Z + opts.tip_margin_m * abs(c.world_from_tcp[2, 2]) - 1e-6, c.grasp_id
        assert low <= FLOOR_Z + 0.025 - opts.min_contact_m + 1e-6, c.grasp_id  # jaws overlap the part's sides
    assert any(e.candidate.grasp_id.endswith("@up") for e in feasible)
    # without the raise, the top-down pinches across the bar leave the tips closer to the floor than the margin
    no_raise = EvaluationOptions(max_feasible=0, max_feasible_per_target=0, max_raise_m=0.0)
    plan0 = plan_pick([_fit(bar, pose)], [], bin_cell, PlanOptions(evaluation=no_raise))
    top = [
        e
        for e in plan0.evaluations
        if e.candidate.world_from_tcp[2, 2] < -0.99 and e.candidate.opening_m <= bin_cell.tool.stroke_m
    ]
    assert top
    assert all(
        _tip_lowest_z(bin_cell, e.candidate.world_from_tcp, e.candidate.opening_m) < FLOOR_Z + opts.tip_margin_m
        for e in top
    )


def test_box_pinches_tilt_about_the_closing_axis() -> None:
    t = Template("b", "b", trimesh.creation.box((0.05, 0.03, 0.03)), shape="box")
    by_id = {g.id: g for g in synthesize(t, ("parallel",))}
    for gid, g in by_id.items():
        if "_t" not in gid:
            continue
        base = by_id[gid.split("_t")[0]]
        # same TCP point and closing axis; the approach turned about the closing axis
        assert np.allclose(g.object_from_tcp[:3, 3], base.object_from_tcp[:3, 3])
        assert np.allclose(g.object_from_tcp[:3, 0], base.object_from_tcp[:3, 0])
        assert not np.allclose(g.object_from_tcp[:3, 2], base.object_from_tcp[:3, 2])


def test_box_next_to_a_wall_is_picked(bin_cell: CellConfig) -> None:
    """A 60 x 60 x 30 mm box 5 mm from the -y wall, turned 45 degrees: the untilted pinches put a finger or the
    125 mm palm into the wall; a pinch tilted away from it is found."""
    part = Template("sq", "sq", trimesh.creation.box((0.06, 0.06, 0.03)), shape="box")
    half_diag = 0.03 * np.sqrt(2)
    pose = make_pose(rotation_from_rotvec([0.0, 0.0, np.pi / 4]), [0.5, -0.15 + half_diag + 0.005, FLOOR_Z + 0.015])
    plan = plan_pick([_fit(part, pose)], [], bin_cell, PlanOptions())
    assert plan.status == "ok" and plan.chosen is not None
    assert plan.chosen.candidate.world_from_tcp[1, 2] < -0.1  # the approach leans towards the wall: hand away


def test_opening_narrowed_to_the_stroke(bin_cell: CellConfig) -> None:
    """A 70 mm part + 2 x 10 mm clearance = 90 mm exceeds the 85 mm stroke: opened to the stroke instead."""
    part = Template("c", "c", trimesh.creation.box((0.07, 0.04, 0.04)), shape="box")
    pose = make_pose(None, [0.5, 0.0, FLOOR_Z + 0.02])
    opts = EvaluationOptions(max_feasible=0, max_feasible_per_target=0)
    plan = plan_pick([_fit(part, pose)], [], bin_cell, PlanOptions(evaluation=opts))
    across_long = [e for e in plan.evaluations if abs(e.candidate.world_from_tcp[0, 0]) > 0.99]
    assert across_long
    for e in across_long:
        assert e.reason != "stroke"
        assert e.candidate.opening_m == pytest.approx(bin_cell.tool.stroke_m)
    strict = EvaluationOptions(max_feasible=0, max_feasible_per_target=0, opening_slack_m=0.0)
    plan0 = plan_pick([_fit(part, pose)], [], bin_cell, PlanOptions(evaluation=strict))
    assert all(
        e.reason in ("stroke", "approach_angle")
        for e in plan0.evaluations
        if abs(e.candidate.world_from_tcp[0, 0]) > 0.99
    )


def test_flat_ring_pinched_across_its_outer_diameter(bin_cell: CellConfig) -> None:
    ring_mesh = trimesh.creation.annulus(r_min=0.018, r_max=0.03, height=0.015)
    ring = Template("ring", "ring", ring_mesh, shape="ring")
    ids = [g.id for g in synthesize(ring, ("parallel",))]
    assert any(i.startswith("cyl_top") for i in ids)
    pose = make_pose(None, [0.5, 0.0, FLOOR_Z + 0.0075])
    plan = plan_pick([_fit(ring, pose)], [], bin_cell, PlanOptions())
    assert plan.status == "ok" and plan.chosen is not None
    c = plan.chosen.candidate
    assert c.opening_m > 0.06  # outside the ring, not a finger in the 36 mm hole
    assert _tip_lowest_z(bin_cell, c.world_from_tcp, c.opening_m) >= FLOOR_Z + 0.003 - 1e-6


def test_configs_clear_is_conservative(bin_cell: CellConfig) -> None:
    """The vectorised sphere pre-test never calls a configuration free that the exact check finds colliding, and
    proves some free (random configurations around a bin with parts, holding one)."""
    from normpos_grasp.kinematics.arm import ArmModel
    from normpos_grasp.planning.plan import build_world

    part = Template("b", "b", trimesh.creation.box((0.06, 0.04, 0.03)), shape="box")
    fits = [_fit(part, make_pose(None, [0.45 + 0.08 * k, 0.02 * k, FLOOR_Z + 0.015]), k + 1) for k in range(3)]
    arm = ArmModel.from_name(bin_cell.robot_model, bin_cell.world_from_base)
    world, targets, _ = build_world(bin_cell, fits, [], arm)
    world.set_arm(arm)
    world.set_tool(bin_cell.tool)
    rng = np.random.default_rng(3)
    home = np.asarray(bin_cell.home_q)
    qs = home + rng.uniform(-1.2, 1.2, size=(300, 6))

    def bound_is_sound() -> None:
        clear = world.configs_clear(qs, 0.05)
        exact = np.array([world.check_config(q, 0.05) is None for q in qs])
        assert not np.any(clear & ~exact)
        assert clear.any() and (~exact).any()

    bound_is_sound()
    with world.holding(targets[0].name, targets[0].mesh, make_pose(None, [0.0, 0.0, 0.01])):  # type: ignore[arg-type]
        assert world.held_name == targets[0].name and not world.is_enabled(targets[0].name)
        bound_is_sound()
    assert world.held_name == "" and world.is_enabled(targets[0].name)


def test_symmetric_part_next_to_a_wall_closes_along_it(bin_cell: CellConfig) -> None:
    """A flat ring 16 mm from the -y wall, turned 15 degrees: the pinches across its outer diameter at the synthesised
    angles all put the 125 mm palm into the wall; the one turned about the ring's axis to close along the wall
    (palm parallel to it) is taken."""
    ring_mesh = trimesh.creation.annulus(r_min=0.018, r_max=0.03, height=0.015)
    ring = Template("ring", "ring", ring_mesh, shape="ring")
    pose = make_pose(rotation_from_rotvec([0.0, 0.0, np.deg2rad(15)]), [0.5, -0.15 + 0.03 + 0.016, FLOOR_Z + 0.0075])
    plan = plan_pick([_fit(ring, pose)], [], bin_cell, PlanOptions())
    assert plan.status == "ok" and plan.chosen is not None
    c = plan.chosen.candidate
    assert "@align" in c.grasp_id
    assert abs(c.world_from_tcp[1, 0]) < 0.05  # jaws close along x, parallel to the wall


def test_noise_margin_keeps_the_tool_off_neighbours(bin_cell: CellConfig) -> None:
    """A neighbour 1 mm beside a jaw's outer face: free for the exact tool, a hit for the tool grown by the 2 mm
    noise margin; 3 mm away it is free for both."""
    from normpos_grasp.collision.world import CollisionWorld

    opening = 0.05
    finger = next(s for s in bin_cell.tool.shapes if s.moves > 0)
    outer = opening / 2 + finger.size[0]  # right jaw's outer face, TCP x
    z = float(finger.tcp_from_shape[2, 3])
    for gap, margin_hit in ((0.001, True), (0.003, False)):
        world = CollisionWorld()
        world.add_box("n", make_pose(None, [outer + gap + 0.01, 0.0, z]), (0.02, 0.02, 0.02), "object")
        world.set_tool(bin_cell.tool, noise_margin_m=0.002)
        assert world.check_tool(np.eye(4), opening) is None
        hit = world.check_tool(np.eye(4), opening, margin=True)
        assert (hit is not None) == margin_hit
        assert hit is None or hit.reason == "collision_object"
