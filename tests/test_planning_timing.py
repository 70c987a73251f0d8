"""Ruckig timing of planned paths (planning.timing.time_path): time-optimality against the closed-form jerk-limited
profile, caps on the samples (the execution safety checks), exact joint edges and Cartesian lines, blends through
waypoints only where the path allows them, and the planner's plans checked as execution checks them."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import trimesh

from normpos_grasp.cell import CellConfig, load_cell
from normpos_grasp.cell.stream import check_stream, stream_cuts
from normpos_grasp.errors import SafetyViolation
from normpos_grasp.execution.driver import DriverOptions
from normpos_grasp.execution.plan import check_plan, parse_plan
from normpos_grasp.execution.safety import SafetyLimits
from normpos_grasp.geometry import make_pose
from normpos_grasp.kinematics import IKOptions, Robot
from normpos_grasp.planning import plan_pick
from normpos_grasp.planning.plan import PlanOptions
from normpos_grasp.planning.timing import PathPiece, TimingOptions, time_path
from normpos_grasp.records.plan import Trajectory
from normpos_grasp.records.template import Template, TemplateFit

EXAMPLES = Path(__file__).resolve().parents[1] / "examples" / "cells"
VMAX, AMAX = np.full(6, 2.5), np.full(6, 5.0)
LOWER, UPPER = np.full(6, -2 * math.pi), np.full(6, 2 * math.pi)
OPTS = TimingOptions()
SHARE = OPTS.cap_share
ROBOT = Robot.load("ur5e")
TOOL_DOWN = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])
NEAR = np.array([0.0, -1.2, 1.4, -1.8, -1.57, 0.0])


def _limits() -> SafetyLimits:
    lim = SafetyLimits.for_model("ur5e", max_joint_accel=float(AMAX[0]))
    return SafetyLimits(
        "ur5e", lim.q_lower, lim.q_upper, VMAX.copy(), AMAX.copy(), lim.workspace_min, lim.workspace_max
    )


def _jerk(traj: Trajectory) -> np.ndarray:
    """Third finite differences where three consecutive intervals are regular (a weighted mean of the true jerk)."""
    uniform = np.isclose(np.diff(traj.t), OPTS.dt_s, rtol=0, atol=1e-9)
    i = np.flatnonzero(uniform[:-2] & uniform[1:-1] & uniform[2:])
    q = traj.q
    return (q[i + 3] - 3 * q[i + 2] + 3 * q[i + 1] - q[i]) / OPTS.dt_s**3


def _line_samples(start: np.ndarray, end: np.ndarray, step: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """UR5e joint samples (K, 6) of the straight flange line start -> end (tool down), 1 cm apart, one branch."""
    n = max(int(math.ceil(np.linalg.norm(end - start) / step)), 1)
    tcp = start + np.linspace(0.0, 1.0, n + 1)[:, None] * (end - start)
    qs, near = [], NEAR
    for p in tcp:
        sol = ROBOT.ik(make_pose(TOOL_DOWN, p), near, IKOptions(all_branches=False))
        near = sol[0]
        qs.append(near)
    return np.array(qs), tcp


def _flange(q: np.ndarray) -> np.ndarray:
    return ROBOT.fk_batch(q)[:, :3, 3]


def test_rest_to_rest_edge_is_time_optimal_and_exact() -> None:
    a = np.array([0.0, -1.5, 1.5, -1.5, -1.5, 0.0])
    b = a + np.array([2.0, -0.6, 0.4, 0.0, 0.3, -1.0])  # joint 0 leads (2 rad)
    traj = time_path([PathPiece(np.stack([a, b]), rest_after=True)], VMAX, AMAX, LOWER, UPPER, options=OPTS)
    v, acc, j = 2.5 * SHARE, 5.0 * SHARE, OPTS.jerk_rad_s3 * SHARE
    # closed-form duration of the jerk-limited rest-to-rest profile reaching cruise speed: D/v + v/a + a/j
    assert traj.duration_s == pytest.approx(2.0 / v + v / acc + acc / j, rel=1e-6)
    direction = (b - a) / np.linalg.norm(b - a)
    rel = traj.q - a
    assert np.abs(rel - np.outer(rel @ direction, direction)).max() < 1e-12  # on the straight edge
    np.testing.assert_array_equal(traj.q[0], a)
    np.testing.assert_array_equal(traj.q[-1], b)
    _limits().check_trajectory(traj.t, traj.q)  # speed and acceleration caps by finite differences
    assert np.abs(_jerk(traj)).max() <= OPTS.jerk_rad_s3 * (1 + 1e-6)
    assert np.abs(traj.qd[-1]).max() == pytest.approx(0.0, abs=1e-9)


def test_cartesian_line_stays_on_its_line_within_the_tcp_caps() -> None:
    q, tcp = _line_samples(np.array([0.45, 0.1, 0.35]), np.array([0.45, 0.1, 0.15]))
    traj = time_path([PathPiece(q, tcp, rest_after=True)], VMAX, AMAX, LOWER, UPPER, 0.4, 2.0, OPTS)
    p = _flange(traj.q)
    u = (tcp[-1] - tcp[0]) / np.linalg.norm(tcp[-1] - tcp[0])
    rel = p - tcp[0]
    along = rel @ u
    assert np.linalg.norm(rel - np.outer(along, u), axis=1).max() < 2e-6  # m: the spline through 1 cm IK samples
    assert np.all(np.diff(along) >= -1e-9)  # never backwards
    speed = np.linalg.norm(np.diff(p, axis=0), axis=1) / np.diff(traj.t)
    assert speed.max() <= 0.4 * (1 + 1e-3)
    _limits().check_trajectory(traj.t, traj.q)
    assert traj.duration_s >= 0.2 / 0.4  # m / (m/s)


def test_collinear_lines_pass_their_common_waypoint_at_speed() -> None:
    q1, tcp1 = _line_samples(np.array([0.45, 0.1, 0.35]), np.array([0.45, 0.1, 0.25]))
    q2, tcp2 = _line_samples(np.array([0.45, 0.1, 0.25]), np.array([0.45, 0.1, 0.15]))
    q2 = q2 + 2 * math.pi * np.round((q1[-1] - q2[0]) / (2 * math.pi))
    pieces = [PathPiece(q1, tcp1), PathPiece(q2, tcp2, rest_after=True)]
    blended = time_path(pieces, VMAX, AMAX, LOWER, UPPER, 0.4, 2.0, OPTS)
    stopped = time_path(pieces, VMAX, AMAX, LOWER, UPPER, 0.4, 2.0, TimingOptions(blend=False))
    for traj in (blended, stopped):
        gap = np.abs(traj.q - q1[-1]).max(axis=1)
        assert gap.min() == 0.0  # the common waypoint is a sample (execution splits the stream there)
        _limits().check_trajectory(traj.t, traj.q)
    k = int(np.argmin(np.abs(blended.q - q1[-1]).max(axis=1)))
    tcp_speed = np.linalg.norm(np.diff(_flange(blended.q[k - 1 : k + 2]), axis=0), axis=1) / np.diff(
        blended.t[k - 1 : k + 2]
    )
    assert tcp_speed.min() > 0.3  # m/s: passing, not stopping
    k = int(np.argmin(np.abs(stopped.q - q1[-1]).max(axis=1)))
    assert np.abs(stopped.qd[k]).max() < 1e-9
    assert blended.duration_s < stopped.duration_s - 0.1


def test_blend_into_a_line_is_checked_and_falls_back_to_a_stop() -> None:
    q_line, tcp = _line_samples(np.array([0.45, 0.1, 0.30]), np.array([0.45, 0.1, 0.15]))
    home = q_line[0] + np.array([0.8, -0.3, 0.2, 0.1, 0.0, 0.5])
    checked: list[np.ndarray] = []

    def free(qs: np.ndarray) -> bool:
        checked.append(qs)
        return True

    edge = np.stack([home, q_line[0]])
    blended = time_path(
        [PathPiece(edge, None, False, free), PathPiece(q_line, tcp, rest_after=True)],
        VMAX,
        AMAX,
        LOWER,
        UPPER,
        0.4,
        2.0,
        OPTS,
    )
    assert checked, "the blended transfer was not collision-checked"
    steps = np.abs(np.diff(checked[0], axis=0)).max(axis=1)
    assert steps.max() <= OPTS.check_step_rad + 1e-9  # checked as densely as the planner checks its edges
    k = int(np.argmin(np.abs(blended.q - q_line[0]).max(axis=1)))
    assert np.abs(blended.q[k] - q_line[0]).max() == 0.0
    assert np.abs(blended.qd[k]).max() > 0.1  # rad/s: entering the line at speed
    _limits().check_trajectory(blended.t, blended.q)
    # the TCP is on the line after the junction, as before
    p = _flange(blended.q[k:])
    u = (tcp[-1] - tcp[0]) / np.linalg.norm(tcp[-1] - tcp[0])
    rel = p - tcp[0]
    assert np.linalg.norm(rel - np.outer(rel @ u, u), axis=1).max() < 2e-6

    blocked = time_path(
        [PathPiece(edge, None, False, lambda qs: False), PathPiece(q_line, tcp, rest_after=True)],
        VMAX,
        AMAX,
        LOWER,
        UPPER,
        0.4,
        2.0,
        OPTS,
    )
    k = int(np.argmin(np.abs(blocked.q - q_line[0]).max(axis=1)))
    assert np.abs(blocked.qd[k]).max() < 1e-9  # rests at the junction
    direction = (q_line[0] - home) / np.linalg.norm(q_line[0] - home)
    rel = blocked.q[: k + 1] - home
    assert np.abs(rel - np.outer(rel @ direction, direction)).max() < 1e-12  # and follows the checked edge
    assert blocked.duration_s > blended.duration_s


def test_short_line_lowers_its_passing_speeds() -> None:
    q1, tcp1 = _line_samples(np.array([0.45, 0.1, 0.30]), np.array([0.45, 0.1, 0.295]), 0.0025)
    q2, tcp2 = _line_samples(np.array([0.45, 0.1, 0.295]), np.array([0.45, 0.1, 0.15]))
    q2 = q2 + 2 * math.pi * np.round((q1[-1] - q2[0]) / (2 * math.pi))
    home = q1[0] + np.array([0.5, -0.2, 0.1, 0.0, 0.0, 0.3])
    pieces = [
        PathPiece(np.stack([home, q1[0]]), None, False, lambda qs: True),
        PathPiece(q1, tcp1),  # 5 mm: too short to pass both ends at cruise speed
        PathPiece(q2, tcp2, rest_after=True),
    ]
    traj = time_path(pieces, VMAX, AMAX, LOWER, UPPER, 0.4, 2.0, OPTS)
    k0 = int(np.argmin(np.abs(traj.q - q1[0]).max(axis=1)))
    along = (_flange(traj.q[k0:]) - tcp1[0]) @ np.array([0.0, 0.0, -1.0])
    assert np.all(np.diff(along) >= -1e-9)  # the TCP never moves back up the line
    _limits().check_trajectory(traj.t, traj.q)


def test_a_retry_reuses_the_blends_it_left_unchanged() -> None:
    """A blocked blend late in the path lowers its passing speeds and the profiles are recomputed; the first
    transfer's speeds stay as they were, so its blend (and its collision check) is taken as found, not redone."""
    q_line, tcp = _line_samples(np.array([0.45, 0.1, 0.30]), np.array([0.45, 0.1, 0.15]))
    home = q_line[0] + np.array([0.8, -0.3, 0.2, 0.1, 0.0, 0.5])
    away = q_line[-1] + np.array([-0.6, 0.2, -0.1, 0.0, 0.3, 0.0])
    first: list[np.ndarray] = []
    second: list[np.ndarray] = []

    def free_first(qs: np.ndarray) -> bool:
        first.append(qs)
        return True

    def blocked(qs: np.ndarray) -> bool:
        second.append(qs)
        return False

    pieces = [
        PathPiece(np.stack([home, q_line[0]]), None, False, free_first),
        PathPiece(q_line, tcp),
        PathPiece(np.stack([q_line[-1], away]), None, True, blocked),
    ]
    traj = time_path(pieces, VMAX, AMAX, LOWER, UPPER, 0.4, 2.0, OPTS)
    assert len(second) == 1  # the blocked blend was tried, then the arm rests at the line's end
    assert len(first) == 1  # the retry reused the first blend instead of checking it again
    k0 = int(np.argmin(np.abs(traj.q - q_line[0]).max(axis=1)))
    k1 = int(np.argmin(np.abs(traj.q - q_line[-1]).max(axis=1)))
    assert np.abs(traj.qd[k0]).max() > 0.1  # still entering the line at speed
    assert np.abs(traj.qd[k1]).max() < 1e-9  # and resting before the blocked transfer
    _limits().check_trajectory(traj.t, traj.q)


