"""Safety limits checked on every target before anything is sent to an arm.

The judge itself lives one floor down, in `normpos_grasp.cell.limits`, so that the planner holds its plans to the
same checks execution runs (`SafetyLimits.check_path`); this module names it for the drivers and `execute_plan`.
"""

from __future__ import annotations

from normpos_grasp.cell.limits import (
    JOINT_TOL,
    MAX_JOINT_ACCEL_CEILING,
    MAX_TOOL_ACCEL_CEILING,
    MAX_TOOL_SPEED_CEILING,
    SafetyLimits,
)

__all__ = ["JOINT_TOL", "MAX_JOINT_ACCEL_CEILING", "MAX_TOOL_ACCEL_CEILING", "MAX_TOOL_SPEED_CEILING", "SafetyLimits"]
