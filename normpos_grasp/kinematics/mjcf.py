"""MJCF text of a UR arm and its scene, built from the parameter table (used by robots/generate.py and,
for calibrated arms, at run time). Deterministic output: the same input gives the same bytes.

Body frames: `base` = DH frame 0 (the controller's base frame); body i = DH frame i-1 rotated by q_i about z,
so every joint axis is its body's z axis; the child body sits at Rz(theta_i) Tz(d_i) Tx(a_i) Rx(alpha_i). The
`flange` site is DH frame 6, the frame UR's actual_TCP_pose reports with a zero TCP offset.
"""

from __future__ import annotations

import math

import numpy as np

from normpos_grasp.kinematics.dh import DHChain
from normpos_grasp.kinematics.gripper import Gripper
from normpos_grasp.kinematics.shapes import ARM_LINKS, CollisionShape, arm_collision_shapes
from normpos_grasp.kinematics.ur_params import JOINT_NAMES, URParams
from normpos_grasp.typing import FloatArray

HOME_Q = (0.0, -math.pi / 2, math.pi / 2, -math.pi / 2, -math.pi / 2, 0.0)
_RGBA = (
    "0.15 0.15 0.15 1",
    "0.49 0.68 0.8 1",
    "0.82 0.82 0.82 1",
    "0.82 0.82 0.82 1",
    "0.49 0.68 0.8 1",
    "0.49 0.68 0.8 1",
    "0.6 0.6 0.6 1",
)


def fmt(value: float) -> str:
    """Shortest round-trip decimal of a float (17 significant digits at most), '-0' written as '0'."""
    v = float(value)
    if v == 0.0:
        return "0"
    text = repr(v)
    return text[:-2] if text.endswith(".0") else text


def _vec(values: FloatArray | tuple[float, ...] | list[float]) -> str:
    return " ".join(fmt(v) for v in values)


