"""The planner holds its plans to the cell's judge (`SafetyLimits.check_path`, what `execution.plan.check_plan` runs
before anything moves): a branch whose segments leave the workspace box is a rejected branch with a named reason,
never a plan that execution would refuse."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import trimesh

from normpos_grasp.cell import CellConfig, load_cell
from normpos_grasp.errors import SafetyViolation
from normpos_grasp.execution.plan import check_plan, parse_plan
from normpos_grasp.execution.safety import SafetyLimits
from normpos_grasp.geometry import make_pose
from normpos_grasp.planning import plan_pick
from normpos_grasp.planning.plan import stop_line
from normpos_grasp.records.template import Template, TemplateFit

CELL = load_cell(Path(__file__).resolve().parents[1] / "examples" / "cells" / "ur5e_bin_parallel.yaml")
PART = Template("box", "box", trimesh.creation.box((0.06, 0.04, 0.03)), shape="box")
FIT = TemplateFit(PART, make_pose(np.eye(3), [0.5, 0.05, 0.025]), 1.0, 0.0, 1.0, 1.0, 0.0, True, instance_id=1)


def _cell_with_y_min(y_min: float) -> CellConfig:
    """The example cell with the workspace box's lower y bound (world frame) at `y_min` m."""
    lo = np.array(CELL.motion.workspace_min, dtype=np.float64)
    lo[1] = y_min
    return replace(CELL, motion=replace(CELL.motion, workspace_min=lo))


def test_a_branch_whose_transfer_leaves_the_box_is_replaced_by_one_the_cell_accepts() -> None:
    # the place's TCP is at y = -0.450 m; the quickest branch's straight joint segment retreat -> pre_place dips to
    # y = -0.4522 m on the way: a box ending at y = -0.452 m admits every waypoint but not that segment
    cell = _cell_with_y_min(-0.452)
    quickest = plan_pick([FIT], [], CELL)
    assert quickest.status == "ok"
    check_plan(parse_plan(quickest.to_json()), SafetyLimits.from_cell(CELL))
    with pytest.raises(SafetyViolation, match="outside the workspace box") as refused:
        check_plan(parse_plan(quickest.to_json()), SafetyLimits.from_cell(cell))
    assert refused.value.detail["check"] == "workspace"
    plan = plan_pick([FIT], [], cell)
    assert plan.status == "ok" and plan.trajectory is not None
    check_plan(parse_plan(plan.to_json()), SafetyLimits.from_cell(cell))  # raises if execution would refuse it
    assert plan.counts.get("place_cell_workspace", 0) >= 1  # the refused branches are counted by reason


def test_a_cell_that_allows_no_place_gets_no_plan_and_a_named_reason() -> None:
    cell = _cell_with_y_min(-0.40)  # the place (y = -0.45 m) lies outside the box: nothing may be carried there
    plan = plan_pick([FIT], [], cell)
    assert plan.status == "no_feasible_grasp" and plan.trajectory is None
    assert plan.counts.get("place_cell_workspace", 0) >= 1
    assert "place_cell_workspace" in stop_line(plan)
