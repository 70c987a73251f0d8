"""Physics validation of one grasp in MuJoCo: approach, close (or seal), lift, move sideways, hold, judge.

`validate_grasp` builds a MuJoCo scene holding the target (its convex decomposition, or exact primitives for
boxes and spheres), its neighbours (free bodies in their true poses, far ones fixed), the static cell geometry
(boxes) and the gripper as a mocap-driven hand: a parallel-jaw gripper whose two coupled fingers close at a set
speed and squeeze with a force limit (position servo with saturated force, like a Robotiq 2F-85's force setting), or
a suction cup on a compliant bellows whose vacuum holds the part with pressure x area once a seal check on the true
surface passed (MuJoCo adhesion actuator). It then replays the pick and reports:

- 'collision': the hand hit the cell or a neighbour (or landed on the target before closing) harder than
  `collision_force_n` or deeper than `collision_penetration_m`: a real arm would stop;
- 'missed': after closing / sealing the gripper does not touch the target;
- 'drop': the target is not in the hand at the end, or was not lifted;
- 'slip': it is in the hand but moved relative to the TCP beyond `slip_tolerance_m` / `slip_tolerance_rad`;
- 'held': it stayed in the hand.

TCP frame: z is the approach direction (into the object), x the jaw closing direction. Metres, seconds, newtons.
The simulation is deterministic: the same inputs give bit-identical results.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from normpos_grasp.errors import InputError, SimulationError
from normpos_grasp.geometry.transforms import invert_pose, make_pose, rotation_angle
from normpos_grasp.records.template import Template
from normpos_grasp.sim.physics_decompose import DecompositionOptions, collision_hulls, convex_decomposition
from normpos_grasp.sim.physics_suction import SealCheck, SealOptions, check_seal, vacuum_force_n
from normpos_grasp.typing import FloatArray
from normpos_grasp.validation import as_float_array, check_pose

if TYPE_CHECKING:
    import mujoco

logger = logging.getLogger(__name__)

OUTCOMES = ("held", "slip", "drop", "collision", "missed")

StaticBox = tuple[str, FloatArray, FloatArray]  # (name, world_from_box (4, 4), full size (3,))


@dataclass(frozen=True, eq=False)
class GripperSpec:
    """What physics needs to know about a gripper (TCP frame: z approach, x closing). Metres, newtons.

    kind: 'parallel' or 'suction'. stroke_m: maximum jaw opening. grip_force_n: squeeze force per finger
    (force limit of the jaw drive). closing_speed_m_s: jaw closing speed (both fingers together).
    finger_length_m / finger_width_m / finger_thickness_m: finger box along z / y / x. tip_beyond_tcp_m: how far
    the fingertips reach past the TCP along +z. palm_size_m: (x, y, z) palm box right behind the fingers, used
    when `body_shapes` is empty. body_shapes: the rest of the hand in the TCP frame as (kind, size, tcp_from_shape
    (4, 4)) with python-fcl size conventions (kinematics CollisionShape), kinds box / cylinder / capsule / sphere.
    finger_friction: Coulomb friction of the pads; torsional_friction_m: torsional friction of the pads (m).
    cup_diameter_m: suction cup diameter; vacuum_kpa: pressure difference of the vacuum; vacuum_efficiency:
    share of the ideal pressure x area force the cup delivers; bellows_travel_m / bellows_stiffness_n_m:
    compliance of the cup along z; cup_friction: friction of the lip. tool_radius_m / tool_length_m: the
    suction tool's shaft behind the cup (when `body_shapes` is empty).
    """

    kind: str = "parallel"
    name: str = "2f85"
    stroke_m: float = 0.085
    grip_force_n: float = 100.0
    closing_speed_m_s: float = 0.1
    finger_length_m: float = 0.062
    finger_width_m: float = 0.027
    finger_thickness_m: float = 0.02
    tip_beyond_tcp_m: float = 0.013
    palm_size_m: tuple[float, float, float] = (0.125, 0.075, 0.09)
    finger_friction: float = 0.9
    torsional_friction_m: float = 0.004
    cup_diameter_m: float = 0.03
    vacuum_kpa: float = 60.0
    vacuum_efficiency: float = 0.8
    bellows_travel_m: float = 0.01
    bellows_stiffness_n_m: float = 400.0
    cup_friction: float = 0.8
    tool_radius_m: float = 0.012
    tool_length_m: float = 0.1
    body_shapes: tuple[tuple[str, tuple[float, ...], FloatArray], ...] = ()

    def __post_init__(self) -> None:
        if self.kind not in ("parallel", "suction"):
            raise InputError(f"GripperSpec.kind must be 'parallel' or 'suction', got {self.kind!r}")
        positive = (
            "stroke_m",
            "grip_force_n",
            "closing_speed_m_s",
            "finger_length_m",
            "finger_width_m",
            "finger_thickness_m",
            "cup_diameter_m",
            "vacuum_kpa",
            "bellows_travel_m",
        )
        for name in positive:
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise InputError(f"GripperSpec.{name} must be a positive finite number, got {value!r}")

    @property
    def vacuum_force_n(self) -> float:
        """Holding force of a sealed cup, N."""
        return vacuum_force_n(self.cup_diameter_m, self.vacuum_kpa, self.vacuum_efficiency)

    @classmethod
    def preset(cls, name: str) -> GripperSpec:
        """Built-in specs: '2f85' (Robotiq 2F-85 class: 85 mm stroke, 20-235 N, here 100 N), '2f140' (140 mm,
        10-125 N, here 60 N), 'suction' (30 mm cup, 60 kPa)."""
        presets = {
            "2f85": cls(),
            "2f140": cls(
                name="2f140",
                stroke_m=0.14,
                grip_force_n=60.0,
                finger_length_m=0.101,
                palm_size_m=(0.195, 0.075, 0.12),
            ),
            "suction": cls(kind="suction", name="suction"),
        }
        if name not in presets:
            raise InputError(f"unknown gripper preset {name!r}; expected one of {sorted(presets)}")
        return presets[name]

    @classmethod
    def from_gripper(cls, gripper: Any, **overrides: Any) -> GripperSpec:
        """Spec from a `normpos_grasp.kinematics.gripper.Gripper`: kind, name, stroke, finger boxes, cup diameter
        and stroke, and the hand's other collision shapes (in the TCP frame) are taken over; forces, speeds and
        friction come from the preset of the same kind (Gripper carries none). Attributes grip_force_n /
        max_force_n, when an object has them, set the force. `overrides` replace fields afterwards."""
        if isinstance(gripper, GripperSpec):
            return replace(gripper, **overrides)
        kind = str(getattr(gripper, "kind", "parallel"))
        kind = "suction" if "suction" in kind or "vacuum" in kind else "parallel"
        name = str(getattr(gripper, "name", "2f85" if kind == "parallel" else "suction"))
        stroke = float(getattr(gripper, "stroke_m", 0.0) or 0.0)
        base = cls.preset("suction") if kind == "suction" else cls.preset("2f140" if stroke > 0.1 else "2f85")
        values: dict[str, Any] = {"kind": kind, "name": name}
        if stroke > 0:
            values["stroke_m"] = stroke
        for attr in ("grip_force_n", "max_force_n", "force_n"):
            force = getattr(gripper, attr, None)
            if force:
                values["grip_force_n"] = float(force)
                break
        finger = getattr(gripper, "finger", None)
        if finger is not None:
            values["finger_length_m"] = float(finger.length_m)
            values["finger_thickness_m"] = float(finger.thickness_m)
            values["finger_width_m"] = float(finger.width_m)
            values["tip_beyond_tcp_m"] = float(finger.tip_beyond_tcp_m)
        for attr in ("cup_diameter_m", "closing_speed_m_s", "vacuum_kpa"):
            value = getattr(gripper, attr, None)
            if value:
                values[attr] = float(value)
        if getattr(gripper, "cup_stroke_m", 0.0):
            values["bellows_travel_m"] = float(gripper.cup_stroke_m)
        shapes_fn = getattr(gripper, "collision_shapes", None)
        if callable(shapes_fn):
            shapes = list(shapes_fn(stroke) if kind == "parallel" and stroke > 0 else shapes_fn())
            if kind == "parallel" and finger is not None:
                shapes = shapes[:-2]  # the two finger boxes come last; physics moves its own fingers
            body = []
            for sh in shapes:
                pose = np.asarray(sh.link_from_shape, dtype=np.float64)
                reach = _shape_max_z(str(sh.kind), tuple(float(v) for v in sh.size), pose)
                travel = float(values.get("bellows_travel_m", base.bellows_travel_m))
                if kind == "suction" and reach > -travel - 1e-3:
                    continue  # the cup itself: physics models it on its bellows
                body.append((str(sh.kind), tuple(float(v) for v in sh.size), pose))
            values["body_shapes"] = tuple(body)
        values.update(overrides)
        return replace(base, **values)


def _shape_max_z(kind: str, size: tuple[float, ...], tcp_from_shape: FloatArray) -> float:
    """Largest TCP-frame z reached by a primitive (python-fcl sizes), metres."""
    rot, centre = tcp_from_shape[:3, :3], tcp_from_shape[:3, 3]
    if kind == "box":
        return float(centre[2] + np.abs(rot[2, :]) @ (np.asarray(size) / 2.0))
    if kind == "sphere":
        return float(centre[2] + size[0])
    radius, length = size[0], size[1]
    axis_z = abs(float(rot[2, 2]))
    radial = math.sqrt(max(0.0, 1.0 - axis_z**2)) * radius
    half = length / 2.0 * axis_z
    return float(centre[2] + half + (radius if kind == "capsule" else radial))


@dataclass(frozen=True)
class PhysicsOptions:
    """Settings of the pick replay. Seconds, metres, newtons, radians.

    timestep_s: MuJoCo step. settle_s: the scene settles with the hand at the pre-grasp pose first.
    approach_m / approach_s: straight approach along TCP z, distance and duration. press_m: how far a suction
    cup is driven past the surface (compresses the bellows). close_hold_s: time after the jaws stop (or the
    vacuum builds) before lifting. lift_m / lift_s: vertical lift (world +z); lift_to_z_m: when set, the lift
    continues until the TCP is at least at this world height (out of a bin), its time growing as sqrt(distance).
    move_m / move_s: sideways move
    (world +x, minimum-jerk: peak acceleration 5.8 * move_m / move_s^2). hold_s: hold at the end.
    slip_tolerance_m / slip_tolerance_rad: allowed motion of the object relative to the TCP from grip to end.
    collision_force_n / collision_penetration_m: a hand contact with the cell or a neighbour above either is a
    collision; target_collision_force_n: the same for the hand pressing on the target before closing (a protective
    stop of the arm; lighter pushes just move the part). release_s: after a failed pick the jaws open (the vacuum
    stops) and the hand rises 5 cm for this long. rest_s / rest_speed_m_s / rest_spin_rad_s: then (after the hold
    of a held pick too) the run goes on, the hand where it is, until no free part moves faster than
    rest_speed_m_s and turns faster than rest_spin_rad_s, for at most rest_s: the final poses are where the parts
    came to rest (a part still falling would start the next pick in mid-air). neighbour_radius_m: neighbours
    whose bounding sphere comes closer than this to the target's centre are simulated; the rest stay fixed where
    they are (a simulated part leaning on one keeps its support instead of falling through it).
    object_friction / static_friction: Coulomb friction of parts and cell geometry.
    check_every: contact checks every this many steps. seal: suction seal criteria.
    decomposition: convex decomposition settings for non-convex parts.
    """

    timestep_s: float = 0.002
    settle_s: float = 0.1
    approach_m: float = 0.06
    approach_s: float = 0.3
    press_m: float = 0.004
    close_hold_s: float = 0.2
    lift_m: float = 0.1
    lift_s: float = 0.5
    lift_to_z_m: float | None = None
    move_m: float = 0.15
    move_s: float = 0.5
    hold_s: float = 0.3
    slip_tolerance_m: float = 0.01
    slip_tolerance_rad: float = 0.2
    collision_force_n: float = 40.0
    target_collision_force_n: float = 150.0
    release_s: float = 0.5
    rest_s: float = 1.5
    rest_speed_m_s: float = 0.005
    rest_spin_rad_s: float = 0.1
    collision_penetration_m: float = 0.004
    neighbour_radius_m: float = 0.25
    object_friction: float = 0.5
    static_friction: float = 0.5
    check_every: int = 5
    seal: SealOptions = field(default_factory=SealOptions)
    decomposition: DecompositionOptions = field(default_factory=DecompositionOptions)


@dataclass(frozen=True, eq=False)
class PhysicsResult:
    """Outcome of one simulated pick.

    outcome: one of OUTCOMES. reason: a short human-readable cause. slip_m / slip_rad: motion of the object relative
    to what holds it (the hand; the cup for suction) from grip to end (translation norm, rotation angle).
    object_offset_m (3,): final object position in the TCP frame minus the planned one (true poses), metres.
    tcp_from_object (4, 4): final object pose in the TCP frame (the hand's actual pose).
    lift_m: how far the object rose.
    max_penetration_m: deepest contact during the run. grip_force_n: normal force between hand and target after
    closing. collision_with: names of what the hand hit ('' if nothing). seal: the suction seal check (None for
    parallel jaws). sim_time_s: simulated time; wall_time_s: compute time. n_pieces: convex pieces of the target.
    world_from_object_final (4, 4) / world_from_neighbours_final (K, 4, 4): poses at the end of the run (the
    target where it ended, in the hand or not; neighbours held fixed keep their poses).
    """

    outcome: str
    reason: str
    slip_m: float
    slip_rad: float
    object_offset_m: FloatArray
    tcp_from_object: FloatArray
    lift_m: float
    max_penetration_m: float
    grip_force_n: float
    collision_with: str
    seal: SealCheck | None
    sim_time_s: float
    wall_time_s: float
    n_pieces: int
    world_from_object_final: FloatArray = field(default_factory=lambda: np.eye(4))
    world_from_neighbours_final: FloatArray = field(default_factory=lambda: np.zeros((0, 4, 4)))

    @property
    def success(self) -> bool:
        return self.outcome == "held"

    def as_dict(self) -> dict[str, Any]:
        """Flat JSON-friendly record (floats rounded to 1e-9)."""
        return {
            "outcome": self.outcome,
            "reason": self.reason,
            "slip_m": round(self.slip_m, 9),
            "slip_rad": round(self.slip_rad, 9),
            "offset_x_m": round(float(self.object_offset_m[0]), 9),
            "offset_y_m": round(float(self.object_offset_m[1]), 9),
            "offset_z_m": round(float(self.object_offset_m[2]), 9),
            "lift_m": round(self.lift_m, 9),
            "max_penetration_m": round(self.max_penetration_m, 9),
            "grip_force_n": round(self.grip_force_n, 6),
            "collision_with": self.collision_with,
            "seal": "" if self.seal is None else ("sealed" if self.seal.sealed else self.seal.reason),
            "sim_time_s": round(self.sim_time_s, 6),
        }


# -- geometry of bodies -------------------------------------------------------------------------------
def _fmt(values: Any) -> str:
    return " ".join(f"{float(v):.12g}" for v in np.asarray(values, dtype=np.float64).reshape(-1))


def _quat_wxyz(rotation: FloatArray) -> FloatArray:
    import mujoco

    q = np.zeros(4)
    mujoco.mju_mat2Quat(q, np.ascontiguousarray(rotation, dtype=np.float64).reshape(-1))
    return q


def _primitive(template: Template) -> tuple[str, FloatArray] | None:
    """('box', full size) or ('sphere', (r,)) when the mesh is exactly that primitive centred in its frame."""
    mesh = template.mesh
    v = np.asarray(mesh.vertices, dtype=np.float64)
    lo, hi = v.min(axis=0), v.max(axis=0)
    ext = hi - lo
    centred = bool(np.allclose((lo + hi) / 2.0, 0.0, atol=1e-9 + 1e-6 * float(ext.max())))
    vol = float(mesh.volume)
    if centred and abs(vol - float(np.prod(ext))) < 1e-3 * float(np.prod(ext)) and len(v) <= 64:
        return "box", ext
    r = float(np.linalg.norm(v, axis=1).max())
    rmin = float(np.linalg.norm(v, axis=1).min())
    if centred and r > 0 and rmin > 0.98 * r and abs(vol - 4.0 / 3.0 * np.pi * r**3) < 0.03 * vol:
        return "sphere", np.array([r])
    return None


def collision_pieces(template: Template, options: DecompositionOptions | None = None) -> list[tuple[str, FloatArray]]:
    """Collision geometry of a template in its object frame: [('box', size (3,))], [('sphere', (r,))] or
    [('mesh', hull vertices (K, 3)), ...] from the convex decomposition, each one MuJoCo accepts
    (`collision_hulls`: flat or thin pieces thickened, pieces without area dropped). Metres."""
    prim = _primitive(template)
    if prim is not None:
        return [prim]
    pieces = convex_decomposition(
        np.asarray(template.mesh.vertices, dtype=np.float64), np.asarray(template.mesh.faces), options
    )
    return [("mesh", p) for p in collision_hulls([p.vertices for p in pieces])]


def _hand_scene_xml(
    name: str,
    timestep_s: float,
    assets: list[str],
    world_geoms: list[str],
    hand: str,
    world_from_hand: FloatArray,
    exclude: str,
    actuators: str,
    equality: str = "",
) -> str:
    """MJCF of a scene with a mocap-welded hand (from `_hand_xml`) starting at `world_from_hand` (4, 4): the shared
    contact settings, `assets`, the `world_geoms` (static geoms and part bodies), extra `equality` constraints."""
    pos, quat = _fmt(world_from_hand[:3, 3]), _fmt(_quat_wxyz(world_from_hand[:3, :3]))
    return (
        f'<mujoco model="{name}"><compiler angle="radian" boundmass="1e-6" boundinertia="1e-12"/>'
        f'<option timestep="{timestep_s:.12g}" integrator="implicitfast" cone="elliptic" impratio="10">'
        '<flag multiccd="enable"/></option>'
        '<default><geom solref="0.004 1" solimp="0.95 0.99 0.001"/></default>'
        f"<asset>{''.join(assets)}</asset>"
        f"<worldbody>{''.join(world_geoms)}{hand}"
        f'<body name="hand_mocap" mocap="true" pos="{pos}" quat="{quat}"/>'
        "</worldbody>"
        '<equality><weld body1="hand" body2="hand_mocap" relpose="0 0 0 1 0 0 0" solref="0.005 1"/>'
        f"{equality}</equality>"
        f"<contact>{exclude}</contact><actuator>{actuators}</actuator></mujoco>"
    )


def _static_geoms(static_boxes: list[StaticBox] | tuple[StaticBox, ...], friction: float, lowest: float) -> list[str]:
    """MJCF geoms of the fixed cell boxes (name, world pose (4, 4), full size (3,) m); without any, a floor plane at
    height `lowest` (m) under the parts."""
    statics = []
    sf = f'friction="{friction:.6g} 0.003 0.0001"'
    for k, (name, pose_in, size_in) in enumerate(static_boxes):
        pose = check_pose(pose_in, f"static box {name!r} pose", tol=1e-5)
        size = as_float_array(size_in, f"static box {name!r} size", (3,))
        statics.append(
            f'<geom name="static{k}_{_safe(name)}" type="box" size="{_fmt(size / 2.0)}" pos="{_fmt(pose[:3, 3])}" '
            f'quat="{_fmt(_quat_wxyz(pose[:3, :3]))}" {sf}/>'
        )
    if not statics:
        statics.append(f'<geom name="static_floor" type="plane" size="0 0 1" pos="0 0 {lowest:.12g}" {sf}/>')
    return statics


def _object_body_xml(
    name: str,
    template: Template,
    world_from_object: FloatArray,
    pieces: list[tuple[str, FloatArray]],
    friction: float,
    assets: list[str],
    fixed: bool = False,
) -> str:
    """MJCF body of a part at `world_from_object`: a free body, or with `fixed` one welded where it is (it carries
    what rests on it and does not move)."""
    mesh = template.mesh
    volume = max(float(mesh.volume), 1e-12)
    inertia = np.asarray(mesh.moment_inertia, dtype=np.float64) * (template.mass_kg / volume)
    com = np.asarray(mesh.center_mass, dtype=np.float64)
    eig = np.linalg.eigvalsh(inertia)
    floor = max(float(eig.max()) * 1e-3, 1e-12)
    inertia = inertia + np.eye(3) * max(0.0, floor - float(eig.min()))
    full = _fmt([inertia[0, 0], inertia[1, 1], inertia[2, 2], inertia[0, 1], inertia[0, 2], inertia[1, 2]])
    geoms = []
    for j, (kind, data) in enumerate(pieces):
        common = f'name="{name}_g{j}" friction="{friction:.6g} 0.003 0.0001" mass="0"'
        if kind == "box":
            geoms.append(f'<geom type="box" size="{_fmt(np.asarray(data) / 2.0)}" {common}/>')
        elif kind == "sphere":
            geoms.append(f'<geom type="sphere" size="{float(data[0]):.12g}" {common}/>')
        else:
            assets.append(f'<mesh name="{name}_m{j}" vertex="{_fmt(data)}" inertia="convex"/>')
            geoms.append(f'<geom type="mesh" mesh="{name}_m{j}" {common}/>')
    pose = world_from_object
    joint = "" if fixed else f'<freejoint name="{name}_free"/>'
    return (
        f'<body name="{name}" pos="{_fmt(pose[:3, 3])}" quat="{_fmt(_quat_wxyz(pose[:3, :3]))}">'
        f"{joint}"
        f'<inertial pos="{_fmt(com)}" mass="{template.mass_kg:.12g}" fullinertia="{full}"/>'
        f"{''.join(geoms)}</body>"
    )


def _body_geoms(shapes: tuple[tuple[str, tuple[float, ...], FloatArray], ...]) -> str:
    """MJCF geoms of the hand's rigid shapes (TCP frame, python-fcl sizes); 1 kg spread over them."""
    out = []
    mass = 1.0 / max(len(shapes), 1)
    for i, (kind, size, pose) in enumerate(shapes):
        if kind == "box":
            msize = _fmt(np.asarray(size) / 2.0)
        elif kind in ("cylinder", "capsule"):
            msize = _fmt([size[0], size[1] / 2.0])
        elif kind == "sphere":
            msize = _fmt([size[0]])
        else:
            raise InputError(f"hand shape {i}: kind must be box, cylinder, capsule or sphere, got {kind!r}")
        out.append(
            f'<geom name="hand_body{i}" type="{kind}" size="{msize}" pos="{_fmt(pose[:3, 3])}" '
            f'quat="{_fmt(_quat_wxyz(pose[:3, :3]))}" condim="3" mass="{mass:.6g}"/>'
        )
    return "".join(out)


def _hand_xml(spec: GripperSpec, world_from_tcp: FloatArray, opening_m: float) -> tuple[str, str, str, str]:
    """(hand body xml, actuator xml, contact-exclude xml, equality xml) of the mocap-driven hand; the body frame is
    the TCP. The two jaws of a parallel gripper are coupled (equal travel, as the 2F-85's single drive and
    linkage move them): each drive still saturates at `grip_force_n`, but the jaws cannot drift together along
    the closing axis, which two independent force-saturated servos let a gripped part do (both saturated, nothing
    holds the pair in place: a part gripped across an inclined closing axis slid downhill with both fingers until
    the upper finger came within the servo band of its stop, half the part's width, 10-13 mm)."""
    pos, quat = _fmt(world_from_tcp[:3, 3]), _fmt(_quat_wxyz(world_from_tcp[:3, :3]))
    grip_friction = f'friction="{spec.finger_friction:.6g} {spec.torsional_friction_m:.6g} 0.0001"'
    if spec.kind == "parallel":
        tip = spec.tip_beyond_tcp_m
        length, width, thick = spec.finger_length_m, spec.finger_width_m, spec.finger_thickness_m
        half_stroke = spec.stroke_m / 2.0
        palm = spec.palm_size_m
        default_body = [("box", palm, make_pose(translation=[0.0, 0.0, tip - length - palm[2] / 2.0]))]
        fz = tip - length / 2.0
        band = 0.008  # the servo saturates at the force limit once 8 mm behind its target
        kp = spec.grip_force_n / band
        finger_mass = 0.05
        kv = 2.0 * 0.7 * math.sqrt(kp * finger_mass)
        fingers = []
        for side, sign in (("left", -1.0), ("right", 1.0)):
            x = sign * (half_stroke + thick / 2.0)
            fingers.append(
                f'<body name="hand_{side}" gravcomp="1">'
                f'<joint name="jaw_{side}" type="slide" axis="{-sign:g} 0 0" range="0 {half_stroke:.12g}" '
                f'damping="{kv:.6g}" limited="true"/>'
                f'<geom name="hand_{side}_finger" type="box" '
                f'size="{thick / 2:.12g} {width / 2:.12g} {length / 2:.12g}" '
                f'pos="{x:.12g} 0 {fz:.12g}" mass="{finger_mass:g}" condim="4" {grip_friction}/></body>'
            )
        body = (
            f'<body name="hand" pos="{pos}" quat="{quat}" gravcomp="1"><freejoint name="hand_free"/>'
            f"{_body_geoms(spec.body_shapes or tuple(default_body))}{''.join(fingers)}</body>"
        )
        limit = half_stroke + band
        actuators = "".join(
            f'<position name="drive_{side}" joint="jaw_{side}" kp="{kp:.6g}" ctrlrange="0 {limit:.12g}" '
            f'forcerange="{-spec.grip_force_n:.6g} {spec.grip_force_n:.6g}"/>'
            for side in ("left", "right")
        )
        exclude = '<exclude body1="hand_left" body2="hand_right"/>'
        coupling = '<joint joint1="jaw_left" joint2="jaw_right" polycoef="0 1 0 0 0" solref="0.005 1"/>'
        return body, actuators, exclude, coupling
    cup_h = 0.006
    r = spec.cup_diameter_m / 2.0
    travel = spec.bellows_travel_m
    cup_friction = f'friction="{spec.cup_friction:.6g} {spec.torsional_friction_m:.6g} 0.0001"'
    tool_z = -travel - cup_h - spec.tool_length_m / 2.0 - 0.002
    tool = (("cylinder", (spec.tool_radius_m, spec.tool_length_m), make_pose(translation=[0.0, 0.0, tool_z])),)
    body = (
        f'<body name="hand" pos="{pos}" quat="{quat}" gravcomp="1"><freejoint name="hand_free"/>'
        f"{_body_geoms(spec.body_shapes or tool)}"
        f'<body name="hand_cup" gravcomp="1">'
        f'<joint name="bellows" type="slide" axis="0 0 -1" range="0 {travel:.12g}" limited="true" '
        f'stiffness="{spec.bellows_stiffness_n_m:.6g}" damping="40"/>'
        f'<geom name="hand_cup_lip" type="cylinder" size="{r:.12g} {cup_h / 2:.12g}" pos="0 0 {-cup_h / 2:.12g}" '
        f'mass="0.05" condim="4" {cup_friction}/></body></body>'
    )
    return body, "", "", ""


# -- validation ---------------------------------------------------------------------------------------
def _min_jerk(s: float) -> float:
    s = min(max(s, 0.0), 1.0)
    return s**3 * (10.0 - 15.0 * s + 6.0 * s * s)


@dataclass
class _Monitor:
    """Contact bookkeeping during the run."""

    groups: np.ndarray  # geom id -> 0 static, 1 target, 2 neighbour, 3 hand
    names: list[str]
    max_penetration: float = 0.0
    collision: str = ""

    def check(self, data: mujoco.MjData, opts: PhysicsOptions, target_counts: bool) -> tuple[bool, float]:
        """Update penetration / collision state; returns (hand touches target, normal force hand-target)."""
        n = data.ncon
        if n == 0:
            return False, 0.0
        geom = np.asarray(data.contact.geom[:n])
        dist = np.asarray(data.contact.dist[:n])
        adr = np.asarray(data.contact.efc_address[:n])
        efc = np.asarray(data.efc_force)
        force = np.zeros(n)
        active = adr >= 0
        force[active] = np.abs(efc[adr[active]])
        g = self.groups[geom]
        self.max_penetration = max(self.max_penetration, float(max(0.0, -dist.min())))
        hand = (g == 3).any(axis=1)
        other = np.where(g[:, 0] == 3, g[:, 1], g[:, 0])
        touching = hand & (other == 1) & (dist < 0.0005)
        grip = float(force[touching].sum())
        deep = -dist > opts.collision_penetration_m
        bad = hand & ((other == 0) | (other == 2)) & ((force > opts.collision_force_n) | deep)
        if target_counts:  # landing on the target before closing: only a hard hit stops the arm
            bad |= hand & (other == 1) & ((force > opts.target_collision_force_n) | deep)
        if bad.any() and not self.collision:
            k = int(np.argmax(bad))
            a, b = geom[k]
            self.collision = self.names[b] if g[k, 0] == 3 else self.names[a]
        return bool(touching.any()), grip


def validate_grasp(
    target: Template,
    world_from_object: FloatArray,
    neighbours: list[tuple[Template, FloatArray]] | tuple[tuple[Template, FloatArray], ...],
    static_boxes: list[StaticBox] | tuple[StaticBox, ...],
    gripper: GripperSpec | Any,
    world_from_tcp: FloatArray,
    opening_m: float,
    options: PhysicsOptions | None = None,
) -> PhysicsResult:
    """Replay a pick of `target` (at `world_from_object` (4, 4), its true pose) in MuJoCo and judge it.

    neighbours: other parts with their true poses (free bodies). static_boxes: (name, world_from_box (4, 4),
    full size (3,)) of the cell (table, bin walls); when empty, a floor is put under the lowest part.
    gripper: a GripperSpec, or a kinematics Gripper (converted with GripperSpec.from_gripper).
    world_from_tcp (4, 4): grasp pose (z approach, x closing). opening_m: jaw opening before closing (ignored
    for suction). Raises InputError for bad poses / openings, SimulationError if MuJoCo rejects the scene or
    the state diverges.
    """
    import mujoco

    t_wall = time.perf_counter()
    opts = options or PhysicsOptions()
    spec = gripper if isinstance(gripper, GripperSpec) else GripperSpec.from_gripper(gripper)
    w_obj = check_pose(world_from_object, "world_from_object", tol=1e-5)
    w_tcp = check_pose(world_from_tcp, "world_from_tcp", tol=1e-5)
    if spec.kind == "parallel" and not (0.0 < opening_m <= spec.stroke_m + 1e-9):
        raise InputError(
            f"opening_m must be in (0, {spec.stroke_m}] for gripper {spec.name!r}, got {opening_m!r}; "
            "choose a grasp whose width fits the stroke"
        )

    # the scene
    assets: list[str] = []
    bodies = []
    target_pieces = collision_pieces(target, opts.decomposition)
    bodies.append(_object_body_xml("target", target, w_obj, target_pieces, opts.object_friction, assets))
    centre = w_obj[:3, :3] @ np.asarray(target.mesh.bounding_sphere.primitive.center) + w_obj[:3, 3]
    kept = 0
    neighbour_poses = []
    simulated: list[int] = []
    lowest = float((np.asarray(target.mesh.vertices) @ w_obj[:3, :3].T + w_obj[:3, 3])[:, 2].min())
    for i, (tmpl, pose_in) in enumerate(neighbours):
        pose = check_pose(pose_in, f"neighbours[{i}] pose", tol=1e-5)
        neighbour_poses.append(pose)
        sphere = tmpl.mesh.bounding_sphere.primitive
        c = pose[:3, :3] @ np.asarray(sphere.center) + pose[:3, 3]
        far = bool(np.linalg.norm(c - centre) - float(sphere.radius) > opts.neighbour_radius_m)
        if not far:
            kept += 1
            simulated.append(i)
        lowest = min(lowest, float((np.asarray(tmpl.mesh.vertices) @ pose[:3, :3].T + pose[:3, 3])[:, 2].min()))
        pieces = collision_pieces(tmpl, opts.decomposition)
        # a far neighbour stays in the scene, fixed where it is: a simulated part leaning on it keeps its support
        bodies.append(_object_body_xml(f"nb{i}", tmpl, pose, pieces, opts.object_friction, assets, fixed=far))
    statics = _static_geoms(static_boxes, opts.static_friction, lowest)
    pre = w_tcp @ make_pose(translation=[0.0, 0.0, -opts.approach_m])
    opening = min(opening_m, spec.stroke_m) if spec.kind == "parallel" else 0.0
    hand, actuators, exclude, coupling = _hand_xml(spec, pre, opening)
    vacuum_eq = (
        '<weld name="vacuum" body1="hand_cup" body2="target" active="false" solref="0.004 1"/>'
        if spec.kind == "suction"
        else ""
    )
    xml = _hand_scene_xml(
        "grasp_check", opts.timestep_s, assets, statics + bodies, hand, pre, exclude, actuators, coupling + vacuum_eq
    )
    try:
        model = mujoco.MjModel.from_xml_string(xml)
    except ValueError as exc:
        raise SimulationError(f"MuJoCo rejected the grasp-check scene: {exc}") from exc
    data = mujoco.MjData(model)

    groups = np.zeros(model.ngeom, dtype=np.int64)
    names = []
    hand_body = model.body("hand").id
    target_body = model.body("target").id
    for gid in range(model.ngeom):
        body = int(model.geom_bodyid[gid])
        root = int(model.body_rootid[body])
        if body == target_body:
            groups[gid] = 1
        elif root == hand_body:
            groups[gid] = 3
        elif body != 0:
            groups[gid] = 2
        names.append(model.geom(gid).name or f"geom{gid}")
    monitor = _Monitor(groups, names)

    if spec.kind == "parallel":
        q0 = min(max((spec.stroke_m - opening) / 2.0, 0.0), spec.stroke_m / 2.0)
        for side in ("left", "right"):
            data.qpos[model.joint(f"jaw_{side}").qposadr[0]] = q0
            data.ctrl[model.actuator(f"drive_{side}").id] = q0
    mujoco.mj_forward(model, data)

    quat = _quat_wxyz(w_tcp[:3, :3])
    mocap = int(model.body("hand_mocap").mocapid[0])
    data.mocap_quat[mocap] = quat
    dt = opts.timestep_s
    seal: SealCheck | None = None
    if spec.kind == "suction":
        import trimesh

        mesh_world = trimesh.Trimesh(
            vertices=np.asarray(target.mesh.vertices) @ w_obj[:3, :3].T + w_obj[:3, 3],
            faces=np.asarray(target.mesh.faces),
            process=False,
        )
        seal = check_seal(mesh_world, w_tcp, spec.cup_diameter_m, opts.seal)

    grasp_pos = w_tcp[:3, 3].copy()
    approach_dir = w_tcp[:3, 2].copy()
    start_pos = pre[:3, 3].copy()
    end_approach = grasp_pos + (approach_dir * opts.press_m if spec.kind == "suction" else 0.0)
    if spec.kind == "parallel":
        close_s = (opening / 2.0 + 0.008) / (spec.closing_speed_m_s / 2.0)
    else:
        close_s = 0.05
    lift_m = opts.lift_m
    if opts.lift_to_z_m is not None:
        lift_m = max(lift_m, float(opts.lift_to_z_m) - float(end_approach[2]))
    lift_s = opts.lift_s * math.sqrt(lift_m / opts.lift_m) if opts.lift_m > 0 else opts.lift_s
    phases = [
        ("settle", opts.settle_s),
        ("approach", opts.approach_s),
        ("close", close_s + opts.close_hold_s),
        ("lift", lift_s),
        ("move", opts.move_s),
        ("hold", opts.hold_s),
    ]
    lift_vec = np.array([0.0, 0.0, lift_m])
    move_vec = np.array([opts.move_m, 0.0, 0.0])
    target_qadr = model.joint("target_free").qposadr[0]
    z0 = float(data.qpos[target_qadr + 2])
    ref_body = "hand_cup" if spec.kind == "suction" else "hand"
    gripped_ref = np.eye(4)
    tcp_from_obj0 = invert_pose(w_tcp) @ w_obj
    vacuum = _Vacuum(spec, seal, w_tcp[:3, 2].copy()) if seal is not None and seal.sealed else None
    in_hand_after_close = False
    grip_force = 0.0
    touching = False
    step = 0
    for phase, duration in phases:
        n_steps = max(1, int(round(duration / dt)))
        for k in range(n_steps):
            s = (k + 1) / n_steps
            if phase == "settle":
                pos = start_pos
            elif phase == "approach":
                pos = start_pos + (end_approach - start_pos) * _min_jerk(s)
            elif phase == "close":
                pos = end_approach
                if spec.kind == "parallel":
                    target_q = q0 + spec.closing_speed_m_s / 2.0 * (k + 1) * dt
                    for side in ("left", "right"):
                        data.ctrl[model.actuator(f"drive_{side}").id] = min(target_q, spec.stroke_m / 2.0 + 0.008)
                elif vacuum is not None and not vacuum.attached and touching and k >= n_steps // 2:
                    vacuum.attach(model, data)
            elif phase == "lift":
                pos = end_approach + lift_vec * _min_jerk(s)
            elif phase == "move":
                pos = end_approach + lift_vec + move_vec * _min_jerk(s)
            else:
                pos = end_approach + lift_vec + move_vec
            data.mocap_pos[mocap] = pos
            mujoco.mj_step(model, data)
            step += 1
            if step % opts.check_every == 0 or k == n_steps - 1:
                touching, force = monitor.check(data, opts, target_counts=phase in ("settle", "approach"))
                if vacuum is not None:
                    vacuum.check(model, data, opts.check_every)
                    touching = vacuum.attached if phase != "close" or vacuum.attached else touching
                    force = vacuum.pull_n if vacuum.attached else force
                if phase == "close" and k == n_steps - 1:
                    grip_force = force
        if not np.all(np.isfinite(data.qpos)):
            raise SimulationError(f"the grasp simulation diverged during {phase!r}; reduce timestep_s")
        if phase == "close":
            in_hand_after_close = touching
            gripped_ref = _frame_from_object(data, model, ref_body)
    # slip: motion of the part relative to what holds it (the hand, or the cup on its bellows)
    final_ref = _frame_from_object(data, model, ref_body)
    slip_m = float(np.linalg.norm(final_ref[:3, 3] - gripped_ref[:3, 3]))
    slip_rad = rotation_angle(final_ref[:3, :3] @ gripped_ref[:3, :3].T)
    final = _frame_from_object(data, model, "hand")
    delta = final[:3, 3] - tcp_from_obj0[:3, 3]
    lift = float(data.qpos[target_qadr + 2]) - z0

    if monitor.collision:
        outcome, reason = "collision", f"the hand hit {monitor.collision}"
    elif vacuum is not None and vacuum.released_by:
        outcome, reason = "drop", f"the vacuum let go: {vacuum.released_by}"
    elif not in_hand_after_close:
        outcome, reason = "missed", "the gripper closed without touching the target"
        if seal is not None and not seal.sealed:
            outcome, reason = "drop", f"no vacuum seal ({seal.reason})"
    elif not touching or lift < 0.5 * lift_m:
        outcome = "drop"
        reason = "the target fell out of the hand" if touching is False else "the target was not lifted"
        if seal is not None and not seal.sealed:
            reason = f"no vacuum seal ({seal.reason})"
    elif slip_m > opts.slip_tolerance_m or slip_rad > opts.slip_tolerance_rad:
        outcome, reason = (
            "slip",
            f"the target moved {slip_m * 1e3:.1f} mm / {math.degrees(slip_rad):.1f} deg in the hand",
        )
    else:
        outcome, reason = "held", ""
    if outcome != "held" and opts.release_s > 0:
        step += _release(model, data, spec, mocap, np.asarray(data.mocap_pos[mocap], dtype=np.float64), opts)
    step += _come_to_rest(model, data, opts)
    sim_time = step * dt
    final_neighbours = np.array(neighbour_poses, dtype=np.float64).reshape(-1, 4, 4)
    for i in simulated:
        bid = model.body(f"nb{i}").id
        final_neighbours[i] = make_pose(np.asarray(data.xmat[bid]).reshape(3, 3), np.asarray(data.xpos[bid]))
    tid = model.body("target").id
    final_target = make_pose(np.asarray(data.xmat[tid]).reshape(3, 3), np.asarray(data.xpos[tid]))
    result = PhysicsResult(
        outcome=outcome,
        reason=reason,
        slip_m=slip_m,
        slip_rad=slip_rad,
        object_offset_m=delta,
        tcp_from_object=final,
        lift_m=lift,
        max_penetration_m=monitor.max_penetration,
        grip_force_n=grip_force,
        collision_with=monitor.collision,
        seal=seal,
        sim_time_s=sim_time,
        wall_time_s=time.perf_counter() - t_wall,
        n_pieces=len(target_pieces),
        world_from_object_final=final_target,
        world_from_neighbours_final=final_neighbours,
    )
    logger.debug("grasp on %s: %s (%s), %d neighbours simulated", target.name, outcome, reason, kept)
    return result


def _release(
    model: mujoco.MjModel, data: mujoco.MjData, spec: GripperSpec, mocap: int, pos: FloatArray, opts: PhysicsOptions
) -> int:
    """Open the jaws (or stop the vacuum), raise the hand 5 cm and let the parts come to rest; returns steps."""
    import mujoco

    if spec.kind == "parallel":
        for side in ("left", "right"):
            data.ctrl[model.actuator(f"drive_{side}").id] = 0.0
    else:
        data.eq_active[model.equality("vacuum").id] = 0
    n_steps = max(1, int(round(opts.release_s / opts.timestep_s)))
    rise = np.array([0.0, 0.0, 0.05])
    for k in range(n_steps):
        data.mocap_pos[mocap] = pos + rise * _min_jerk(min(1.0, 2.0 * (k + 1) / n_steps))
        mujoco.mj_step(model, data)
    if not np.all(np.isfinite(data.qpos)):
        raise SimulationError("the grasp simulation diverged while releasing; reduce timestep_s")
    return n_steps


def _come_to_rest(model: mujoco.MjModel, data: mujoco.MjData, opts: PhysicsOptions) -> int:
    """Step on (the hand's controls as they are) until no free part moves faster than `opts.rest_speed_m_s` or
    turns faster than `opts.rest_spin_rad_s`, checked every 10 steps, for at most `opts.rest_s`; returns steps."""
    import mujoco

    dofs = [
        int(model.jnt_dofadr[j])
        for j in range(model.njnt)
        if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE and not model.joint(j).name.startswith("hand")
    ]
    if not dofs or opts.rest_s <= 0:
        return 0
    lin = np.array([[d, d + 1, d + 2] for d in dofs])
    ang = lin + 3
    n_max = int(round(opts.rest_s / opts.timestep_s))
    step = 0
    while step < n_max:
        if (
            float(np.abs(data.qvel[lin]).max()) <= opts.rest_speed_m_s
            and float(np.abs(data.qvel[ang]).max()) <= opts.rest_spin_rad_s
        ):
            break
        for _ in range(10):
            mujoco.mj_step(model, data)
        step += 10
    if not np.all(np.isfinite(data.qpos)):
        raise SimulationError("the grasp simulation diverged while the parts came to rest; reduce timestep_s")
    return step


class _Vacuum:
    """A sealed cup as a breakable weld between cup and target, released when the wrench it carries exceeds
    what the vacuum can hold (Dex-Net 3.0 style limits): with V = pressure x area x efficiency and the pull
    F_n (away from the cup), the seal holds while F_n <= V, shear <= mu (V - F_n), torsion <= mu (V - F_n) 2r/3
    and the peeling moment about the cup centre <= (V - F_n) r, each for no longer than 10 ms."""

    def __init__(self, spec: GripperSpec, seal: SealCheck, axis_world: FloatArray) -> None:
        self.force = spec.vacuum_force_n
        self.mu = spec.cup_friction
        self.r = spec.cup_diameter_m / 2.0
        self.axis_world = axis_world
        self.attached = False
        self.released_by = ""
        self.pull_n = 0.0
        self._violation_steps = 0

    def attach(self, model: mujoco.MjModel, data: mujoco.MjData) -> None:
        import mujoco

        eq = model.equality("vacuum").id
        cup = model.body("hand_cup").id
        tgt = model.body("target").id
        r1 = data.xmat[cup].reshape(3, 3)
        r2 = data.xmat[tgt].reshape(3, 3)
        quat = np.zeros(4)
        mujoco.mju_mat2Quat(quat, (r1.T @ r2).reshape(-1))
        model.eq_data[eq, 0:3] = 0.0
        model.eq_data[eq, 3:6] = r1.T @ (data.xpos[tgt] - data.xpos[cup])
        model.eq_data[eq, 6:10] = quat
        data.eq_active[eq] = 1
        self.attached = True

    def check(self, model: mujoco.MjModel, data: mujoco.MjData, steps: int) -> None:
        """Compare the weld's wrench on the target with the vacuum's limits; release after 10 ms over them."""
        if not self.attached:
            return
        eq = model.equality("vacuum").id
        rows = np.nonzero((np.asarray(data.efc_type) == 0) & (np.asarray(data.efc_id) == eq))[0]
        if len(rows) != 6:
            return
        efc = np.asarray(data.efc_force)[rows]
        cup = model.body("hand_cup").id
        tgt = model.body("target").id
        force = -efc[:3]  # on the target, world frame
        r_tgt = data.xmat[tgt].reshape(3, 3)
        torque = r_tgt @ (-efc[3:] / 2.0)  # on the target about its origin, world frame
        centre = data.xpos[cup]  # the cup face centre (body origin = lip face)
        torque_c = torque + np.cross(data.xpos[tgt] - centre, force)
        z = data.xmat[cup].reshape(3, 3)[:, 2]
        pull = -float(force @ z)  # cup pulling the part towards itself (z points into the part)
        shear = float(np.linalg.norm(force + pull * z))
        torsion = abs(float(torque_c @ z))
        peel = float(np.linalg.norm(torque_c - (torque_c @ z) * z))
        self.pull_n = pull
        press = self.force - max(pull, 0.0)
        why = ""
        if pull > self.force:
            why = f"pull {pull:.1f} N > vacuum {self.force:.1f} N"
        elif shear > self.mu * press:
            why = f"shear {shear:.1f} N > {self.mu * press:.1f} N"
        elif torsion > self.mu * press * 2.0 * self.r / 3.0:
            why = f"torsion {torsion:.3f} N m over the lip's friction"
        elif peel > press * self.r:
            why = f"peeling moment {peel:.3f} N m > {press * self.r:.3f} N m"
        if not why:
            self._violation_steps = 0
            return
        self._violation_steps += steps
        if self._violation_steps * model.opt.timestep >= 0.01:
            data.eq_active[eq] = 0
            self.attached = False
            self.released_by = why


def _frame_from_object(data: mujoco.MjData, model: mujoco.MjModel, frame_body: str) -> FloatArray:
    """(4, 4) pose of the target in the frame of body `frame_body` (the hand = TCP, or the suction cup)."""
    tgt = model.body("target").id
    ref = model.body(frame_body).id
    world_from_obj = make_pose(np.asarray(data.xmat[tgt]).reshape(3, 3), np.asarray(data.xpos[tgt]))
    world_from_ref = make_pose(np.asarray(data.xmat[ref]).reshape(3, 3), np.asarray(data.xpos[ref]))
    return invert_pose(world_from_ref) @ world_from_obj


def _safe(name: str) -> str:
    return "".join(ch if ch.isalnum() or ch in "_-" else "_" for ch in str(name))
