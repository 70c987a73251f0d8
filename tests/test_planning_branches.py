"""Equivalent configurations of a pick-and-place (planning.branches) and the motion-time estimate they are ranked
by (planning.timing.rest_to_rest_s): the estimate is Ruckig's time, a half turn of joint 6 is the same grasp only
for a tool that looks the same turned, and an equivalent place pose leaves the part where the planned one does."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import trimesh

import normpos_grasp.planning.plan as plan_module
from normpos_grasp.cell import load_cell
from normpos_grasp.errors import PlanningError
from normpos_grasp.execution.plan import check_plan, parse_plan
from normpos_grasp.execution.safety import SafetyLimits
from normpos_grasp.geometry import make_pose, rotation_from_rotvec
from normpos_grasp.kinematics.arm import ArmModel
from normpos_grasp.planning import plan_pick
from normpos_grasp.planning.branches import HALF_TURN, half_turn_symmetric, place_poses, quickest_grasp
from normpos_grasp.planning.plan import PlanOptions
from normpos_grasp.planning.timing import _ruckig, joint_caps, rest_to_rest_s
from normpos_grasp.records.grasp import GraspCandidate
from normpos_grasp.records.plan import Evaluation, PickPlan
from normpos_grasp.records.template import Template, TemplateFit
from normpos_grasp.records.tool import ToolShape

EXAMPLES = Path(__file__).resolve().parents[1] / "examples" / "cells"
CELL = load_cell(EXAMPLES / "ur5e_bin_parallel.yaml")
ARM = ArmModel.from_name("ur5e")
CAPS = joint_caps(np.full(6, 2.5), np.full(6, 5.0))
DOWN = np.diag([1.0, -1.0, -1.0, 1.0])  # TCP z pointing down


def test_rest_to_rest_estimate_is_ruckigs_time() -> None:
    rng = np.random.default_rng(3)
    for _ in range(40):
        d, v, a, j = rng.uniform(1e-3, 4.0), rng.uniform(0.2, 3.0), rng.uniform(0.5, 6.0), rng.uniform(5.0, 100.0)
        want = _ruckig(([0.0], [0.0], [0.0]), ([d], [0.0], [0.0]), ([v], [a], [j])).duration
        assert abs(float(rest_to_rest_s(d, v, a, j)) - want) < 1e-9
    assert float(rest_to_rest_s(0.0, 1.0, 1.0, 1.0)) == 0.0


def test_two_jaw_gripper_is_half_turn_symmetric_and_a_lopsided_one_is_not() -> None:
    tool = CELL.tool
    assert half_turn_symmetric(tool)
    camera = ToolShape(
        "camera", (0.03, 0.03, 0.03), np.array([[1, 0, 0, 0.06], [0, 1, 0, 0], [0, 0, 1, -0.1], [0, 0, 0, 1.0]])
    )
    assert not half_turn_symmetric(replace(tool, shapes=(*tool.shapes, camera)))
    offset = np.array(tool.flange_from_tcp, dtype=np.float64)
    offset[0, 3] += 0.02  # TCP off the flange axis: the half turn is not joint 6 alone
    assert not half_turn_symmetric(replace(tool, flange_from_tcp=offset))


def _evaluation(q6: float) -> Evaluation:
    """A five-pose evaluation above the bin on one branch, joint 6 at q6 at every pose."""
    flange_from_tcp = np.asarray(CELL.tool.flange_from_tcp)
    q = np.array([[-0.2, -1.4 + 0.05 * k, 1.6, -1.8, -1.57, q6] for k in range(5)])
    poses = ARM.fk(q) @ flange_from_tcp
    cand = GraspCandidate(0, "box", "g0", "annotated", "parallel", poses[2], 0.04, 0.08, 0.08, 0.9)
    return Evaluation(cand, True, "", "", poses, q, 2, 1.0, 1.0)


def test_quickest_grasp_turns_joint_6_the_short_way_only_for_a_symmetric_tool() -> None:
    home = np.asarray(CELL.home_q, dtype=np.float64)
    flange_from_tcp = np.asarray(CELL.tool.flange_from_tcp)
    ev = _evaluation(2.6)
    out = quickest_grasp(ev, ARM, flange_from_tcp, home, CAPS, True, lambda q: True)
    assert out.q is not None and out.world_from_tcp is not None
    assert abs(out.q[0, 5] - (2.6 - np.pi)) < 1e-12
    np.testing.assert_allclose(out.q[:, :5], ev.q[:, :5])  # type: ignore[index]
    np.testing.assert_allclose(out.world_from_tcp, ev.world_from_tcp @ HALF_TURN, atol=1e-12)
    np.testing.assert_allclose(ARM.fk(out.q) @ flange_from_tcp, out.world_from_tcp, atol=1e-9)
    np.testing.assert_allclose(out.candidate.world_from_tcp, ev.candidate.world_from_tcp @ HALF_TURN, atol=1e-12)
    assert quickest_grasp(ev, ARM, flange_from_tcp, home, CAPS, False, lambda q: True) is ev
    assert quickest_grasp(ev, ARM, flange_from_tcp, home, CAPS, True, lambda q: False) is ev  # the arm would hit
    near = _evaluation(0.3)
    assert quickest_grasp(near, ARM, flange_from_tcp, home, CAPS, True, lambda q: True) is near


def _place(yaw: float, xy: tuple[float, float] = (0.0, -0.45)) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    pose = DOWN.copy()
    pose[:3, :3] = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ pose[:3, :3]
    pose[:2, 3] = xy
    pose[2, 3] = 0.2
    return pose


def _placed(pose: np.ndarray, tcp_from_object: np.ndarray, verts: np.ndarray) -> np.ndarray:
    obj = pose @ tcp_from_object
    return np.sort(np.round(verts @ obj[:3, :3].T + obj[:3, 3], 6), axis=0)


def test_equivalent_place_poses_leave_a_symmetric_part_where_the_planned_pose_does() -> None:
    box = np.asarray(trimesh.creation.box((0.12, 0.05, 0.03)).vertices)
    tcp_from_object = np.eye(4)
    tcp_from_object[:3, 3] = (0.02, 0.0, 0.015)  # grasped 2 cm off the part's centre
    pose = _place(0.3)
    poses = place_poses(pose, tcp_from_object, box, False)
    np.testing.assert_array_equal(poses[0], pose)
    assert len(poses) == 2  # the box's half turn about its own vertical axis; its quarter turns differ
    for p in poses:
        np.testing.assert_allclose(_placed(p, tcp_from_object, box), _placed(pose, tcp_from_object, box), atol=1e-5)
    assert np.linalg.norm(poses[1][:2, 3] - pose[:2, 3]) > 0.03  # the TCP moves: the turn is about the part's axis
    # an L-shaped part has no such symmetry: only the pose itself, and with a free tool turn that turn
    ell = np.vstack([box, box + (0.0, 0.05, 0.0)])[: len(box) + 4]
    assert len(place_poses(pose, tcp_from_object, ell, False)) == 1
    turned = place_poses(pose, tcp_from_object, ell, True)
    assert len(turned) == 2
    np.testing.assert_allclose(turned[1], pose @ HALF_TURN)
    cube = np.asarray(trimesh.creation.box((0.04, 0.04, 0.04)).vertices)
    centred = np.eye(4)
    centred[2, 3] = 0.02
    assert len(place_poses(pose, centred, cube, False)) == 4  # quarter turns of a cube grasped on its axis


def _box_plan(quickest: bool, yaw_deg: float) -> tuple[PickPlan, np.ndarray]:
    """One box in the example bin, turned `yaw_deg` about z; the plan and the box's vertices where it is released."""
    part = Template("box", "box", trimesh.creation.box((0.06, 0.04, 0.03)), shape="box")
    pose = make_pose(rotation_from_rotvec([0.0, 0.0, np.radians(yaw_deg)]), [0.5, 0.05, 0.025])
    fit = TemplateFit(part, pose, 1.0, 0.0, 1.0, 1.0, 0.0, True, instance_id=1)
    plan = plan_pick([fit], [], CELL, PlanOptions(quickest_branches=quickest))
    assert plan.status == "ok" and plan.chosen is not None and plan.trajectory is not None
    release = next(w for w in plan.waypoints if w.name == "place").world_from_tcp
    placed = release @ np.linalg.inv(plan.chosen.candidate.world_from_tcp) @ pose
    verts = np.asarray(part.mesh.vertices) @ placed[:3, :3].T + placed[:3, 3]
    return plan, np.sort(np.round(verts, 5), axis=0)


