"""Picks on the loopback controller with the real ur_rtde client for the arm and the Robotiq client for the gripper
(the emulator's URCap socket), plus the vacuum gripper's analog level input and `normpos-grasp execute` with a
cell whose `gripper.driver` is a Robotiq."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from loopback import loopback_host

from normpos_grasp.cell import load_cell
from normpos_grasp.cell.gripper_driver import RobotiqDriverSpec
from normpos_grasp.cli.main import main
from normpos_grasp.errors import GripperFault
from normpos_grasp.execution import ExecuteOptions, GripperIO, SafetyLimits, SupervisedRtdeDriver, execute_plan
from normpos_grasp.execution.gripper_config import ArmIOGripper
from normpos_grasp.execution.robotiq import RobotiqGripper
from normpos_grasp.sim.ur_emulator import EmulatorProcess

HOST = loopback_host(161)  # one emulator per loopback address; no other test uses this one
HOME = np.array([0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0])
OPENING = 0.0437  # m: the plan's jaw opening


def _plan(opening: float = OPENING) -> dict[str, Any]:
    """A pick-and-place plan near home: start, pre_grasp, grasp, lift, place (joints in rad)."""
    names = ("start", "pre_grasp", "grasp", "lift", "place")
    offsets = (
        [0, 0, 0, 0, 0, 0],
        [0.1, 0, 0, 0, 0, 0],
        [0.1, 0.05, 0, 0, 0, 0],
        [0.1, 0, 0, 0, 0, 0],
        [-0.2, 0, 0, 0, 0, 0],
    )
    return {
        "status": "ok",
        "robot": "ur5e",
        "joint_waypoints": [
            {"name": n, "q": (HOME + np.array(o)).tolist()} for n, o in zip(names, offsets, strict=True)
        ],
        "grasp": {"opening_m": opening},
    }


LIMITS = SafetyLimits.for_model("ur5e", workspace_min=(-1.0, -1.0, -0.2), workspace_max=(1.0, 1.0, 1.2))
FAST = ExecuteOptions(speed=1.0, accel=3.0)


@pytest.fixture(scope="module")
def emu(tmp_path_factory: pytest.TempPathFactory) -> Iterator[EmulatorProcess]:
    log = tmp_path_factory.mktemp("emu") / "emulator.log"
    with EmulatorProcess(HOST, "ur5e", ready_timeout_s=60.0, log_path=log, verbose=0) as proc:
        yield proc


@pytest.fixture(scope="module")
def arm(emu: EmulatorProcess) -> Iterator[SupervisedRtdeDriver]:
    # ur_rtde's client in a child process, as the CLI runs it (its stream age is judged there, robust to load)
    drv = SupervisedRtdeDriver(HOST, LIMITS, GripperIO(close_output=0, open_output=None))
    drv.connect()
    yield drv
    drv.disconnect()


@pytest.fixture(scope="module")
def gripper(emu: EmulatorProcess) -> Iterator[RobotiqGripper]:
    g = RobotiqGripper(HOST, RobotiqDriverSpec(open_counts=3, closed_counts=229))  # the emulated 2F-85's ends
    g.connect()
    yield g
    g.disconnect()


def _gripper_state(emu: EmulatorProcess) -> dict[str, str]:
    reply = emu.emu("gripper", "state")
    return dict(word.split("=", 1) for word in reply.split() if "=" in word)


def test_pick_on_nothing_stops_at_the_grasp(
    emu: EmulatorProcess, arm: SupervisedRtdeDriver, gripper: RobotiqGripper
) -> None:
    emu.emu("gripper", "part", "none")
    report = execute_plan(arm, _plan(), LIMITS, dry_run=False, options=FAST, gripper=gripper)
    assert report.status == "grip_failed" and report.grip_detected is False
    assert float(np.max(np.abs(arm.state().q - (HOME + [0.1, 0.05, 0, 0, 0, 0])))) < 1e-3  # rests at the grasp
    assert _gripper_state(emu)["OBJ"] == "3"  # closed on nothing


def test_pick_commands_the_plans_opening_and_detects_the_part(
    emu: EmulatorProcess, arm: SupervisedRtdeDriver, gripper: RobotiqGripper
) -> None:
    # the part lies where the TCP will be at the grasp (measured there over RTDE), caught only within 1 cm of it
    grasp_q = HOME + [0.1, 0.05, 0, 0, 0, 0]
    at_grasp = arm.move_joints(grasp_q[None], 1.0, 3.0).base_from_tcp[:3, 3]
    arm.move_joints(HOME[None], 1.0, 3.0)
    emu.emu("gripper", "part", "0.030", *(f"{v:.6f}" for v in at_grasp), "0.01")
    report = execute_plan(arm, _plan(), LIMITS, dry_run=False, options=FAST, gripper=gripper)
    assert report.status == "executed" and report.grip_detected is True
    state = _gripper_state(emu)
    assert abs(float(state["opening_m"]) - OPENING) < 1e-3  # released at the place: fingers at the plan's opening
    assert state["held"] == "none" and state["OBJ"] == "3"
    emu.emu("gripper", "part", "none")


def test_gripper_fault_mid_pick_is_a_driver_fault(
    emu: EmulatorProcess, arm: SupervisedRtdeDriver, gripper: RobotiqGripper
) -> None:
    gripper.open(0.05)
    emu.emu("gripper", "fault", "0x0E")
    with pytest.raises(GripperFault, match="overcurrent"):
        execute_plan(arm, _plan(), LIMITS, dry_run=False, options=FAST, gripper=gripper)
    gripper.link.set(ACT=0)  # a reset clears the fault (what activation does)


def test_vacuum_level_on_an_analog_input(emu: EmulatorProcess, arm: SupervisedRtdeDriver) -> None:
    vacuum = ArmIOGripper(arm, analog_input=1, threshold=2.5, held_when="above")
    emu.emu("set_analog", "1", "0.4")
    report = execute_plan(arm, _plan(0.0), LIMITS, dry_run=False, options=FAST, gripper=vacuum)
    assert report.status == "grip_failed"
    assert arm.state().digital_out & 1  # the vacuum output was switched on at the grasp
    emu.emu("set_analog", "1", "4.2")
    arm.move_joints(HOME[None], 1.0, 3.0)
    report = execute_plan(arm, _plan(0.0), LIMITS, dry_run=False, options=FAST, gripper=vacuum)
    assert report.status == "executed" and report.grip_detected is True
    assert not arm.state().digital_out & 1  # released at the place
    emu.emu("set_analog", "1", "0.0")


def _robotiq_cell(tmp_path: Path) -> Path:
    from importlib import resources

    packaged = resources.files("normpos_grasp.examples").joinpath("cells", "ur5e_bin_parallel.yaml")
    with resources.as_file(packaged) as path:
        data = yaml.safe_load(path.read_text())
    data.pop("templates", None)
    data["gripper"]["driver"] = {"type": "robotiq", "model": "2F-85", "open_counts": 3, "closed_counts": 229}
    cell = tmp_path / "robotiq_cell.yaml"
    cell.write_text(yaml.safe_dump(data))
    return cell


def test_execute_cli_uses_the_cells_robotiq(
    emu: EmulatorProcess, arm: SupervisedRtdeDriver, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    arm.disconnect()  # the CLI's own client needs the controller's input registers (the last test of the module)
    cell_path = _robotiq_cell(tmp_path)
    cell = load_cell(cell_path)
    plan = _plan()
    plan["world_from_base"] = cell.world_from_base.tolist()
    plan["tool"] = {"flange_from_tcp": cell.tool.flange_from_tcp.tolist()}
    plan_path = tmp_path / "plan.json"
    plan_path.write_text(json.dumps(plan))
    emu.emu("gripper", "part", "none")
    argv = ["execute", str(plan_path), "--robot", HOST, "--cell", str(cell_path), "--execute"]
    assert main(argv) == 1  # grip not detected: the pick stopped at the grasp
    assert "grip not detected" in capsys.readouterr().out
    emu.emu("gripper", "part", "0.02")
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "gripper opening 43.7 mm (the plan's)" in out and "grip detected: True" in out
    assert abs(float(_gripper_state(emu)["opening_m"]) - OPENING) < 1e-3
    emu.emu("gripper", "part", "none")
    assert main([*argv, "--grip-input", "3"]) == 2  # the cell's driver and a wiring flag contradict each other
    assert "gripper.driver" in capsys.readouterr().err