def test_joint_edges_pass_their_common_via_at_speed_only_where_the_blend_is_clear() -> None:
    """Two joint edges (an RRT transfer's vias): with `free` tests the arm passes the via at speed (a 6-DoF blend
    through the exact via, collision-checked as densely as the planner's edges); where the blended samples leave
    the edges into a collision (a corner cut), it rests at the via and follows the checked edges exactly."""
    a = np.array([0.0, -1.5, 1.5, -1.5, -1.5, 0.0])
    via = a + np.array([1.2, 0.4, -0.3, 0.0, 0.2, 0.0])
    b = via + np.array([0.9, 0.5, -0.4, 0.3, 0.0, 0.0])  # the same turning sense for the moving joints

    def on_edges(qs: np.ndarray) -> bool:  # the corner at the via is an obstacle: only the edges are free
        for p0, p1 in ((a, via), (via, b)):
            d = (p1 - p0) / np.linalg.norm(p1 - p0)
            rel = qs - p0
            off = np.linalg.norm(rel - np.outer(rel @ d, d), axis=1)
            if np.all(off < 1e-9):
                return True
        return False

    checked: list[np.ndarray] = []

    def free(qs: np.ndarray) -> bool:
        checked.append(qs)
        return True

    edges = [np.stack([a, via]), np.stack([via, b])]
    blended = time_path(
        [PathPiece(edges[0], None, False, free), PathPiece(edges[1], None, True, free)],
        VMAX, AMAX, LOWER, UPPER, options=OPTS,
    )  # fmt: skip
    corner = time_path(
        [PathPiece(edges[0], None, False, on_edges), PathPiece(edges[1], None, True, on_edges)],
        VMAX, AMAX, LOWER, UPPER, options=OPTS,
    )  # fmt: skip
    stopped = time_path(
        [PathPiece(edges[0], None, False, free), PathPiece(edges[1], None, True, free)],
        VMAX, AMAX, LOWER, UPPER, options=TimingOptions(blend=False),
    )  # fmt: skip
    for traj in (blended, corner, stopped):
        k = int(np.argmin(np.abs(traj.q - via).max(axis=1)))
        np.testing.assert_array_equal(traj.q[k], via)  # the via is a sample (execution splits the stream there)
        _limits().check_trajectory(traj.t, traj.q)
    k = int(np.argmin(np.abs(blended.q - via).max(axis=1)))
    assert np.abs(blended.qd[k]).max() > 0.3  # rad/s: passing, not stopping
    assert checked and max(np.abs(np.diff(c, axis=0)).max() for c in checked) <= OPTS.check_step_rad + 1e-9
    assert blended.duration_s < stopped.duration_s - 0.1
    # the corner: the blended samples would leave the edges, so the arm rests at the via and stays on the edges
    k = int(np.argmin(np.abs(corner.q - via).max(axis=1)))
    assert np.abs(corner.qd[k]).max() < 1e-9
    assert on_edges(corner.q[: k + 1]) and on_edges(corner.q[k:])
    assert corner.duration_s == pytest.approx(stopped.duration_s, abs=1e-9)


