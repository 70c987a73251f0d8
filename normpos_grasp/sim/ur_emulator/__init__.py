"""Loopback UR controller: RTDE, dashboard and script servers that the unmodified ur_rtde clients drive."""

from .arm import SimulatedArm
from .controller import EmulatedController, EmulatorOptions
from .process import EmulatorProcess, dashboard_request
from .server import UREmulator

__all__ = [
    "EmulatedController",
    "EmulatorOptions",
    "EmulatorProcess",
    "SimulatedArm",
    "UREmulator",
    "dashboard_request",
]
