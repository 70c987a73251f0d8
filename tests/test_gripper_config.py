"""The cell YAML's `gripper.driver` section: every kind parses to its spec, every bad key or value is a
CellConfigError naming the key, and execution builds the wiring and tool driver from it."""

from __future__ import annotations

import copy
from importlib import resources
from typing import Any

import numpy as np
import pytest
import yaml

from normpos_grasp.cell.config import cell_from_dict
from normpos_grasp.cell.gripper_driver import IODriverSpec, RobotiqDriverSpec, VacuumDriverSpec
from normpos_grasp.errors import CellConfigError
from normpos_grasp.execution import ArmState, GripperIO
from normpos_grasp.execution.gripper_config import ArmIOGripper, gripper_io, held_by_level, tool_driver
from normpos_grasp.execution.robotiq import RobotiqGripper


def _cell(**driver: Any) -> dict[str, Any]:
    with resources.as_file(resources.files("normpos_grasp.examples").joinpath("cells", "ur5e_bin_parallel.yaml")) as p:
        data: dict[str, Any] = yaml.safe_load(p.read_text())
    data.pop("templates", None)
    data["gripper"]["driver"] = driver
    return data


def _suction(**driver: Any) -> dict[str, Any]:
    data = _cell()
    data["gripper"] = {"model": "cup", "kind": "suction", "flange_to_tcp_m": 0.12, "driver": driver}
    return data


def test_each_kind_parses() -> None:
    robotiq = cell_from_dict(_cell(type="robotiq", model="2F-85", port=50001, speed=128, force=40, calibrate=True))
    spec = robotiq.gripper_driver
    assert isinstance(spec, RobotiqDriverSpec)
    assert (spec.port, spec.speed, spec.force, spec.calibrate, spec.stroke_m) == (50001, 128, 40, True, 0.085)
    io = cell_from_dict(_cell(type="io", close_output=4, open_output=None, grip_input=17)).gripper_driver
    assert io == IODriverSpec(close_output=4, open_output=None, grip_input=17)
    analog = _suction(type="vacuum", vacuum_output=2, level_input={"analog": 1, "threshold": 2.5, "held_when": "below"})
    vac = cell_from_dict(analog).gripper_driver
    assert vac == VacuumDriverSpec(vacuum_output=2, analog_input=1, threshold=2.5, held_when="below")
    assert cell_from_dict(_cell(type="io")).gripper_driver == IODriverSpec()  # defaults: close 0, open 1
    data = _cell()
    del data["gripper"]["driver"]
    assert cell_from_dict(data).gripper_driver is None


@pytest.mark.parametrize(
    ("data", "key", "words"),
    [
        (_cell(type="servo"), "gripper.driver.type", "robotiq, io or vacuum"),
        (_cell(type="robotiq", prot=63352), "gripper.driver.prot", "did you mean 'port'"),
        (_cell(type="robotiq", model="3F"), "gripper.driver.model", "2F-85, 2F-140"),
        (_cell(type="robotiq", model="2F-140"), "gripper.driver.model", "opens 140 mm"),
        (_cell(type="robotiq", speed=300), "gripper.driver.speed", "0-255"),
        (_cell(type="robotiq", force=True), "gripper.driver.force", "0-255"),
        (_cell(type="robotiq", port=0), "gripper.driver.port", "1-65535"),
        (_cell(type="robotiq", open_counts=100, closed_counts=120), "gripper.driver.closed_counts", "at least 50"),
        (_cell(type="robotiq", move_timeout_s=-1), "gripper.driver.move_timeout_s", "[0.1, 60] s"),
        (_cell(type="robotiq", calibrate="yes"), "gripper.driver.calibrate", "true or false"),
        (_cell(type="io", close_output=16), "gripper.driver.close_output", "0-15"),
        (_cell(type="io", close_output=1, tool_outputs=True, open_output=2), "gripper.driver.open_output", "0-1"),
        (_cell(type="io", close_output=1, open_output=1), "gripper.driver.open_output", "both 1"),
        (_cell(type="io", grip_input=18), "gripper.driver.grip_input", "0-17"),
        (_cell(type="vacuum", level_input={"digital": 1}), "gripper.driver.type", "suction gripper"),
        (_suction(type="robotiq"), "gripper.driver.type", "parallel gripper"),
        (_suction(type="vacuum"), "gripper.driver.level_input", "required key is missing"),
        (_suction(type="vacuum", level_input={"digital": 1, "analog": 0}), "gripper.driver.level_input", "exactly one"),
        (
            _suction(type="vacuum", level_input={"analog": 2, "threshold": 1.0}),
            "gripper.driver.level_input.analog",
            "0-1",
        ),
        (_suction(type="vacuum", level_input={"analog": 0}), "gripper.driver.level_input.threshold", "missing"),
        (
            _suction(type="vacuum", level_input={"digital": 3, "threshold": 1.0}),
            "gripper.driver.level_input.threshold",
            "no threshold",
        ),
        (
            _suction(type="vacuum", level_input={"analog": 0, "threshold": 1.0, "held_when": "high"}),
            "gripper.driver.level_input.held_when",
            "above or below",
        ),
        (
            _suction(type="vacuum", vacuum_output=3, release_output=3, level_input={"digital": 1}),
            "gripper.driver.release_output",
            "both 3",
        ),
    ],
)
def test_bad_driver_sections_name_the_key(data: dict[str, Any], key: str, words: str) -> None:
    with pytest.raises(CellConfigError) as err:
        cell_from_dict(copy.deepcopy(data))
    assert err.value.path == key
    assert words in str(err.value)
    assert "\n" not in str(err.value)


def _state(digital_in: int = 0, analog: tuple[float, float] = (0.0, 0.0)) -> ArmState:
    z = np.zeros(6)
    return ArmState(z, z, np.eye(4), 0.0, 7, 1, 0, 2, True, 0, digital_in, 0.0, analog)


def test_wiring_and_detection_from_the_spec() -> None:
    io = IODriverSpec(close_output=4, open_output=5, grip_input=9, settle_s=0.1)
    assert gripper_io(io) == GripperIO(4, 5, 9, 0.1, False)
    vac = VacuumDriverSpec(vacuum_output=1, release_output=None, analog_input=0, threshold=2.0)
    assert gripper_io(vac) == GripperIO(1, None, None, 0.3, False)
    assert gripper_io(RobotiqDriverSpec()) is None  # the arm switches nothing for a Robotiq
    assert isinstance(tool_driver(RobotiqDriverSpec(), arm=None, host="127.0.0.1"), RobotiqGripper)  # type: ignore[arg-type]
    built = tool_driver(vac, arm=None, host="127.0.0.1")  # type: ignore[arg-type]
    assert isinstance(built, ArmIOGripper) and built.detects_grip
    assert tool_driver(IODriverSpec(), arm=None, host="x") is not None  # type: ignore[arg-type]
    assert not tool_driver(IODriverSpec(), arm=None, host="x").detects_grip  # type: ignore[arg-type, union-attr]
    assert held_by_level(_state(digital_in=1 << 9), 9, None, 0.0, "above")
    assert not held_by_level(_state(digital_in=1 << 8), 9, None, 0.0, "above")
    assert held_by_level(_state(analog=(2.5, 0.0)), None, 0, 2.0, "above")
    assert not held_by_level(_state(analog=(1.5, 0.0)), None, 0, 2.0, "above")
    assert held_by_level(_state(analog=(0.0, -0.8)), None, 1, -0.5, "below")  # a vacuum sensor reading negative
