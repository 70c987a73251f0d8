"""The real ur_rtde 1.6.5 client (through RtdeDriver) against the loopback UR controller in a subprocess.

One emulator per test module on its own loopback address (ports are fixed, so parallel runs use distinct
127.x addresses). No timing assertions: waits are generous and only outcomes are checked.
"""

from __future__ import annotations

import os
import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import rtde_control  # noqa: F401  (a hard dependency: imported, never skipped)

from normpos_grasp.errors import ConnectionLost, DriverFault, ProtectiveStop, SafetyViolation
from normpos_grasp.execution import DriverOptions, RtdeDriver, SafetyLimits, execute_plan
from normpos_grasp.sim.ur_emulator import EmulatorProcess

HOST = f"127.{100 + os.getpid() % 100}.{os.getpid() // 100 % 250 + 1}.7"
HOME = np.array([0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0])
EXAMPLES = Path(__file__).resolve().parents[1] / "examples" / "cells"


def _state(emu: EmulatorProcess) -> dict[str, str]:
    reply = emu.emu("state")
    return dict(part.split("=", 1) for part in reply.split()[2:] if "=" in part)


@pytest.fixture(scope="module")
def emu(tmp_path_factory: pytest.TempPathFactory) -> Iterator[EmulatorProcess]:
    log = tmp_path_factory.mktemp("emu") / "emulator.log"
    with EmulatorProcess(HOST, "ur5e", ready_timeout_s=60.0, log_path=log) as proc:
        proc.emu("unlock_delay", "1.0")
        yield proc


@pytest.fixture(scope="module")
def driver(emu: EmulatorProcess) -> Iterator[RtdeDriver]:
    drv = RtdeDriver(HOST, SafetyLimits.for_model("ur5e"), options=DriverOptions(stale_state_s=1.0))
    drv.connect()
    yield drv
    drv.disconnect()


def _healthy(driver: RtdeDriver, emu: EmulatorProcess) -> None:
    """Bring the driver back to a clean state after a fault test."""
    deadline = time.monotonic() + 20.0
    while True:
        emu.dashboard("unlock protective stop")
        try:
            driver.resume()
            return
        except DriverFault:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.3)


def test_joint_path_and_single_move(driver: RtdeDriver) -> None:
    start = driver.state().q
    q1 = start + np.array([0.2, 0.1, -0.1, 0.0, 0.1, 0.2])
    q2 = q1 + np.array([0.1, 0.0, 0.0, 0.1, 0.0, 0.0])
    st = driver.move_joints([q1, q2], 2.0, 4.0)
    assert np.max(np.abs(st.q - q2)) < 1e-3  # path values travel as 6 significant digits in the script
    st = driver.move_joints([start], 2.0, 4.0)
    assert np.max(np.abs(st.q - start)) < 1e-9


def test_out_of_limit_target_refused_before_sending(driver: RtdeDriver, emu: EmulatorProcess) -> None:
    before = _state(emu)
    bad = driver.state().q.copy()
    bad[2] = 3.4
    with pytest.raises(SafetyViolation):
        driver.move_joints([bad], 1.0, 1.0)
    far = driver.limits.with_workspace((-2, -2, 0.8), (2, 2, 2))  # TCP must be above 0.8 m: home is not
    safe_driver_limits, driver.limits = driver.limits, far
    try:
        with pytest.raises(SafetyViolation, match="workspace"):
            driver.move_joints([HOME + 0.05], 1.0, 1.0)
    finally:
        driver.limits = safe_driver_limits
    after = _state(emu)
    assert after["commands"] == before["commands"] and after["q"] == before["q"]
    assert driver.fault is None


def test_protective_stop_mid_move(driver: RtdeDriver, emu: EmulatorProcess) -> None:
    driver.move_joints([HOME], 2.0, 4.0)
    goal = HOME + np.array([1.2, 0.0, 0.0, 0.0, 0.0, 0.0])
    threading.Timer(0.4, lambda: emu.emu("protective_stop")).start()
    with pytest.raises(ProtectiveStop):
        driver.move_joints([goal], 0.6, 1.0)
    time.sleep(0.3)
    q_stopped = _state(emu)["q"]
    commands = _state(emu)["commands"]
    with pytest.raises(DriverFault, match="resume"):
        driver.move_joints([HOME], 1.0, 1.0)
    time.sleep(0.2)
    assert _state(emu)["q"] == q_stopped and _state(emu)["commands"] == commands  # no further motion
    assert "Cannot unlock" in emu.dashboard("unlock protective stop")  # refused right after the stop
    with pytest.raises(ProtectiveStop):
        driver.resume()
    _healthy(driver, emu)
    st = driver.move_joints([HOME], 2.0, 4.0)
    assert np.max(np.abs(st.q - HOME)) < 1e-9


def test_stalled_stream_aborts_safely_and_reconnects(driver: RtdeDriver, emu: EmulatorProcess) -> None:
    goal = HOME + np.array([1.2, 0.0, 0.0, 0.0, 0.0, 0.0])
    threading.Timer(0.4, lambda: emu.emu("stall", "1.6")).start()
    with pytest.raises(ConnectionLost):
        driver.move_joints([goal], 0.6, 1.0)
    time.sleep(0.3)
    state = _state(emu)
    assert state["moving"] == "False" and state["program"] == "stopped"  # stopped through the dashboard
    with pytest.raises(DriverFault):
        driver.move_joints([HOME], 1.0, 1.0)  # latched: nothing sent until resume()
    assert _state(emu)["commands"] == state["commands"]
    _healthy(driver, emu)
    st = driver.move_joints([HOME], 2.0, 4.0)
    assert np.max(np.abs(st.q - HOME)) < 1e-9


