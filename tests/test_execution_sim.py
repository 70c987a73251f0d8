"""SimDriver: the guarded driver on the in-process arm model; faults latch and nothing is sent until resume()."""

from __future__ import annotations

import threading
from collections.abc import Iterator

import numpy as np
import pytest

from normpos_grasp.errors import ConnectionLost, DriverFault, EmergencyStop, ProtectiveStop, SafetyViolation
from normpos_grasp.execution import GripperIO, SafetyLimits, SimDriver, execute_plan

HOME = np.array([0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0])


@pytest.fixture()
def sim() -> Iterator[SimDriver]:
    drv = SimDriver(SafetyLimits.for_model("ur5e"), GripperIO(grip_detect_input=3), time_scale=8.0, unlock_delay_s=0.2)
    drv.connect()
    yield drv
    drv.shutdown()


def test_move_joints_path_reaches_goal(sim: SimDriver) -> None:
    q1 = HOME + np.array([0.3, 0.1, -0.1, 0.0, 0.1, 0.2])
    q2 = q1 + np.array([0.2, 0.0, 0.0, 0.1, 0.0, 0.0])
    st = sim.move_joints([q1, q2], 2.0, 4.0)
    assert np.max(np.abs(st.q - q2)) < 1e-9


def test_follow_trajectory_ends_on_last_sample(sim: SimDriver) -> None:
    t = np.linspace(0.0, 0.8, 41)
    q = HOME + np.outer((1 - np.cos(np.pi * t / 0.8)) / 2, [0.2, 0, 0, 0, 0, 0.1])
    st = sim.follow_trajectory(t, q)
    assert np.max(np.abs(st.q - q[-1])) < 1e-3


def test_out_of_limit_target_sends_nothing(sim: SimDriver) -> None:
    bad = HOME.copy()
    bad[2] = 3.3
    before = sim.commands_sent
    with pytest.raises(SafetyViolation):
        sim.move_joints([HOME + 0.1, bad], 1.0, 1.0)
    assert sim.commands_sent == before and not sim.arm.moving
    assert sim.fault is None  # a refused target is not a controller fault


def test_protective_stop_latches_until_resume(sim: SimDriver) -> None:
    goal = HOME + np.array([1.0, 0, 0, 0, 0, 0])
    threading.Timer(0.05, sim.inject_protective_stop).start()
    with pytest.raises(ProtectiveStop):
        sim.move_joints([goal], 0.5, 1.0)
    sent = sim.commands_sent
    with pytest.raises(DriverFault, match="resume"):
        sim.move_joints([HOME], 0.5, 1.0)
    assert sim.commands_sent == sent
    with pytest.raises(ProtectiveStop, match="unlock"):
        sim.resume()  # still stopped: not unlocked yet
    import time

    time.sleep(0.25)
    assert sim.unlock_protective_stop()
    sim.resume()
    st = sim.move_joints([goal], 2.0, 4.0)
    assert np.max(np.abs(st.q - goal)) < 1e-9


def test_emergency_stop(sim: SimDriver) -> None:
    threading.Timer(0.05, sim.inject_emergency_stop).start()
    with pytest.raises(EmergencyStop):
        sim.move_joints([HOME + np.array([1.0, 0, 0, 0, 0, 0])], 0.5, 1.0)
    with pytest.raises(EmergencyStop):
        sim.resume()
    sim.release_emergency_stop()
    sim.resume()


def test_link_loss_stops_and_requires_resume(sim: SimDriver) -> None:
    threading.Timer(0.05, sim.inject_link_loss).start()
    with pytest.raises(ConnectionLost):
        sim.move_joints([HOME + np.array([1.0, 0, 0, 0, 0, 0])], 0.5, 1.0)
    import time

    time.sleep(0.2)
    assert not sim.arm.moving  # stopped by the link-loss path, not left running
    with pytest.raises(DriverFault):
        sim.move_joints([HOME], 0.5, 1.0)
    sim.restore_link()
    sim.resume()
    sim.move_joints([HOME], 2.0, 4.0)


def test_gripper_outputs_and_grip_detect(sim: SimDriver) -> None:
    sim.gripper_close()
    assert sim.state().digital_out & 1 and not sim.state().digital_out & 2
    assert not sim.grip_detected()
    sim.set_digital_input(3, True)
    assert sim.grip_detected()
    sim.gripper_open()
    assert not sim.state().digital_out & 1 and sim.state().digital_out & 2


def test_execute_plan_on_sim(sim: SimDriver) -> None:
    q1 = HOME + np.array([0.3, 0.0, 0.1, 0.0, 0.0, 0.0])
    t = np.linspace(0.0, 1.0, 51)
    traj = HOME + np.outer((1 - np.cos(np.pi * t)) / 2, q1 - HOME)
    plan = {
        "status": "ok",
        "robot": "ur5e",
        "joint_waypoints": [{"name": "home", "q": HOME.tolist()}, {"name": "grasp", "q": q1.tolist()}],
        "trajectory": {"samples": [{"t": float(a), "q": b.tolist()} for a, b in zip(t, traj, strict=True)]},
    }
    sim.set_digital_input(3, True)
    report = execute_plan(sim, plan, sim.limits, dry_run=False)
    assert report.status == "executed" and report.final_error_rad is not None and report.final_error_rad < 1e-3
    assert report.grip_detected is True
    assert [s.kind for s in report.steps] == ["gripper_open", "trajectory", "gripper_close"]
