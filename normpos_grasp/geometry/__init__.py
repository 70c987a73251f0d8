"""Rigid-body geometry: poses as 4x4 `a_from_b` matrices, rotations, and reflection-safe alignment."""

from normpos_grasp.geometry.kabsch import kabsch
from normpos_grasp.geometry.transforms import (
    invert_pose,
    make_pose,
    pose_from_ur,
    pose_to_ur,
    random_rotation,
    rotation_angle,
    rotation_from_rotvec,
    rotation_to_rotvec,
    transform_points,
)

__all__ = [
    "invert_pose",
    "kabsch",
    "make_pose",
    "pose_from_ur",
    "pose_to_ur",
    "random_rotation",
    "rotation_angle",
    "rotation_from_rotvec",
    "rotation_to_rotvec",
    "transform_points",
]
