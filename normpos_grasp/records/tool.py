"""`ToolModel`: the end effector as the collision checker and planner see it (TCP frame: z = approach, x = jaw
closing direction), built from a cell file or from the robots stage's `Gripper`."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from normpos_grasp.errors import InputError
from normpos_grasp.typing import FloatArray


@dataclass(frozen=True)
class ToolShape:
    """A primitive of the tool in the TCP frame: `kind` 'box' (size = full extents), 'cylinder' / 'capsule'
    (radius, length along z) or 'sphere' (radius), metres; `tcp_from_shape` (4, 4) at zero opening; `moves` is
    +1/-1 for a finger box that slides along TCP x by +-(opening + thickness)/2, 0 for a fixed body."""

    name: str
    size: tuple[float, ...]
    tcp_from_shape: FloatArray
    moves: int = 0
    kind: str = "box"

    def __post_init__(self) -> None:
        need = {"box": 3, "cylinder": 2, "capsule": 2, "sphere": 1}
        if self.kind not in need or len(self.size) != need[self.kind]:
            raise InputError(f"tool shape {self.name!r}: kind/size mismatch ({self.kind!r}, {self.size})")
        if self.moves and self.kind != "box":
            raise InputError(f"tool shape {self.name!r}: only boxes can move with the jaw opening")


@dataclass(frozen=True, eq=False)
class ToolModel:
    """End effector: `kind` 'parallel' or 'suction'; `flange_from_tcp` (4, 4); stroke_m / min_opening_m: jaw
    opening range (m, 0 for suction); `shapes`: boxes in the TCP frame at zero opening; finger_depth_m: how far
    the fingers reach past the TCP along z (m); payload_kg: rated payload; cup_diameter_m: the suction cup's lip
    diameter (m; 0 for parallel jaws)."""

    name: str
    kind: str
    flange_from_tcp: FloatArray
    stroke_m: float
    min_opening_m: float
    shapes: tuple[ToolShape, ...]
    finger_depth_m: float = 0.0
    max_grip_depth_m: float = 0.03
    payload_kg: float = 3.0
    cup_diameter_m: float = 0.0

    def __post_init__(self) -> None:
        if self.kind not in ("parallel", "suction"):
            raise InputError(f"tool kind must be 'parallel' or 'suction', got {self.kind!r}")

    def posed_shapes(self, opening_m: float) -> list[tuple[ToolShape, FloatArray]]:
        """(shape, tcp_from_shape (4, 4)) for each shape at jaw opening `opening_m` (metres)."""
        out = []
        for s in self.shapes:
            pose = np.array(s.tcp_from_shape, dtype=np.float64)
            if s.moves:
                pose[0, 3] += s.moves * (opening_m / 2.0 + s.size[0] / 2.0)
            out.append((s, pose))
        return out

    def to_json(self, opening_m: float) -> dict[str, Any]:
        """The plan.json `tool` entry."""
        return {
            "name": self.name,
            "type": self.kind,
            "flange_from_tcp": np.asarray(self.flange_from_tcp).tolist(),
            "opening_m": float(opening_m),
            "stroke_m": float(self.stroke_m),
            "collision": [
                {"name": s.name, "kind": s.kind, "size": [float(v) for v in s.size], "tcp_from_shape": pose.tolist()}
                for s, pose in self.posed_shapes(opening_m)
            ],
        }


def _box_pose(x: float, y: float, z: float) -> FloatArray:
    pose = np.eye(4)
    pose[:3, 3] = (x, y, z)
    return pose


def parallel_gripper(
    name: str,
    stroke_m: float,
    finger_length_m: float,
    flange_to_tcp_m: float,
    finger_width_m: float = 0.02,
    finger_thickness_m: float = 0.01,
    body_size_m: tuple[float, float, float] = (0.14, 0.06, 0.09),
    min_opening_m: float = 0.0,
    grip_depth_m: float = 0.015,
    payload_kg: float = 2.5,
) -> ToolModel:
    """A two-finger gripper: a body box from the flange to the finger roots and two finger boxes; the TCP sits
    `grip_depth_m` above the finger tips, on the jaw centre line, `flange_to_tcp_m` along flange z."""
    flange_from_tcp = _box_pose(0.0, 0.0, flange_to_tcp_m)
    root_z = finger_length_m - grip_depth_m  # finger root height above the TCP (towards the flange: -z)
    tip_z = -grip_depth_m
    body_h = min(body_size_m[2], flange_to_tcp_m - root_z)
    body = ToolShape("body", (body_size_m[0], body_size_m[1], body_h), _box_pose(0.0, 0.0, -root_z - body_h / 2.0))
    finger_pose_z = -(root_z + tip_z) / 2.0
    fingers = tuple(
        ToolShape(
            f"finger_{'right' if sign > 0 else 'left'}",
            (finger_thickness_m, finger_width_m, finger_length_m),
            _box_pose(0.0, 0.0, finger_pose_z),
            moves=sign,
        )
        for sign in (1, -1)
    )
    return ToolModel(
        name=name,
        kind="parallel",
        flange_from_tcp=flange_from_tcp,
        stroke_m=stroke_m,
        min_opening_m=min_opening_m,
        shapes=(body, *fingers),
        finger_depth_m=grip_depth_m,
        max_grip_depth_m=finger_length_m * 0.6,
        payload_kg=payload_kg,
    )


def suction_tool(
    name: str,
    flange_to_tcp_m: float,
    cup_diameter_m: float = 0.03,
    stem_diameter_m: float = 0.02,
    body_size_m: tuple[float, float, float] = (0.06, 0.06, 0.05),
    payload_kg: float = 3.0,
) -> ToolModel:
    """A suction cup on a stem: the TCP is the cup's lip centre, `flange_to_tcp_m` along flange z."""
    stem_len = max(flange_to_tcp_m - body_size_m[2], 0.01)
    shapes = (
        ToolShape("cup", (cup_diameter_m, cup_diameter_m, 0.01), _box_pose(0.0, 0.0, -0.005)),
        ToolShape(
            "stem",
            (stem_diameter_m, stem_diameter_m, stem_len - 0.01),
            _box_pose(0.0, 0.0, -0.01 - (stem_len - 0.01) / 2),
        ),
        ToolShape("body", body_size_m, _box_pose(0.0, 0.0, -stem_len - body_size_m[2] / 2.0)),
    )
    return ToolModel(
        name=name,
        kind="suction",
        flange_from_tcp=_box_pose(0.0, 0.0, flange_to_tcp_m),
        stroke_m=0.0,
        min_opening_m=0.0,
        shapes=shapes,
        max_grip_depth_m=0.0,
        payload_kg=payload_kg,
        cup_diameter_m=cup_diameter_m,
    )


