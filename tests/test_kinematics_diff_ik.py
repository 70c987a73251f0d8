"""Differential IK through mink: converges to analytic-IK targets, Cartesian moves stay on the line, failures
raise NoIKSolution(not_converged) carrying the problem, limits are explicit lists."""

from __future__ import annotations

import math

import mink
import numpy as np
import pytest

from normpos_grasp.errors import NoIKSolution
from normpos_grasp.kinematics import Gripper, Robot
from normpos_grasp.kinematics.diff_ik import DiffIK, DiffIKNotConverged, DiffIKOptions, cartesian_path, solve_pose

Q0 = np.array([0.3, -1.2, 1.4, -1.7, -1.5, 0.2])


def test_solve_pose_reaches_a_nearby_target() -> None:
    robot = Robot.load("ur5e")
    q_goal = Q0 + np.array([0.2, -0.15, 0.1, 0.2, -0.1, 0.3])
    result = solve_pose(robot, Q0, robot.fk(q_goal))
    assert result.converged
    assert result.position_error_m <= 1e-4 and result.orientation_error_rad <= math.radians(0.1)
    np.testing.assert_allclose(robot.fk(result.q)[:3, 3], robot.fk(q_goal)[:3, 3], atol=1e-4)


@pytest.mark.parametrize("name", ["ur3e", "ur10e"])
def test_cartesian_path_is_straight_and_ends_at_the_goal(name: str) -> None:
    robot = Robot.load(name)
    start = robot.fk(Q0)
    goal = start.copy()
    goal[:3, 3] += (0.05, -0.08, 0.04)
    path = cartesian_path(robot, Q0, goal, step_m=0.005)
    assert path.shape[1] == 6 and path.shape[0] >= 20
    np.testing.assert_allclose(path[0], Q0)
    pos = robot.fk_batch(path)[:, :3, 3]
    direction = (goal[:3, 3] - start[:3, 3]) / np.linalg.norm(goal[:3, 3] - start[:3, 3])
    rel = pos - start[:3, 3]
    off_line = np.linalg.norm(rel - np.outer(rel @ direction, direction), axis=1)
    assert off_line.max() < 2e-4
    assert np.all(np.diff(rel @ direction) > 0)  # monotone progress
    assert np.linalg.norm(pos[-1] - goal[:3, 3]) < 1e-4
    assert robot.within_limits(path).all()


def test_tcp_straight_line_with_a_gripper() -> None:
    robot = Robot.load("ur5e")
    tool = Gripper.load("2f85")
    start_tcp = robot.fk(Q0) @ tool.flange_from_tcp
    goal = start_tcp.copy()
    goal[:3, 3] += start_tcp[:3, 2] * 0.06  # approach along the tool axis
    ik = DiffIK(robot, DiffIKOptions(), flange_from_tcp=tool.flange_from_tcp)
    path = ik.cartesian_path(Q0, goal, step_m=0.01)
    tcp = robot.fk_batch(path) @ tool.flange_from_tcp
    np.testing.assert_allclose(tcp[-1][:3, 3], goal[:3, 3], atol=1e-4)
    np.testing.assert_allclose(tcp[:, :3, :3], np.broadcast_to(start_tcp[:3, :3], (len(path), 3, 3)), atol=2e-3)


def test_unreachable_target_raises_with_the_problem() -> None:
    robot = Robot.load("ur5e")
    far = robot.fk(Q0)
    far[:3, 3] = (1.5, 0.0, 0.2)
    with pytest.raises(NoIKSolution) as exc:
        solve_pose(robot, Q0, far, DiffIKOptions(max_iterations=40))
    err = exc.value
    assert isinstance(err, DiffIKNotConverged) and err.reason == "not_converged"
    np.testing.assert_allclose(err.problem.q_start, Q0)
    assert err.result.position_error_m > 0.3 and not err.result.converged
    with pytest.raises(DiffIKNotConverged) as exc2:
        cartesian_path(robot, Q0, far, step_m=0.02, options=DiffIKOptions(max_iterations=40))
    assert exc2.value.problem.waypoint > 0


def test_limits_are_explicit_and_collision_pairs_build() -> None:
    robot = Robot.load("ur5e")
    none = DiffIK(robot, DiffIKOptions(use_configuration_limit=False, use_velocity_limit=False))
    assert none.limits == []  # never None: mink would add a ConfigurationLimit
    full = DiffIK(robot, DiffIKOptions(collision_pairs=((("wrist_3",), ("upper_arm", "base")),)))
    kinds = {type(lim) for lim in full.limits}
    assert kinds == {mink.ConfigurationLimit, mink.VelocityLimit, mink.CollisionAvoidanceLimit}
    goal = robot.fk(Q0)
    goal[:3, 3] += (0.0, 0.0, 0.05)
    path = full.cartesian_path(Q0, goal, step_m=0.01)
    np.testing.assert_allclose(robot.fk(path[-1])[:3, 3], goal[:3, 3], atol=1e-4)


def test_solve_without_configuration_limit_wraps_into_limits() -> None:
    robot = Robot.load("ur5e")
    start = np.array([6.0, -1.2, 1.4, -1.7, -1.5, 6.1])  # near the +2 pi limits
    goal_q = start + np.array([0.5, 0.1, 0.0, 0.0, 0.1, 0.4])  # beyond them: reachable as goal_q - 2 pi
    result = solve_pose(robot, start, robot.fk(goal_q), DiffIKOptions(use_configuration_limit=False))
    assert robot.within_limits(result.q)
    np.testing.assert_allclose(robot.fk(result.q)[:3, 3], robot.fk(goal_q)[:3, 3], atol=1e-4)