def _box_plan(timing: TimingOptions) -> tuple[dict, CellConfig]:
    cell = load_cell(EXAMPLES / "ur5e_bin_parallel.yaml")
    part = Template("box", "box", trimesh.creation.box((0.06, 0.04, 0.03)), shape="box")
    fit = TemplateFit(part, make_pose(None, [0.5, 0.05, 0.025]), 1.0, 0.0, 1.0, 1.0, 0.0, True, instance_id=1)
    plan = plan_pick([fit], [], cell, PlanOptions(timing=timing))
    assert plan.status == "ok" and plan.trajectory is not None
    return plan.to_json(), cell


def test_planned_trajectory_passes_the_execution_checks_and_stops_at_the_gripper() -> None:
    doc, cell = _box_plan(TimingOptions())
    before, _ = _box_plan(TimingOptions(method="trapezoid"))
    limits = SafetyLimits.from_cell(cell)
    parsed = parse_plan(doc)
    check_plan(parsed, limits)  # every sample: joint limits, workspace, speed and acceleration caps
    assert parsed.traj_t is not None and parsed.traj_q is not None
    qd = np.diff(parsed.traj_q, axis=0) / np.diff(parsed.traj_t)[:, None]
    for name in ("grasp", "place"):  # the gripper acts there: the arm is at rest
        q = parsed.q[parsed.names.index(name)]
        k = int(np.argmin(np.abs(parsed.traj_q - q).max(axis=1)))
        assert np.abs(parsed.traj_q[k] - q).max() < 1e-8
        assert np.abs(qd[k - 1]).max() < 0.05 and np.abs(qd[k]).max() < 0.05  # rad/s over one sample
    assert doc["trajectory"]["duration_s"] < before["trajectory"]["duration_s"]


