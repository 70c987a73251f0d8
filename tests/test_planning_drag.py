"""Drags: a part in a bin corner that no grasp reaches is dragged out by a fingertip on its top; the arm motion passes
the cell's judge, MuJoCo slides the part away from the walls, and a grasp is feasible afterwards."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest
import trimesh

from normpos_grasp.cell import load_cell
from normpos_grasp.cell.config import CellConfig
from normpos_grasp.cell.limits import SafetyLimits
from normpos_grasp.errors import PlanningError
from normpos_grasp.geometry import make_pose
from normpos_grasp.planning import PlanOptions, plan_pick
from normpos_grasp.planning.drag import drag_candidates, wall_gap
from normpos_grasp.planning.push import PushHand, judged_push_motion, push_candidates
from normpos_grasp.records.template import Template, TemplateFit
from normpos_grasp.sim.physics import GripperSpec
from normpos_grasp.sim.physics_push import simulate_push

CELL = Path(__file__).resolve().parents[1] / "examples" / "cells" / "ur5e_bin_parallel.yaml"
FLOOR_Z = 0.01  # the example cell's inner bin floor; walls at x = 0.3 / 0.7, y = -0.15 / 0.15, 0.15 m high


@pytest.fixture(scope="module")
def cell() -> CellConfig:
    return load_cell(CELL)


def _corner_block() -> tuple[Template, np.ndarray, TemplateFit]:
    part = Template("block", "block", trimesh.creation.box((0.05, 0.05, 0.02)), shape="box", mass_kg=0.06)
    pose = make_pose(None, [0.7 - 0.025 - 0.001, 0.15 - 0.025 - 0.001, FLOOR_Z + 0.01])  # 1 mm off both walls
    return part, pose, TemplateFit(part, pose, 1.0, 0.0, 1.0, 1.0, 0.0, True, instance_id=1)


def _statics(cell: CellConfig) -> list[tuple[str, np.ndarray, np.ndarray]]:
    return [(b.name, np.asarray(b.world_from_box), np.asarray(b.size)) for b in cell.static_boxes]


def test_a_corner_part_without_a_grasp_gets_a_drag_that_the_cell_accepts(cell: CellConfig) -> None:
    part, pose, fit = _corner_block()
    plan = plan_pick([fit], [], cell, PlanOptions())
    assert plan.status == "no_feasible_grasp" and plan.counts.get("collision_cell", 0) > 0  # the walls are in the way
    spec = GripperSpec.preset("2f85")
    hand = PushHand(spec.tip_beyond_tcp_m, spec.finger_width_m, spec.finger_thickness_m)
    assert next(push_candidates(plan, [fit], [], cell, hand, FLOOR_Z, 0.05), None) is None  # no room for a push
    drags = list(itertools.islice(drag_candidates(plan, [fit], [], cell, FLOOR_Z, 0.08), 6))
    assert drags and all(d.kind == "drag" and d.press_m > 0 for d in drags)
    assert all(d.push[0] <= 1e-9 and d.push[1] <= 1e-9 for d in drags)  # out of the (+x, +y) corner, not into it
    home = np.asarray(cell.home_q, dtype=np.float64)
    judged = []  # as simulate does: the drags whose arm motion is planned and passes the cell's judge
    for d in drags:
        try:
            judged.append((d, judged_push_motion(d, [fit], [], cell, home)))
        except PlanningError:
            continue
        if len(judged) == 2:
            break
    assert judged
    limits = SafetyLimits.from_cell(cell)
    bin_pose = np.asarray(cell.bin.world_from_bin)  # type: ignore[union-attr]
    inner = np.asarray(cell.bin.inner_size)  # type: ignore[union-attr]
    verts = np.asarray(part.mesh.vertices)
    assert wall_gap(verts @ pose[:3, :3].T + pose[:3, 3], bin_pose, inner) < 0.002  # it starts in the corner
    cleared = 0
    for drag, motion in judged:
        limits.check_trajectory(motion.t, motion.q)  # within the cell's joint, speed and workspace caps
        result = simulate_push([(part, pose)], _statics(cell), spec, drag.world_from_tcp, drag.push)
        assert result.outcome == "pushed", result.collision_with  # the hand never hits the bin
        moved = result.world_from_objects_final[0]
        assert abs(moved[2, 3] - pose[2, 3]) < 0.003  # slid (or stayed), still lying on the floor
        assert float((moved[:3, 3] - pose[:3, 3]) @ drag.push) > -1e-4  # never towards the walls
        fit_after = TemplateFit(part, moved, 1.0, 0.0, 1.0, 1.0, 0.0, True, instance_id=1)
        cleared += int(plan_pick([fit_after], [], cell, PlanOptions()).status == "ok")
    assert cleared >= 1  # MuJoCo slides the block out of the corner far enough to be picked


def test_a_part_away_from_the_walls_gets_no_drag(cell: CellConfig) -> None:
    part = Template("block", "block", trimesh.creation.box((0.05, 0.05, 0.02)), shape="box", mass_kg=0.06)
    pose = make_pose(None, [0.5, 0.0, FLOOR_Z + 0.01])
    fit = TemplateFit(part, pose, 1.0, 0.0, 1.0, 1.0, 0.0, True, instance_id=1)
    plan = plan_pick([fit], [], cell, PlanOptions())
    assert next(drag_candidates(plan, [fit], [], cell, FLOOR_Z, 0.05), None) is None
