"""Execution: the ArmDriver contract, RTDE and simulated drivers, safety limits, and plan execution."""

from .driver import ArmDriver, ArmState, DriverOptions, GripperIO, GuardedDriver
from .interrupts import exit_code, stop_signals
from .plan import ExecuteOptions, ExecutionReport, check_plan, execute_plan, load_plan, parse_plan
from .rtde_driver import ControllerIdentity, RtdeDriver, check_controller, read_controller_identity
from .safety import SafetyLimits
from .sim_driver import SimDriver
from .supervised import SupervisedRtdeDriver

__all__ = [
    "ArmDriver",
    "ArmState",
    "ControllerIdentity",
    "DriverOptions",
    "ExecuteOptions",
    "ExecutionReport",
    "GripperIO",
    "GuardedDriver",
    "RtdeDriver",
    "SafetyLimits",
    "SimDriver",
    "SupervisedRtdeDriver",
    "check_controller",
    "check_plan",
    "execute_plan",
    "exit_code",
    "load_plan",
    "parse_plan",
    "read_controller_identity",
    "stop_signals",
]
