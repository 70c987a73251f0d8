"""Collision world on python-fcl: static cell, fitted objects, unexplained clutter, arm, tool and held object."""

from normpos_grasp.collision.world import CollisionWorld, Hit
from normpos_grasp.records.tool import ToolModel, ToolShape, parallel_gripper, suction_tool, tool_from_gripper

__all__ = ["CollisionWorld", "Hit", "ToolModel", "ToolShape", "parallel_gripper", "suction_tool", "tool_from_gripper"]
