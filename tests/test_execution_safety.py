"""SafetyLimits and plan checks: everything outside the limits is refused before sending; dry runs send nothing."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from normpos_grasp.errors import InputError, SafetyViolation
from normpos_grasp.execution import SafetyLimits, check_plan, execute_plan, parse_plan
from normpos_grasp.kinematics.ur_params import dh_forward_kinematics, ur_params

HOME = np.array([0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0])


def _plan(qs: list[np.ndarray], times: np.ndarray | None = None) -> dict[str, object]:
    plan: dict[str, object] = {
        "status": "ok",
        "robot": "ur5e",
        "world_from_base": np.eye(4).tolist(),
        "joint_waypoints": [{"name": f"w{i}", "q": q.tolist()} for i, q in enumerate(qs)],
        "tool": {"flange_from_tcp": np.eye(4).tolist()},
    }
    if times is not None:
        s = (1 - np.cos(np.pi * times / times[-1])) / 2
        traj = qs[0] + np.outer(s, qs[-1] - qs[0])
        plan["trajectory"] = {"samples": [{"t": float(t), "q": q.tolist()} for t, q in zip(times, traj, strict=True)]}
    return plan


def test_joint_limit_violation_names_joint() -> None:
    lim = SafetyLimits.for_model("ur5e")
    q = HOME.copy()
    q[2] = 3.3  # elbow limit is +-pi
    with pytest.raises(SafetyViolation, match="joint 2") as info:
        lim.check_joints(q)
    assert info.value.detail["joint"] == 2


def test_nan_target_refused() -> None:
    with pytest.raises(SafetyViolation, match="finite"):
        SafetyLimits.for_model("ur5e").check_joints([np.nan, 0, 0, 0, 0, 0])


def test_workspace_box_in_base_and_world_frame() -> None:
    lim = SafetyLimits.for_model("ur5e", workspace_min=(-1, -1, 0.05), workspace_max=(1, 1, 1))
    tcp = dh_forward_kinematics(ur_params("ur5e"), HOME)[:3, 3]
    lim.check_joints(HOME)  # home is inside
    low = lim.with_workspace((-1, -1, tcp[2] + 0.01), (1, 1, 1))
    with pytest.raises(SafetyViolation, match="workspace"):
        low.check_joints(HOME)
    # the same box expressed in a world frame where the base stands 0.5 m up
    world_from_base = np.eye(4)
    world_from_base[2, 3] = 0.5
    from dataclasses import replace

    shifted = replace(lim.with_workspace((-1, -1, tcp[2] + 0.49), (1, 1, 2)), box_from_base=world_from_base)
    shifted.check_joints(HOME)


def test_speed_and_accel_caps() -> None:
    lim = SafetyLimits.for_model("ur5e", speed_fraction=0.5, max_joint_accel=2.0)
    lim.check_joint_speed(1.0, 1.0)
    with pytest.raises(SafetyViolation):
        lim.check_joint_speed(2.0, 1.0)
    with pytest.raises(SafetyViolation):
        lim.check_joint_speed(1.0, 3.0)
    with pytest.raises(SafetyViolation):
        lim.check_joint_speed(0.0, 1.0)


@settings(max_examples=25, deadline=None)
@given(st.floats(0.2, 3.0), st.floats(0.05, 1.0))
def test_trajectory_speed_check_matches_finite_differences(duration: float, amplitude: float) -> None:
    lim = SafetyLimits.for_model("ur5e", max_joint_accel=40.0)
    t = np.linspace(0.0, duration, 200)
    q = np.tile(HOME, (200, 1))
    q[:, 0] += amplitude * (1 - np.cos(np.pi * t / duration)) / 2
    peak_speed = float(np.max(np.abs(np.diff(q[:, 0]) / np.diff(t))))
    peak_accel = float(np.max(np.abs(np.diff(np.diff(q[:, 0]) / np.diff(t)) / np.diff(t)[1:])))
    if peak_speed <= lim.max_joint_speed[0] and peak_accel <= lim.max_joint_accel[0]:
        lim.check_trajectory(t, q)
    else:
        with pytest.raises(SafetyViolation):
            lim.check_trajectory(t, q)


def test_trajectory_time_must_increase() -> None:
    lim = SafetyLimits.for_model("ur5e")
    with pytest.raises(SafetyViolation, match="increase"):
        lim.check_trajectory([0.0, 0.1, 0.1], np.tile(HOME, (3, 1)))


def test_dry_run_checks_and_sends_nothing() -> None:
    q1 = HOME + np.array([0.3, 0.1, -0.1, 0.0, 0.0, 0.2])
    plan = _plan([HOME, q1], np.linspace(0.0, 2.0, 101))
    report = execute_plan(None, plan, SafetyLimits.for_model("ur5e"))
    assert report.status == "dry_run" and report.commands_sent == 0 and not report.steps
    assert any("101 samples" in m for m in report.messages)


def test_plan_with_out_of_limit_waypoint_refused() -> None:
    bad = HOME.copy()
    bad[2] = 3.5
    with pytest.raises(SafetyViolation):
        execute_plan(None, _plan([HOME, bad]), SafetyLimits.for_model("ur5e"))


def test_plan_too_fast_refused() -> None:
    q1 = HOME + np.array([1.5, 0, 0, 0, 0, 0])
    with pytest.raises(SafetyViolation, match="speed|acceleration"):
        execute_plan(None, _plan([HOME, q1], np.linspace(0.0, 0.3, 31)), SafetyLimits.for_model("ur5e"))


def test_plan_status_and_robot_checked() -> None:
    with pytest.raises(InputError, match="status"):
        parse_plan({"status": "no_feasible_grasp", "robot": "ur5e", "joint_waypoints": []})
    parsed = parse_plan(_plan([HOME]))
    with pytest.raises(InputError, match="ur10e"):
        check_plan(parsed, SafetyLimits.for_model("ur10e"))
    with pytest.raises(InputError, match="joint_waypoints"):
        parse_plan({"status": "ok", "robot": "ur5e", "joint_waypoints": [{"name": "a", "q": [0, 0]}]})


def test_plan_format_and_tool_openings_checked() -> None:
    """Another plan format, and a tool opening that is no length or more than the tool's stroke, are refused
    before anything connects; a plan without `format` (hand-written) is read by its fields."""
    parse_plan({**_plan([HOME]), "format": "normpos-grasp/plan@1"})
    with pytest.raises(InputError, match="plan.format"):
        parse_plan({**_plan([HOME]), "format": "normpos-grasp/plan@2"})
    for bad in (-0.5, float("inf"), float("nan"), "85mm", True):
        with pytest.raises(InputError, match="plan.tool.opening_m"):
            parse_plan({**_plan([HOME]), "tool": {"flange_from_tcp": np.eye(4).tolist(), "opening_m": bad}})
    too_wide = {**_plan([HOME]), "tool": {"stroke_m": 0.085}, "grasp": {"opening_m": 0.12}}
    with pytest.raises(InputError, match="stroke"):
        parse_plan(too_wide)
    parse_plan({**too_wide, "grasp": {"opening_m": 0.06}})


def test_trajectory_must_pass_through_waypoints() -> None:
    q1 = HOME + np.array([0.3, 0, 0, 0, 0, 0])
    plan = _plan([HOME, q1], np.linspace(0.0, 2.0, 101))
    plan["joint_waypoints"].insert(1, {"name": "detour", "q": (HOME + 0.2).tolist()})  # type: ignore[attr-defined]
    with pytest.raises(SafetyViolation, match="detour"):
        execute_plan(None, plan, SafetyLimits.for_model("ur5e"))
