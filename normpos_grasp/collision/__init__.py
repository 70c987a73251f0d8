"""Collision world on python-fcl: static cell, fitted objects, unexplained clutter, arm, tool and held object."""

from normpos_grasp.collision.tool import ToolModel, ToolShape, parallel_gripper, suction_tool, tool_from_gripper
from normpos_grasp.collision.world import CollisionWorld, Hit

__all__ = ["CollisionWorld", "Hit", "ToolModel", "ToolShape", "parallel_gripper", "suction_tool", "tool_from_gripper"]
