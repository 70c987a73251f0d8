"""The move to a wrist camera's capture pose (cell `camera: {mount: wrist}`): a collision-free joint path from where
the arm is to the capture joints, timed within the cell's caps, as a plan document that `execution.execute_plan`
checks and runs like any plan (no gripper action).

The capture poses are joint positions, so the move needs no IK: a joint-space path (straight when free, else
RRT-Connect, `planning.rrt`) in the cell's static world plus whatever the caller knows is in the bin (the last
frame's fits and norm-positions). The camera housing and its cable clearance are among the tool's shapes
(`cell.wrist_camera.mounted_on`), so every configuration checked keeps them clear too. Each edge is timed rest to
rest (trapezoids within `motion.joint_velocity` / `joint_acceleration`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from normpos_grasp.cell.config import CellConfig
from normpos_grasp.collision.world import CollisionWorld
from normpos_grasp.errors import InputError, PlanningError
from normpos_grasp.kinematics.arm import ArmModel
from normpos_grasp.planning.plan import build_world
from normpos_grasp.planning.rrt import MotionOptions, plan_joint_motion
from normpos_grasp.planning.timing import TimingOptions, time_parameterise
from normpos_grasp.records.normpos import NormPosition
from normpos_grasp.records.plan import Trajectory
from normpos_grasp.records.template import TemplateFit
from normpos_grasp.typing import ArrayLike, BoolArray, FloatArray


@dataclass(frozen=True, eq=False)
class CaptureMove:
    """A timed joint path to capture pose `index`: path (K, 6) rad from the start to the capture joints,
    trajectory (samples, rest at every path node), world_from_camera (4, 4) at the end (the commanded joints)."""

    index: int
    path: FloatArray
    trajectory: Trajectory
    world_from_camera: FloatArray

    @property
    def capture_q(self) -> FloatArray:
        return np.asarray(self.path[-1], dtype=np.float64)

    def to_json(self, cell: CellConfig) -> dict[str, Any]:
        """The plan document `execute_plan` runs (status, robot, world_from_base, tool, joint_waypoints,
        trajectory, cell); waypoints 'start', 'via_<i>', 'capture'."""
        names = ["start", *(f"via_{i}" for i in range(1, len(self.path) - 1)), "capture"]
        traj = self.trajectory
        return {
            "status": "ok",
            "kind": "capture_move",
            "capture_index": self.index,
            "robot": cell.robot_model,
            "world_from_base": np.asarray(cell.world_from_base).tolist(),
            "tool": cell.tool.to_json(0.0),
            "joint_waypoints": [{"name": n, "q": q.tolist()} for n, q in zip(names, self.path, strict=True)],
            "trajectory": {
                "dt_s": float(np.median(np.diff(traj.t))) if len(traj.t) > 1 else 0.0,
                "duration_s": traj.duration_s,
                "samples": [{"t": float(t), "q": q.tolist()} for t, q in zip(traj.t, traj.q, strict=True)],
            },
            "cell": cell.record(),
        }


class _Free:
    """Collision-free test of one configuration (tool closed: the fingers at zero opening) with the sphere pre-test."""

    def __init__(self, world: CollisionWorld) -> None:
        self.world = world

    def __call__(self, q: FloatArray) -> bool:
        return self.world.check_config(q, 0.0) is None

    def clear_batch(self, qs: FloatArray) -> BoolArray:
        return self.world.configs_clear(qs, 0.0)


def plan_capture_move(
    cell: CellConfig,
    start_q: ArrayLike,
    index: int = 0,
    fits: Sequence[TemplateFit] = (),
    normpositions: Sequence[NormPosition] = (),
    motion: MotionOptions | None = None,
) -> CaptureMove:
    """The move from `start_q` (6,) rad to `cell.wrist_camera.capture_q[index]`. InputError for a cell without a
    wrist camera or an index out of range; PlanningError (naming the capture pose) when the start or the capture
    pose collides or no joint path is found."""
    wrist = cell.wrist_camera
    if wrist is None:
        raise InputError(f"cell {cell.name!r} has no wrist camera (camera: {{mount: wrist}})")
    if not 0 <= index < len(wrist.capture_q):
        raise InputError(f"capture pose {index} does not exist: the cell has {len(wrist.capture_q)}")
    goal = np.asarray(wrist.capture_q[index], dtype=np.float64)
    start = np.asarray(start_q, dtype=np.float64)
    arm = ArmModel.from_name(cell.robot_model, cell.world_from_base)
    world, _, _ = build_world(cell, fits, normpositions, arm)
    world.set_arm(arm)
    world.set_tool(cell.tool)
    world.update()
    try:
        path = plan_joint_motion(start, goal, _Free(world), arm.lower, arm.upper, motion)
    except PlanningError as exc:
        raise PlanningError(f"camera.capture[{index}]: no collision-free move to the capture pose: {exc}") from exc
    vmax = np.asarray(cell.motion.joint_velocity, dtype=np.float64)
    amax = np.asarray(cell.motion.joint_acceleration, dtype=np.float64)
    edges = [np.stack(path[k : k + 2]) for k in range(len(path) - 1)]
    trajectory = time_parameterise(edges, vmax, amax, options=TimingOptions(method="trapezoid"))
    return CaptureMove(
        index, np.stack(path), trajectory, wrist.world_from_camera(cell.world_from_base, cell.robot_model, goal)
    )