def quat_wxyz(rotation: FloatArray) -> FloatArray:
    """Unit quaternion (w, x, y, z) of a (3, 3) rotation (Shepperd's method), w >= 0."""
    r = np.asarray(rotation, dtype=np.float64)
    tr = r[0, 0] + r[1, 1] + r[2, 2]
    if tr > 0:
        s = 2.0 * math.sqrt(1.0 + tr)
        q = np.array([0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s])
    elif r[0, 0] > r[1, 1] and r[0, 0] > r[2, 2]:
        s = 2.0 * math.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2])
        q = np.array([(r[2, 1] - r[1, 2]) / s, 0.25 * s, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s])
    elif r[1, 1] > r[2, 2]:
        s = 2.0 * math.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2])
        q = np.array([(r[0, 2] - r[2, 0]) / s, (r[0, 1] + r[1, 0]) / s, 0.25 * s, (r[1, 2] + r[2, 1]) / s])
    else:
        s = 2.0 * math.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1])
        q = np.array([(r[1, 0] - r[0, 1]) / s, (r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, 0.25 * s])
    q = q / np.linalg.norm(q)
    return -q if q[0] < 0 else q


def _placement(pose: FloatArray) -> str:
    """MJCF pos/quat attributes of a (4, 4) pose (quat omitted when identity)."""
    text = f'pos="{_vec(pose[:3, 3])}"'
    q = quat_wxyz(pose[:3, :3])
    if not np.allclose(q, [1.0, 0.0, 0.0, 0.0], atol=0.0):
        text += f' quat="{_vec(q)}"'
    return text


def _geom(shape: CollisionShape, rgba: str) -> str:
    if shape.kind in ("capsule", "cylinder"):
        size = f"{fmt(shape.size[0])} {fmt(shape.size[1] / 2.0)}"
    elif shape.kind == "box":
        size = _vec([s / 2.0 for s in shape.size])
    else:
        size = fmt(shape.size[0])
    return f'<geom type="{shape.kind}" size="{size}" {_placement(shape.link_from_shape)} rgba="{rgba}"/>'


def _inertial(mass: float, shapes: list[CollisionShape]) -> str:
    """Inertial of a link: `mass` at the centre of its largest shape, solid-cylinder inertia (approximate)."""
    shape = max(shapes, key=lambda s: s.size[0] ** 2 * (s.size[1] if len(s.size) > 1 else s.size[0]))
    r, length = shape.size[0], shape.size[1] + (2.0 * shape.size[0] if shape.kind == "capsule" else 0.0)
    i_axis = 0.5 * mass * r * r
    i_side = mass * (3.0 * r * r + length * length) / 12.0
    inertia = _vec([round(i_side, 9), round(i_side, 9), round(i_axis, 9)])
    return f'<inertial {_placement(shape.link_from_shape)} mass="{fmt(mass)}" diaginertia="{inertia}"/>'


def arm_mjcf(
    params: URParams,
    chain: DHChain | None = None,
    model_name: str | None = None,
    gripper: Gripper | None = None,
    opening_m: float | None = None,
) -> str:
    """MJCF document of a UR arm: bodies per `ARM_LINKS`, hinge joints with limits, collision capsules,
    inertials from the link masses, position actuators, a `home` keyframe and `flange` site. With `gripper`,
    a fixed body `gripper` at the flange carries its collision shapes at `opening_m` (default fully open), its
    mass, and a `tcp` site."""
    chain = chain or DHChain.nominal(params)
    shapes = arm_collision_shapes(params)
    by_link = {link: [s for s in shapes if s.link == link] for link in ARM_LINKS}
    lines = [
        f'<mujoco model="{model_name or params.name}">',
        '  <compiler angle="radian" autolimits="true"/>',
        '  <option integrator="implicitfast"/>',
        "  <default>",
        '    <joint axis="0 0 1" armature="0.1"/>',
        '    <geom contype="1" conaffinity="1" group="3"/>',
        "  </default>",
        "  <worldbody>",
        '    <body name="base">',
        "      " + _inertial(params.masses[0], by_link["base"]),
    ]
    lines += ["      " + _geom(s, _RGBA[0]) for s in by_link["base"]]
    indent = "      "
    placement = np.eye(4)
    for i in range(6):
        link = ARM_LINKS[i + 1]
        lines.append(f'{indent}<body name="{link}" {_placement(placement)}>')
        indent += "  "
        lines.append(indent + _inertial(params.masses[i + 1], by_link[link]))
        limit = params.position_limit[i]
        rng = f' range="{fmt(-limit)} {fmt(limit)}"' if math.isfinite(limit) else ' limited="false"'
        damping = fmt(round(0.5 * params.effort_limit[i], 6))
        lines.append(f'{indent}<joint name="{JOINT_NAMES[i]}"{rng} damping="{damping}"/>')
        lines += [indent + _geom(s, _RGBA[i + 1]) for s in by_link[link]]
        placement = chain.link_transform(i)
    lines.append(f'{indent}<site name="flange" {_placement(placement)} size="0.005"/>')
    if gripper is not None:
        lines += _gripper_body(gripper, opening_m, placement, indent)
    for _ in range(6):
        indent = indent[:-2]
        lines.append(f"{indent}</body>")
    lines += ["    </body>", "  </worldbody>", "  <contact>"]
    # Neighbouring links overlap by construction at their shared joint. MuJoCo skips parent-child pairs except
    # those whose parent is welded to the world (base-shoulder), so that pair is listed too.
    lines.append('    <exclude body1="base" body2="shoulder"/>')
    for i in range(len(ARM_LINKS) - 2):
        lines.append(f'    <exclude body1="{ARM_LINKS[i]}" body2="{ARM_LINKS[i + 2]}"/>')
    if gripper is not None:
        lines.append('    <exclude body1="wrist_2" body2="gripper"/>')
    lines += ["  </contact>", "  <actuator>"]
    for i, joint in enumerate(JOINT_NAMES):
        effort = params.effort_limit[i]
        limit = params.position_limit[i]
        ctrl = f' ctrlrange="{fmt(-limit)} {fmt(limit)}"' if math.isfinite(limit) else ""
        lines.append(
            f'    <position name="{joint.removesuffix("_joint")}" joint="{joint}" kp="{fmt(20.0 * effort)}"'
            f' forcerange="{fmt(-effort)} {fmt(effort)}"{ctrl}/>'
        )
    lines += [
        "  </actuator>",
        "  <keyframe>",
        f'    <key name="home" qpos="{_vec(HOME_Q)}" ctrl="{_vec(HOME_Q)}"/>',
        "  </keyframe>",
        "</mujoco>",
    ]
    return "\n".join(lines) + "\n"


def _gripper_body(gripper: Gripper, opening_m: float | None, wrist3_from_flange: FloatArray, indent: str) -> list[str]:
    """Lines of the fixed `gripper` body (frame = flange) with its shapes, inertial and `tcp` site."""
    flange_from_tcp = gripper.flange_from_tcp
    shapes = [s.transformed(flange_from_tcp, "gripper") for s in gripper.collision_shapes(opening_m)]
    centre = np.eye(4)
    centre[:3, 3] = flange_from_tcp[:3, 3] / 2.0
    r = max(0.02, float(np.linalg.norm(flange_from_tcp[:3, 3])) / 4.0)
    i_val = round(0.4 * gripper.mass_kg * r * r, 9)
    out = [
        f'{indent}<body name="gripper" {_placement(wrist3_from_flange)}>',
        f'{indent}  <inertial {_placement(centre)} mass="{fmt(gripper.mass_kg)}" diaginertia="{_vec([i_val] * 3)}"/>',
    ]
    out += [f"{indent}  " + _geom(s, "0.3 0.3 0.3 1") for s in shapes]
    out += [f'{indent}  <site name="tcp" {_placement(flange_from_tcp)} size="0.005"/>', f"{indent}</body>"]
    return out


def scene_mjcf(robot_file: str, model_name: str) -> str:
    """A scene including `robot_file` (relative path): floor at z = 0, light, an offscreen-friendly view."""
    return (
        "\n".join(
            [
                f'<mujoco model="{model_name} scene">',
                f'  <include file="{robot_file}"/>',
                '  <statistic center="0.3 0 0.4" extent="1.2"/>',
                '  <visual><headlight diffuse="0.6 0.6 0.6" ambient="0.3 0.3 0.3"/></visual>',
                "  <asset>",
                '    <texture type="2d" name="grid" builtin="checker" rgb1="0.2 0.3 0.4" rgb2="0.1 0.2 0.3"'
                ' width="300" height="300"/>',
                '    <material name="grid" texture="grid" texrepeat="5 5" reflectance="0.1"/>',
                "  </asset>",
                "  <worldbody>",
                '    <light pos="0 0 2.5" dir="0 0 -1" directional="true"/>',
                '    <geom name="floor" type="plane" size="0 0 0.05" material="grid" contype="1" conaffinity="1"'
                ' pos="0 0 -0.001"/>',
                "  </worldbody>",
                "</mujoco>",
            ]
        )
        + "\n"
    )
