"""The records the stages hand each other, as frozen dataclasses at the bottom of the package.

`Instance` (segmentation), `NormPosition` / `OrientedBox` (measurement), `Template`, `Symmetry`, `GraspAnnotation`
and `TemplateFit` (templates), `GraspCandidate` (grasp synthesis), `ToolModel` / `ToolShape` (the end effector),
`Target`, `Evaluation`, `Waypoint`, `Trajectory` and `PickPlan` (planning). They import only `errors`, `typing`,
`validation` and `geometry`, never a stage. The arm model (`ArmModel`) carries the UR kinematics and lives in
`normpos_grasp.kinematics.arm`.
"""

from normpos_grasp.records.grasp import GraspCandidate
from normpos_grasp.records.instance import Instance
from normpos_grasp.records.normpos import NormPosition, OrientedBox
from normpos_grasp.records.plan import PLAN_FORMAT, Evaluation, PickPlan, Target, Trajectory, Waypoint
from normpos_grasp.records.template import SHAPE_CLASSES, GraspAnnotation, Symmetry, Template, TemplateFit
from normpos_grasp.records.tool import ToolModel, ToolShape, parallel_gripper, suction_tool, tool_from_gripper

__all__ = [
    "PLAN_FORMAT",
    "SHAPE_CLASSES",
    "Evaluation",
    "GraspAnnotation",
    "GraspCandidate",
    "Instance",
    "NormPosition",
    "OrientedBox",
    "PickPlan",
    "Symmetry",
    "Target",
    "Template",
    "TemplateFit",
    "ToolModel",
    "ToolShape",
    "Trajectory",
    "Waypoint",
    "parallel_gripper",
    "suction_tool",
    "tool_from_gripper",
]