def tool_from_gripper(gripper: Any) -> ToolModel:
    """Adapt the kinematics stage's `Gripper` (kind, flange_from_tcp, stroke_m, min_opening_m, finger,
    collision_shapes(opening)) to a ToolModel: shapes that move between the closed and open jaw become fingers."""
    kind = str(gripper.kind)
    closed = list(gripper.collision_shapes(float(gripper.min_opening_m) if kind == "parallel" else None))
    opened = list(gripper.collision_shapes(float(gripper.stroke_m) if kind == "parallel" else None))
    shapes = []
    for i, (c, o) in enumerate(zip(closed, opened, strict=True)):
        pose_c = np.array(c.link_from_shape, dtype=np.float64)
        dx = float(o.link_from_shape[0, 3] - pose_c[0, 3])
        moves = int(np.sign(dx)) if abs(dx) > 1e-9 else 0
        if moves:  # pose at zero opening: inner face on the TCP's y-z plane before the shift
            pose_c[0, 3] = 0.0
        name = f"finger_{'right' if moves > 0 else 'left'}" if moves else f"{c.link}_{i}"
        shapes.append(ToolShape(name, tuple(float(v) for v in c.size), pose_c, moves, str(c.kind)))
    finger = getattr(gripper, "finger", None)
    depth = float(finger.tip_beyond_tcp_m) if finger is not None else 0.0
    length = float(finger.length_m) if finger is not None else 0.0
    return ToolModel(
        name=str(gripper.name),
        kind=kind,
        flange_from_tcp=np.array(gripper.flange_from_tcp, dtype=np.float64),
        stroke_m=float(gripper.stroke_m),
        min_opening_m=float(gripper.min_opening_m),
        shapes=tuple(shapes),
        finger_depth_m=depth,
        max_grip_depth_m=max(length * 0.6, 0.0),
        payload_kg=float(getattr(gripper, "payload_kg", 3.0)),
        cup_diameter_m=float(getattr(gripper, "cup_diameter_m", 0.0)) if kind == "suction" else 0.0,
    )


#: name prefix of the shapes a dual-tool end effector's idle tool adds to the active one (`with_idle`)
IDLE_PREFIX = "idle/"


def own_shapes(tool: ToolModel) -> tuple[ToolShape, ...]:
    """The shapes of `tool` itself, without the idle tool's that `with_idle` added."""
    return tuple(s for s in tool.shapes if not s.name.startswith(IDLE_PREFIX))


def with_idle(active: ToolModel, idle: ToolModel, idle_retract_m: float = 0.0) -> ToolModel:
    """`active` with `idle`'s body added to its shapes, in `active`'s TCP frame (both TCPs given from the same
    flange): the whole end effector of a dual-tool flange as the collision checker sees it when `active` is used.
    The idle jaws stand at their smallest opening (fixed, `moves` 0); an idle tool on a slide is drawn back
    `idle_retract_m` (m) along its approach axis, towards the flange; the idle tool's own idle shapes are left out."""
    retract = np.eye(4)
    retract[2, 3] = -float(idle_retract_m)
    tcp_from_idle_tcp = np.linalg.inv(np.asarray(active.flange_from_tcp)) @ np.asarray(idle.flange_from_tcp) @ retract
    added = []
    for s, pose in idle.posed_shapes(idle.min_opening_m):
        if s.name.startswith(IDLE_PREFIX):
            continue
        added.append(ToolShape(f"{IDLE_PREFIX}{idle.name}/{s.name}", s.size, tcp_from_idle_tcp @ pose, 0, s.kind))
    return ToolModel(
        name=active.name,
        kind=active.kind,
        flange_from_tcp=active.flange_from_tcp,
        stroke_m=active.stroke_m,
        min_opening_m=active.min_opening_m,
        shapes=(*own_shapes(active), *added),
        finger_depth_m=active.finger_depth_m,
        max_grip_depth_m=active.max_grip_depth_m,
        payload_kg=active.payload_kg,
        cup_diameter_m=active.cup_diameter_m,
    )
