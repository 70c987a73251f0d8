"""The one parameter table of the supported UR arms: DH parameters, joint limits, link masses.

Source: UniversalRobots/Universal_Robots_ROS2_Description, commit 2221ec0f (2024-10-14),
config/<model>/{default_kinematics,joint_limits,physical_parameters}.yaml (BSD-3-Clause); DH values
cross-checked against UR's article "DH Parameters for calculations of kinematics and dynamics".
Standard (distal) DH, theta offsets 0, alpha = [pi/2, 0, 0, pi/2, -pi/2, 0]. Metres, radians, kg.
UR30 velocity/effort limits are copies of the UR20's in that source: unverified for the UR30.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from normpos_grasp.errors import RobotModelError
from normpos_grasp.typing import ArrayLike, FloatArray

DH_ALPHA = (np.pi / 2, 0.0, 0.0, np.pi / 2, -np.pi / 2, 0.0)
JOINT_NAMES = (
    "shoulder_pan_joint",
    "shoulder_lift_joint",
    "elbow_joint",
    "wrist_1_joint",
    "wrist_2_joint",
    "wrist_3_joint",
)


@dataclass(frozen=True)
class LinkGeometry:
    """Collision-geometry sizes of one arm, metres (collision only: never used for kinematics).

    footprint_radius: half the base footprint diameter. base_height: height of the base cylinder.
    shoulder_offset: lateral offset of the upper-arm tube from the DH plane along the joint-2 axis;
    elbow_offset: lateral step back from upper arm to forearm (the forearm sits at shoulder_offset - elbow_offset).
    Radii: shoulder (shoulder joint housing, also the vertical column), upper_arm (tube), elbow (housing),
    forearm (tube), wrist (the three wrist housings).
    """

    footprint_radius: float
    base_height: float
    shoulder_offset: float
    elbow_offset: float
    shoulder_radius: float
    upper_arm_radius: float
    elbow_radius: float
    forearm_radius: float
    wrist_radius: float


# UR5e reference sizes: footprint diameter 149 mm (UR5e datasheet); lateral offsets 0.138 / 0.131 m
# (ur_e_description shoulder_offset / elbow_offset, also in mujoco_menagerie's ur5e.xml body positions);
# radii of mujoco_menagerie's hand-made UR5e collision capsules (shoulder 0.06, upper arm 0.05, elbow 0.055,
# forearm 0.038, wrists 0.04). Other models: scaled from these (see `_scaled_geometry`), estimates.
_UR5E_FOOTPRINT_DIAMETER = 0.149
_UR5E_D4, _UR5E_D5 = 0.1333, 0.0997


def _scaled_geometry(footprint_diameter: float, d1: float, d4: float, d5: float) -> LinkGeometry:
    """Collision sizes scaled from the UR5e: radii of the big joints by footprint ratio, lateral offsets by d4
    ratio, wrist radius by d5 ratio, base height 0.5 d1. Rounded to 0.1 mm."""
    big = footprint_diameter / _UR5E_FOOTPRINT_DIAMETER
    lat = d4 / _UR5E_D4
    small = d5 / _UR5E_D5

    def r(value: float) -> float:
        return round(value, 4)

    return LinkGeometry(
        footprint_radius=r(footprint_diameter / 2.0),
        base_height=r(0.5 * d1),
        shoulder_offset=r(0.138 * lat),
        elbow_offset=r(0.131 * lat),
        shoulder_radius=r(0.06 * big),
        upper_arm_radius=r(0.05 * big),
        elbow_radius=r(0.055 * big),
        forearm_radius=r(0.038 * big),
        wrist_radius=r(0.04 * small),
    )


@dataclass(frozen=True)
class URParams:
    """Nominal parameters of one UR model.

    d: (d1, 0, 0, d4, d5, d6) link offsets, metres. a: (0, a2, a3, 0, 0, 0) link lengths, metres.
    position_limit: per-joint symmetric limit, radians (inf: unlimited). velocity_limit: rad/s.
    effort_limit: N m. masses: base, shoulder, upper arm, forearm, wrist 1-3, kg.
    payload_kg, reach_m: UR's rated figures (see robots/README.md for their status).
    footprint_diameter_m: base footprint diameter (UR datasheets; not re-checked against current ones).
    geometry: collision sizes (None: scaled from the UR5e by `footprint_diameter_m`, d4 and d5; see `link_geometry`).
    """

    name: str
    d: tuple[float, float, float, float, float, float]
    a: tuple[float, float, float, float, float, float]
    position_limit: tuple[float, float, float, float, float, float]
    velocity_limit: tuple[float, float, float, float, float, float]
    effort_limit: tuple[float, float, float, float, float, float]
    masses: tuple[float, float, float, float, float, float, float]
    payload_kg: float
    reach_m: float
    verified_limits: bool = True
    footprint_diameter_m: float = 0.149
    geometry: LinkGeometry | None = field(default=None)

    @property
    def link_geometry(self) -> LinkGeometry:
        """Collision sizes of this arm (explicit `geometry` or the UR5e-scaled estimate)."""
        if self.geometry is not None:
            return self.geometry
        return _scaled_geometry(self.footprint_diameter_m, self.d[0], self.d[3], self.d[4])


def _deg(*values: float) -> tuple[float, float, float, float, float, float]:
    out = tuple(float(np.inf) if v == np.inf else float(np.deg2rad(v)) for v in values)
    return out  # type: ignore[return-value]


_INF = np.inf
UR_PARAMS: dict[str, URParams] = {
    "ur3e": URParams(
        "ur3e",
        (0.15185, 0, 0, 0.13105, 0.08535, 0.0921),
        (0, -0.24355, -0.2132, 0, 0, 0),
        _deg(360, 360, 180, 360, 360, _INF),
        _deg(180, 180, 180, 360, 360, 360),
        (54, 54, 28, 9, 9, 9),
        (2.0, 1.98, 3.4445, 1.437, 0.871, 0.805, 0.261),
        3.0,
        0.5,
        footprint_diameter_m=0.128,
    ),
    "ur5e": URParams(
        "ur5e",
        (0.1625, 0, 0, 0.1333, 0.0997, 0.0996),
        (0, -0.425, -0.3922, 0, 0, 0),
        _deg(360, 360, 180, 360, 360, 360),
        _deg(180, 180, 180, 180, 180, 180),
        (150, 150, 150, 28, 28, 28),
        (4.0, 3.761, 8.058, 2.846, 1.37, 1.3, 0.365),
        5.0,
        0.85,
        footprint_diameter_m=0.149,
    ),
    "ur10e": URParams(
        "ur10e",
        (0.1807, 0, 0, 0.17415, 0.11985, 0.11655),
        (0, -0.6127, -0.57155, 0, 0, 0),
        _deg(360, 360, 180, 360, 360, 360),
        _deg(120, 120, 180, 180, 180, 180),
        (330, 330, 150, 54, 54, 54),
        (4.0, 7.369, 13.051, 3.989, 2.1, 1.98, 0.615),
        12.5,
        1.3,
        footprint_diameter_m=0.19,
    ),
    "ur16e": URParams(
        "ur16e",
        (0.1807, 0, 0, 0.17415, 0.11985, 0.11655),
        (0, -0.4784, -0.36, 0, 0, 0),
        _deg(360, 360, 180, 360, 360, 360),
        _deg(120, 120, 180, 180, 180, 180),
        (330, 330, 150, 54, 54, 54),
        (4.0, 7.369, 10.45, 4.321, 2.18, 2.033, 0.907),
        16.0,
        0.9,
        footprint_diameter_m=0.19,
    ),
    "ur20": URParams(
        "ur20",
        (0.2363, 0, 0, 0.201, 0.1593, 0.1543),
        (0, -0.862, -0.7287, 0, 0, 0),
        _deg(360, 360, 180, 360, 360, 360),
        _deg(120, 120, 150, 210, 210, 210),
        (738, 738, 433, 107, 107, 107),
        (4.0, 16.343, 29.632, 7.879, 3.054, 3.126, 0.926),
        20.0,
        1.75,
        footprint_diameter_m=0.245,
    ),
    "ur30": URParams(
        "ur30",
        (0.2363, 0, 0, 0.201, 0.1593, 0.1543),
        (0, -0.637, -0.5037, 0, 0, 0),
        _deg(360, 360, 180, 360, 360, 360),
        _deg(120, 120, 150, 210, 210, 210),
        (738, 738, 433, 107, 107, 107),
        (4.0, 16.343, 28.542, 7.156, 3.054, 3.126, 0.926),
        30.0,
        1.3,
        verified_limits=False,
        footprint_diameter_m=0.245,
    ),
}


def ur_params(name: str) -> URParams:
    """Parameters of a model by name ('ur5e', ...); raises RobotModelError listing the known names."""
    try:
        return UR_PARAMS[name.lower()]
    except KeyError:
        raise RobotModelError(f"unknown UR model {name!r}; known: {', '.join(UR_PARAMS)}") from None


def dh_link(params: URParams, i: int, theta: ArrayLike) -> FloatArray:
    """Standard DH transform (..., 4, 4) of joint i (0-based) from frame i to frame i + 1 at angles theta (...,)."""
    th = np.asarray(theta, dtype=np.float64)
    ct, st = np.cos(th), np.sin(th)
    ca, sa = np.cos(DH_ALPHA[i]), np.sin(DH_ALPHA[i])
    link = np.zeros(th.shape + (4, 4))
    link[..., 0, 0] = ct
    link[..., 0, 1] = -st * ca
    link[..., 0, 2] = st * sa
    link[..., 0, 3] = params.a[i] * ct
    link[..., 1, 0] = st
    link[..., 1, 1] = ct * ca
    link[..., 1, 2] = -ct * sa
    link[..., 1, 3] = params.a[i] * st
    link[..., 2, 1] = sa
    link[..., 2, 2] = ca
    link[..., 2, 3] = params.d[i]
    link[..., 3, 3] = 1.0
    return link


def dh_forward_kinematics(params: URParams, q: ArrayLike) -> FloatArray:
    """base_from_flange (..., 4, 4) from the DH table for joint angles q (..., 6) in radians (vectorised)."""
    qs = np.asarray(q, dtype=np.float64)
    pose = np.broadcast_to(np.eye(4), qs.shape[:-1] + (4, 4)).copy()
    for i in range(6):
        pose = pose @ dh_link(params, i, qs[..., i])
    return pose
