"""Robot kinematics for UR arms: parameter table, FK/Jacobians (pinocchio), analytic and differential IK,
grippers and collision primitives. Differential IK (mink) lives in `normpos_grasp.kinematics.diff_ik`."""

from normpos_grasp.kinematics.arm import ArmModel, LinkShape
from normpos_grasp.kinematics.dh import DHCalibration, DHChain
from normpos_grasp.kinematics.gripper import FingerSpec, Gripper
from normpos_grasp.kinematics.robot import ROBOT_NAMES, IKLabel, IKOptions, Robot, SingularityDistance
from normpos_grasp.kinematics.shapes import ARM_LINKS, CollisionShape
from normpos_grasp.kinematics.ur_params import UR_PARAMS, URParams, dh_forward_kinematics, ur_params

__all__ = [
    "ARM_LINKS",
    "ROBOT_NAMES",
    "UR_PARAMS",
    "ArmModel",
    "CollisionShape",
    "DHCalibration",
    "DHChain",
    "FingerSpec",
    "Gripper",
    "IKLabel",
    "IKOptions",
    "LinkShape",
    "Robot",
    "SingularityDistance",
    "URParams",
    "dh_forward_kinematics",
    "ur_params",
]
