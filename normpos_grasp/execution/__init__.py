"""Execution: the ArmDriver contract, RTDE and simulated drivers, safety limits, and plan execution."""

from .driver import ArmDriver, ArmState, DriverOptions, GripperIO, GuardedDriver
from .plan import ExecuteOptions, ExecutionReport, check_plan, execute_plan, load_plan, parse_plan
from .rtde_driver import RtdeDriver
from .safety import SafetyLimits
from .sim_driver import SimDriver

__all__ = [
    "ArmDriver",
    "ArmState",
    "DriverOptions",
    "ExecuteOptions",
    "ExecutionReport",
    "GripperIO",
    "GuardedDriver",
    "RtdeDriver",
    "SafetyLimits",
    "SimDriver",
    "check_plan",
    "execute_plan",
    "load_plan",
    "parse_plan",
]