def test_plan_turns_the_wrist_the_short_way_and_places_the_part_the_same() -> None:
    nearest, placed_nearest = _box_plan(False, 0.0)  # the evaluation's branch turns joint 6 to 2.97 rad
    quick, placed_quick = _box_plan(True, 0.0)
    assert nearest.chosen is not None and quick.chosen is not None
    assert quick.chosen.candidate.grasp_id == nearest.chosen.candidate.grasp_id  # the same grasp, the wrist turned
    assert quick.chosen.q is not None and quick.chosen.world_from_tcp is not None
    flange_from_tcp = np.asarray(CELL.tool.flange_from_tcp)
    cell_arm = ArmModel.from_name(CELL.robot_model, CELL.world_from_base)
    np.testing.assert_allclose(cell_arm.fk(quick.chosen.q) @ flange_from_tcp, quick.chosen.world_from_tcp, atol=1e-9)
    np.testing.assert_allclose(quick.chosen.candidate.world_from_tcp, quick.chosen.world_from_tcp[2], atol=1e-12)
    assert quick.chosen in quick.evaluations
    home = np.asarray(CELL.home_q)
    assert np.abs(quick.waypoints[1].q - home).max() < np.abs(nearest.waypoints[1].q - home).max()
    np.testing.assert_allclose(placed_quick, placed_nearest, atol=2e-4)  # the box lands where it did
    assert quick.trajectory is not None and nearest.trajectory is not None
    assert quick.trajectory.duration_s < nearest.trajectory.duration_s - 1.0  # 1.8 s of wrist turn -> 0.5 s
    check_plan(parse_plan(quick.to_json()), SafetyLimits.from_cell(CELL))


def test_a_grasp_without_a_path_once_turned_is_planned_with_its_own_angles(monkeypatch: pytest.MonkeyPatch) -> None:
    build = plan_module._build_path

    def refuse_turned(ev: Evaluation, *args: Any) -> Any:
        assert ev.q is not None
        if ev.q[0, 5] < 1.0:  # the turned wrist (the box's own grasp turns joint 6 to 2.97 rad)
            raise PlanningError("no path (test)")
        return build(ev, *args)

    monkeypatch.setattr(plan_module, "_build_path", refuse_turned)
    plan, _ = _box_plan(True, 0.0)
    nearest, _ = _box_plan(False, 0.0)
    assert plan.chosen is not None and plan.chosen.q is not None and nearest.chosen is not None
    np.testing.assert_allclose(plan.chosen.q, nearest.chosen.q)  # type: ignore[arg-type]
    assert plan.chosen in plan.evaluations