def _streamed(doc: dict, limits: SafetyLimits) -> None:
    """Check the servo commands execution streams for plan.json `doc` as the driver does before sending: pieces
    split where the gripper acts (home -> grasp -> place -> post_place, `cell.stream.stream_cuts`), each a cubic
    spline through its samples every `DriverOptions().stream_period_s` (`cell.stream.check_stream`)."""
    parsed = parse_plan(doc)
    t, q = parsed.traj_t, parsed.traj_q
    assert t is not None and q is not None
    cuts = stream_cuts(q, parsed.names, parsed.q, ("grasp", "place"))
    check_stream(t, q, cuts, limits, DriverOptions().stream_period_s)


def test_the_default_jerk_cap_keeps_the_streamed_commands_within_the_caps() -> None:
    """The planner's jerk cap is its own (UR publishes none) but the servo stream bounds it: the spline execution
    streams through the 20 ms samples overshoots sharp acceleration corners. At the default cap this plan's
    commands pass the driver's check as they are (no re-timing: the trajectory is the jerk-100 one)."""
    doc, cell = _box_plan(TimingOptions())
    limits = SafetyLimits.from_cell(cell)
    check_plan(parse_plan(doc), limits)
    _streamed(doc, limits)


def _samples(doc: dict) -> np.ndarray:
    return np.array([[s["t"], *s["q"]] for s in doc["trajectory"]["samples"]])


