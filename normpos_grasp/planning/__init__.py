"""Five-pose grasp evaluation, pick-and-place plans (Cartesian lines, RRT-Connect, time parameterisation)."""

from normpos_grasp.kinematics.arm import ArmModel
from normpos_grasp.planning.evaluate import EvaluationOptions, evaluate_candidates
from normpos_grasp.planning.plan import PlanOptions, build_world, plan_pick
from normpos_grasp.records.plan import Evaluation, PickPlan, Target, Waypoint

__all__ = [
    "ArmModel",
    "Evaluation",
    "EvaluationOptions",
    "PickPlan",
    "PlanOptions",
    "Target",
    "Waypoint",
    "build_world",
    "evaluate_candidates",
    "plan_pick",
]
