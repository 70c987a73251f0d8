"""Five-pose grasp evaluation, pick-and-place plans (Cartesian lines, RRT-Connect, time parameterisation)."""

from normpos_grasp.planning.arm import ArmModel
from normpos_grasp.planning.evaluate import Evaluation, EvaluationOptions, Target, evaluate_candidates
from normpos_grasp.planning.plan import PickPlan, PlanOptions, Waypoint, build_world, plan_pick

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