def test_a_plan_whose_stream_the_driver_would_refuse_is_retimed_with_the_jerk_cap_halved(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Timed at twice the default jerk cap this path's samples are within the caps but its streamed commands are
    not (joint 0 at 5.10 of 5 rad/s^2; the driver would refuse the plan): the planner re-times it at the halved
    cap, where they pass, so the plan is the default-jerk plan, sample for sample."""
    import normpos_grasp.planning.plan as plan_module

    outcomes: list[str] = []
    check = plan_module.check_stream

    def recorded(*args: object, **kwargs: object) -> None:
        try:
            check(*args, **kwargs)  # type: ignore[arg-type]
        except SafetyViolation as exc:
            outcomes.append(str(exc))
            raise
        outcomes.append("passed")

    default, cell = _box_plan(TimingOptions())
    limits = SafetyLimits.from_cell(cell)
    monkeypatch.setattr(plan_module, "check_stream", recorded)
    sharp, _ = _box_plan(TimingOptions(jerk_rad_s3=2.0 * OPTS.jerk_rad_s3))
    assert len(outcomes) == 2 and "streamed commands" in outcomes[0] and outcomes[1] == "passed"
    check_plan(parse_plan(sharp), limits)
    _streamed(sharp, limits)  # the driver takes every piece
    np.testing.assert_array_equal(_samples(sharp), _samples(default))


def test_a_stream_over_the_caps_at_the_default_jerk_is_retimed_or_refused() -> None:
    """With 99 % of the caps planned (1 % left for the spline's overshoot) this path's streamed commands exceed the
    acceleration cap at the default jerk (joint 0 at 1.011 of the cap) and at its half (1.0006): the planner goes
    down to the floor, 25 rad/s^3, where they pass, and returns that plan; with the floor at 50 no timing of that
    grasp passes: it is rejected ('path_stream_joint_accel'), never handed to execution, and the next grasp is
    planned (its stream passes at 50)."""
    tight = TimingOptions(cap_share=0.99)
    cell = load_cell(EXAMPLES / "ur5e_bin_parallel.yaml")
    limits = SafetyLimits.from_cell(cell)
    part = Template("box", "box", trimesh.creation.box((0.06, 0.04, 0.03)), shape="box")
    fit = TemplateFit(part, make_pose(None, [0.5, 0.05, 0.025]), 1.0, 0.0, 1.0, 1.0, 0.0, True, instance_id=1)
    doc, _ = _box_plan(tight)
    check_plan(parse_plan(doc), limits)
    _streamed(doc, limits)
    floor, _ = _box_plan(replace(tight, jerk_rad_s3=25.0))
    np.testing.assert_array_equal(_samples(doc), _samples(floor))  # timed at the floor
    default, _ = _box_plan(TimingOptions())
    assert doc["trajectory"]["duration_s"] > default["trajectory"]["duration_s"]  # the softer corners cost time
    refused = plan_pick([fit], [], cell, PlanOptions(timing=replace(tight, stream_jerk_floor_rad_s3=50.0)))
    assert refused.counts.get("path_stream_joint_accel", 0) == 1
    assert not [r for r in refused.counts if r.startswith("path_cell")]  # the samples passed: only the stream failed
    assert refused.status == "ok" and refused.chosen is not None
    assert refused.chosen.candidate.grasp_id != doc["grasp"]["id"]  # another grasp than the one timed at 25
    _streamed(refused.to_json(), limits)


def test_the_planner_checks_the_stream_the_driver_sends() -> None:
    """The planner and the driver stream with the same function at the same period and cut a plan at the same
    waypoints; `check_stream` refuses what the driver refuses."""
    from normpos_grasp.cell import stream
    from normpos_grasp.execution import driver
    from normpos_grasp.execution.plan import ExecuteOptions
    from normpos_grasp.planning.plan import STREAM_CUTS

    assert driver.stream_samples is stream.stream_samples
    assert DriverOptions().stream_period_s == OPTS.stream_period_s == stream.STREAM_PERIOD_S
    assert set(STREAM_CUTS) == set(ExecuteOptions().close_at) | set(ExecuteOptions().open_at)
    doc, cell = _box_plan(TimingOptions())
    limits = SafetyLimits.from_cell(cell)
    parsed = parse_plan(doc)
    t, q = parsed.traj_t, parsed.traj_q
    assert t is not None and q is not None
    cuts = [0] + [int(np.argmin(np.abs(q - parsed.q[parsed.names.index(n)]).max(axis=1))) for n in STREAM_CUTS]
    cuts.append(len(t) - 1)
    stream.check_stream(t, q, cuts, limits)
    sharper = replace(limits, max_joint_accel=limits.max_joint_accel * 0.9)
    with pytest.raises(SafetyViolation, match="streamed commands"):
        stream.check_stream(t, q, cuts, sharper)
