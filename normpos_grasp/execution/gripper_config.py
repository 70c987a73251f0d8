"""Gripper drivers from the cell's `gripper.driver` section: the wiring the arm driver needs and the `ToolDriver`
that execute_plan commands (open to the plan's opening, close, grip detection).

- `robotiq`: `RobotiqGripper` over the URCap socket of the arm's controller (the arm driver drives no outputs);
- `io`: digital outputs through the arm driver (`GripperIO`), grip detection from a digital input;
- `vacuum`: the vacuum output (and an optional release output) through the arm driver, the vacuum level from a
  digital input or a standard analog input compared with a threshold.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

from normpos_grasp.cell.gripper_driver import GripperDriverSpec, IODriverSpec, RobotiqDriverSpec, VacuumDriverSpec
from normpos_grasp.errors import DriverFault, EmergencyStop, ProtectiveStop

from .driver import ArmDriver, ArmState, GripperIO
from .robotiq import RobotiqGripper

log = logging.getLogger(__name__)


@runtime_checkable
class ToolDriver(Protocol):
    """What execute_plan needs from a gripper. detects_grip: grip_detected() answers (else it is not asked)."""

    @property
    def detects_grip(self) -> bool: ...

    def connect(self) -> None: ...

    def disconnect(self) -> None: ...

    def open(self, opening_m: float | None = None, watch: Callable[[], None] | None = None) -> object: ...

    def close(self, watch: Callable[[], None] | None = None) -> object: ...

    def grip_detected(self) -> bool: ...


@dataclass
class ArmIOGripper:
    """A gripper on the arm's outputs (the arm driver's `GripperIO` switches them); grip detection from the arm's
    inputs: `digital_input` high, or standard analog input `analog_input` above / below `threshold` (V or A)."""

    arm: ArmDriver
    digital_input: int | None = None
    analog_input: int | None = None
    threshold: float = 0.0
    held_when: str = "above"

    @property
    def detects_grip(self) -> bool:
        return self.digital_input is not None or self.analog_input is not None

    def connect(self) -> None:
        return None

    def disconnect(self) -> None:
        return None

    def open(self, opening_m: float | None = None, watch: Callable[[], None] | None = None) -> None:
        self.arm.gripper_open()

    def close(self, watch: Callable[[], None] | None = None) -> None:
        self.arm.gripper_close()

    def grip_detected(self) -> bool:
        st = self.arm.state()
        return held_by_level(st, self.digital_input, self.analog_input, self.threshold, self.held_when)


def held_by_level(
    st: ArmState, digital_input: int | None, analog_input: int | None, threshold: float, held_when: str
) -> bool:
    """The grip (vacuum level) an arm state shows: a digital input bit high, or an analog input past the threshold."""
    if digital_input is not None:
        return bool(st.digital_in >> digital_input & 1)
    if analog_input is None:
        raise DriverFault("this gripper has no grip-detect input configured (gripper.driver)")
    level = float(st.analog_in[analog_input])
    return level >= threshold if held_when == "above" else level <= threshold


def gripper_io(spec: GripperDriverSpec | None) -> GripperIO | None:
    """The arm driver's output wiring for `spec` (None for a Robotiq, which the arm does not switch, and without
    a spec: the driver's default wiring)."""
    if isinstance(spec, IODriverSpec):
        return GripperIO(spec.close_output, spec.open_output, spec.grip_input, spec.settle_s, spec.tool_outputs)
    if isinstance(spec, VacuumDriverSpec):
        return GripperIO(spec.vacuum_output, spec.release_output, spec.digital_input, spec.settle_s, spec.tool_outputs)
    return None


def tool_driver(spec: GripperDriverSpec | None, arm: ArmDriver, host: str) -> ToolDriver | None:
    """The ToolDriver for `spec` on `arm` (a Robotiq talks to the URCap socket of `host`, the arm's controller)."""
    if spec is None:
        return None
    if isinstance(spec, RobotiqDriverSpec):
        return RobotiqGripper(host, spec)
    if isinstance(spec, IODriverSpec):
        return ArmIOGripper(arm, spec.grip_input)
    return ArmIOGripper(arm, spec.digital_input, spec.analog_input, spec.threshold, spec.held_when)


def arm_watch(arm: ArmDriver) -> Callable[[], None]:
    """A check for the gripper's wait loops: the arm must stay out of protective and emergency stops."""

    def watch() -> None:
        st = arm.state()
        if st.emergency_stopped:
            raise EmergencyStop(f"emergency stop while the gripper acts (safety_mode {st.safety_mode})")
        if st.protective_stopped:
            raise ProtectiveStop(f"protective stop while the gripper acts (safety_mode {st.safety_mode})")

    return watch