_DROP_CHILD = """
import sys, threading, numpy as np
from normpos_grasp.errors import DriverFault
from normpos_grasp.execution import RtdeDriver, SafetyLimits
from normpos_grasp.sim.ur_emulator import dashboard_request
host = sys.argv[1]
d = RtdeDriver(host, SafetyLimits.for_model("ur5e"))
d.connect()
goal = d.state().q + np.array([1.2, 0, 0, 0, 0, 0])
threading.Timer(0.4, lambda: dashboard_request(host, "emu drop")).start()
try:
    d.move_joints([goal], 0.6, 1.0)
    print("RESULT no-fault", flush=True)
except DriverFault as exc:
    print("RESULT", type(exc).__name__, flush=True)
"""


def test_dropped_link_aborts_safely_then_reconnects(tmp_path: Path) -> None:
    """A hard drop of every RTDE connection. ur_rtde 1.6.5's control interface then reconnects by itself in a loop
    that can crash its process (a client bug), so the dropping client runs in a child process; the driver must
    have raised ConnectionLost and stopped the arm, and a new connection must drive the arm afterwards."""
    import subprocess
    import sys

    host = HOST.rsplit(".", 1)[0] + ".8"
    with EmulatorProcess(host, "ur5e", ready_timeout_s=60.0, log_path=tmp_path / "emu.log") as emu2:
        child = subprocess.Popen(
            [sys.executable, "-c", _DROP_CHILD, host], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True
        )
        try:
            result = ""
            assert child.stdout is not None
            for line in child.stdout:  # the child may hang or crash in ur_rtde after it reported
                if line.startswith("RESULT"):
                    result = line.strip()
                    break
        finally:
            child.kill()
            child.wait(timeout=30)
        assert result == "RESULT ConnectionLost"
        time.sleep(0.5)
        state = _state(emu2)
        assert state["moving"] == "False"
        q_after = np.array([float(v) for v in state["q"].strip("[]").split(",")])
        assert abs(q_after[0] - 1.2) > 0.1  # the move was neither finished nor retried
        fresh = RtdeDriver(host, SafetyLimits.for_model("ur5e"))
        fresh.connect()
        try:
            st = fresh.move_joints([HOME], 2.0, 4.0)
            assert np.max(np.abs(st.q - HOME)) < 1e-9
        finally:
            fresh.disconnect()


def test_second_control_client_is_refused(driver: RtdeDriver, emu: EmulatorProcess) -> None:
    other = RtdeDriver(HOST, SafetyLimits.for_model("ur5e"))
    with pytest.raises(DriverFault, match="another RTDE client"):
        other.connect()
    st = driver.move_joints([HOME + 0.05], 2.0, 4.0)  # the first client still drives
    assert np.max(np.abs(st.q - (HOME + 0.05))) < 1e-9
    driver.move_joints([HOME], 2.0, 4.0)


def test_unknown_script_refused_loudly(emu: EmulatorProcess) -> None:
    before = _state(emu)
    with socket.create_connection((HOST, 30003), timeout=5.0) as sock:
        sock.sendall(b"movej([1.0, -1.0, 1.0, 0.0, 0.0, 0.0], a=1.0, v=1.0)\n")
        sock.sendall(b"def my_prog():\n  movej([0.5, -1.0, 1.0, 0.0, 0.0, 0.0])\nend\n")
    deadline = time.monotonic() + 10.0
    while int(_state(emu)["refused_scripts"]) < int(before["refused_scripts"]) + 2:
        assert time.monotonic() < deadline, "emulator did not refuse the scripts"
        time.sleep(0.05)
    assert _state(emu)["q"] == before["q"]


def test_planner_plan_executes(driver: RtdeDriver) -> None:
    from dataclasses import replace

    import trimesh

    from normpos_grasp.cell import load_cell
    from normpos_grasp.geometry import make_pose
    from normpos_grasp.planning import plan_pick
    from normpos_grasp.records.template import Template, TemplateFit

    cell = load_cell(EXAMPLES / "ur5e_bin_parallel.yaml")
    fast = replace(  # twice the example's caps (still below the UR5e's rated 3.14 rad/s): a shorter test
        cell.motion,
        joint_velocity=np.minimum(cell.motion.joint_velocity * 2.0, 3.0),
        joint_acceleration=cell.motion.joint_acceleration * 2.0,
    )
    cell = replace(cell, motion=fast)
    part = Template("box", "box", trimesh.creation.box((0.06, 0.04, 0.03)), shape="box")
    fit = TemplateFit(part, make_pose(None, [0.5, 0.05, 0.025]), 1.0, 0.0, 1.0, 1.0, 0.0, True, instance_id=1)
    plan = plan_pick([fit], [], cell).to_json()
    assert plan["status"] == "ok"
    limits = SafetyLimits.from_cell(cell)
    old, driver.limits = driver.limits, limits
    try:
        assert execute_plan(driver, plan, limits).status == "dry_run"
        report = execute_plan(driver, plan, limits, dry_run=False)
    finally:
        driver.limits = old
    assert report.status == "executed"
    assert report.final_error_rad is not None and report.final_error_rad <= 1e-3
    assert {s.kind for s in report.steps} >= {"trajectory", "gripper_close", "gripper_open"}
