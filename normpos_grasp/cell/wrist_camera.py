"""A camera on the wrist (eye-in-hand): where it sits on the flange, where the arm takes frames, and its housing
as a collision box that rides on the flange.

One frame convention (docs/cells.md, camera.model): a frame taken with the arm at joints q carries
world_from_camera = world_from_base @ base_from_flange(q) @ flange_from_camera, with base_from_flange from the UR
DH model (the planner's arm model) and flange_from_camera from `calibrate hand-eye --mode eye-in-hand`.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from normpos_grasp.collision.world import CollisionWorld
from normpos_grasp.errors import InputError
from normpos_grasp.kinematics.arm import ArmModel
from normpos_grasp.kinematics.ur_params import dh_forward_kinematics, ur_params
from normpos_grasp.records.tool import ToolModel, ToolShape
from normpos_grasp.typing import ArrayLike, FloatArray

# The housing of an Intel RealSense D435 (Intel's D400 series datasheet: 90 x 25 x 25 mm), in the camera frame
# (x along the stereo baseline, z the optical axis); the default of `camera.body_size_m`.
D435_BODY_M = (0.090, 0.025, 0.025)
CAMERA_SHAPE = "camera_body"  # the tool shape name of the housing (grown by the cable clearance)


@dataclass(frozen=True, eq=False)
class WristCamera:
    """The `camera:` section of a cell with `mount: wrist`.

    flange_from_camera: (4, 4) camera pose on the flange (OpenCV camera frame), m. capture_q: (K, 6) joint
    positions the arm takes frames at, rad, in the order they are tried. body_size_m: (3,) housing extents along the
    camera's x, y, z, m; camera_from_body: (4, 4) the housing's centre in the camera frame. cable_clearance_m: the
    housing's collision box grows by this on every side (the cable's exit and strain relief), m. source: the
    camera JSON `flange_from_camera` was read from (None when the cell gives the pose itself).
    """

    flange_from_camera: FloatArray
    capture_q: FloatArray
    body_size_m: FloatArray
    camera_from_body: FloatArray
    cable_clearance_m: float = 0.02
    source: Path | None = None

    def world_from_camera(self, world_from_base: ArrayLike, robot: str, q: ArrayLike) -> FloatArray:
        """(4, 4) camera pose in the world with the arm (`robot`, mounted at `world_from_base`) at joints q (6,)
        rad: world_from_base @ base_from_flange(q) @ flange_from_camera."""
        joints = np.asarray(q, dtype=np.float64)
        if joints.shape != (6,) or not np.all(np.isfinite(joints)):
            raise InputError(f"wrist camera: the capture joints must be 6 finite numbers (rad), got {joints.tolist()}")
        base_from_flange = dh_forward_kinematics(ur_params(robot), joints)
        return np.asarray(world_from_base, dtype=np.float64) @ base_from_flange @ self.flange_from_camera

    def collision_shape(self, flange_from_tcp: ArrayLike) -> ToolShape:
        """The housing grown by the cable clearance, as a fixed box of the tool (TCP frame)."""
        tcp_from_flange = np.linalg.inv(np.asarray(flange_from_tcp, dtype=np.float64))
        pose = tcp_from_flange @ self.flange_from_camera @ self.camera_from_body
        size = tuple(float(v) + 2.0 * self.cable_clearance_m for v in self.body_size_m)
        return ToolShape(CAMERA_SHAPE, size, pose)

    def mounted_on(self, tool: ToolModel) -> ToolModel:
        """`tool` with the camera housing among its shapes: every collision check of the tool (planner, execution
        check, zone-watch silhouette) then covers the camera and its cable clearance."""
        kept = tuple(s for s in tool.shapes if s.name != CAMERA_SHAPE)
        return replace(tool, shapes=(*kept, self.collision_shape(tool.flange_from_tcp)))

    def capture_contacts(
        self,
        robot: str,
        world_from_base: ArrayLike,
        tool: ToolModel,
        boxes: Iterable[tuple[str, FloatArray, FloatArray]],
    ) -> list[str]:
        """For each capture pose, what the arm or `tool` (the housing mounted) touches among static `boxes` (name,
        world_from_box (4, 4), size (3,) m), in words; '' where clear."""
        arm = ArmModel.from_name(robot, world_from_base)
        world = CollisionWorld()
        for name, pose, size in boxes:
            world.add_box(name, pose, size, "cell")
        world.set_arm(arm)
        world.set_tool(tool)
        world.update()
        out = []
        for q in np.asarray(self.capture_q, dtype=np.float64):
            hit = world.check_config(q, 0.0)
            if hit is None:
                out.append("")
            elif hit.part == "tool":
                names = world.which(arm.fk(q) @ tool.flange_from_tcp)
                out.append(f"the tool (camera housing included) touches {', '.join(names) or 'the cell'}")
            elif hit.part == "self":
                out.append(f"the arm touches itself or its tool ({hit.name})")
            else:
                out.append(f"the arm's {hit.name or 'links'} touch the cell")
        return out
