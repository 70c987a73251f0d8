"""Grippers: parallel-jaw and suction tools with a TCP frame, opening range and collision shapes.

TCP frame: z = approach direction out of the flange, x = jaw closing direction (parallel grippers). Body shapes
are authored in the gripper's mounting frame (its coupling face, = the flange unless `mounted` adds an
offset); `collision_shapes(opening)` returns them in the TCP frame (link 'tcp'). Metres, kilograms.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from importlib import resources
from pathlib import Path
from typing import Any, Literal

import numpy as np
import yaml

from normpos_grasp.errors import InputError, RobotModelError
from normpos_grasp.io.yaml_safe import load_yaml, load_yaml_file
from normpos_grasp.kinematics.shapes import CollisionShape
from normpos_grasp.typing import ArrayLike, FloatArray

GRIPPER_NAMES = ("2f85", "2f140", "suction")


def pose_from_xyz_rpy(xyz: ArrayLike, rpy: ArrayLike = (0.0, 0.0, 0.0)) -> FloatArray:
    """(4, 4) pose from a translation (m) and roll-pitch-yaw (rad, R = Rz(yaw) Ry(pitch) Rx(roll))."""
    r, p, y = (float(v) for v in np.asarray(rpy, dtype=np.float64).reshape(3))
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    pose = np.eye(4)
    pose[:3, :3] = [
        [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
        [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
        [-sp, cp * sr, cp * cr],
    ]
    pose[:3, 3] = np.asarray(xyz, dtype=np.float64).reshape(3)
    return pose


@dataclass(frozen=True)
class FingerSpec:
    """Parallel-jaw fingers as boxes: length along TCP z, thickness along x, width along y (m); the tips reach
    `tip_beyond_tcp_m` past the TCP along +z."""

    length_m: float
    thickness_m: float
    width_m: float
    tip_beyond_tcp_m: float


@dataclass(frozen=True)
class Gripper:
    """One tool. `gripper_from_tcp` is the TCP in the mounting frame; `flange_from_gripper` the mounting
    offset (identity when mounted directly on the flange)."""

    name: str
    kind: Literal["parallel", "suction"]
    gripper_from_tcp: FloatArray
    mass_kg: float
    stroke_m: float
    min_opening_m: float
    body: tuple[CollisionShape, ...]
    finger: FingerSpec | None = None
    cup_diameter_m: float = 0.0
    cup_stroke_m: float = 0.0
    flange_from_gripper: FloatArray = field(default_factory=lambda: np.eye(4))

    def __post_init__(self) -> None:
        if self.kind not in ("parallel", "suction"):
            raise RobotModelError(f"gripper {self.name!r}: kind must be 'parallel' or 'suction', got {self.kind!r}")
        if self.kind == "parallel" and (self.finger is None or not 0 <= self.min_opening_m <= self.stroke_m):
            raise RobotModelError(
                f"gripper {self.name!r}: a parallel gripper needs fingers and 0 <= min_opening_m <= stroke_m "
                f"(got {self.min_opening_m}, {self.stroke_m})"
            )
        if self.kind == "suction" and not (self.cup_diameter_m > 0 and self.cup_stroke_m >= 0):
            raise RobotModelError(f"gripper {self.name!r}: suction needs cup_diameter_m > 0 and cup_stroke_m >= 0")
        for attr in ("gripper_from_tcp", "flange_from_gripper"):
            pose = np.array(getattr(self, attr), dtype=np.float64)
            if pose.shape != (4, 4):
                raise RobotModelError(f"gripper {self.name!r}: {attr} must be (4, 4), got {pose.shape}")
            pose.setflags(write=False)
            object.__setattr__(self, attr, pose)

    # ------------------------------------------------------------------------------------------ loading
    @staticmethod
    def load(name: str) -> Gripper:
        """A packaged gripper: '2f85', '2f140' or 'suction' (robots/grippers/<name>.yaml)."""
        path = resources.files("normpos_grasp.robot_models") / "grippers" / f"{name.lower()}.yaml"
        if not path.is_file():
            raise RobotModelError(
                f"unknown gripper {name!r}; packaged: {', '.join(GRIPPER_NAMES)} "
                "(or use Gripper.from_yaml for a custom one)"
            )
        return Gripper.from_dict(load_yaml(path.read_text(encoding="utf-8"), str(path)), source=str(path))

    @staticmethod
    def from_yaml(path: str | Path) -> Gripper:
        """A custom gripper from a YAML file in the packaged files' format (see docs/kinematics.md)."""
        try:
            data = load_yaml_file(path)
        except (OSError, yaml.YAMLError) as exc:
            raise RobotModelError(f"gripper file: {exc}") from exc
        return Gripper.from_dict(data, source=str(path))

    @staticmethod
    def from_dict(data: Any, source: str = "<dict>") -> Gripper:
        """Gripper from the YAML mapping (keys: name, kind, mass_kg, tcp_xyz_m, tcp_rpy_rad, body, and finger,
        stroke_m, min_opening_m for parallel or cup_diameter_m, cup_stroke_m for suction)."""
        if not isinstance(data, dict):
            raise RobotModelError(f"{source}: expected a mapping, got {type(data).__name__}")
        try:
            kind = str(data["kind"])
            body = tuple(
                CollisionShape(
                    "gripper",
                    s["kind"],
                    tuple(float(v) for v in s["size"]),
                    pose_from_xyz_rpy(s.get("xyz_m", (0, 0, 0)), s.get("rpy_rad", (0, 0, 0))),
                )
                for s in data.get("body", [])
            )
            finger = FingerSpec(**{k: float(v) for k, v in data["finger"].items()}) if "finger" in data else None
            return Gripper(
                name=str(data["name"]),
                kind=kind,  # type: ignore[arg-type]
                gripper_from_tcp=pose_from_xyz_rpy(data["tcp_xyz_m"], data.get("tcp_rpy_rad", (0, 0, 0))),
                mass_kg=float(data["mass_kg"]),
                stroke_m=float(data.get("stroke_m", 0.0)),
                min_opening_m=float(data.get("min_opening_m", 0.0)),
                body=body,
                finger=finger,
                cup_diameter_m=float(data.get("cup_diameter_m", 0.0)),
                cup_stroke_m=float(data.get("cup_stroke_m", 0.0)),
            )
        except (KeyError, TypeError, ValueError, InputError) as exc:
            raise RobotModelError(f"{source}: invalid gripper description ({type(exc).__name__}: {exc})") from exc

    @staticmethod
    def suction(
        cup_diameter_m: float = 0.03,
        cup_stroke_m: float = 0.01,
        length_m: float = 0.12,
        mass_kg: float = 0.3,
        name: str = "suction",
    ) -> Gripper:
        """A single suction cup on a straight tube of `length_m` from the coupling; TCP at the free cup lip."""
        tube_r = max(0.012, 0.4 * cup_diameter_m)
        cup_len = cup_stroke_m + 0.005
        body = (
            CollisionShape(
                "gripper",
                "cylinder",
                (tube_r, length_m - cup_len),
                pose_from_xyz_rpy((0.0, 0.0, 0.5 * (length_m - cup_len))),
            ),
            CollisionShape(
                "gripper",
                "cylinder",
                (cup_diameter_m / 2.0, cup_len),
                pose_from_xyz_rpy((0.0, 0.0, length_m - 0.5 * cup_len)),
            ),
        )
        return Gripper(
            name,
            "suction",
            pose_from_xyz_rpy((0.0, 0.0, length_m)),
            mass_kg,
            0.0,
            0.0,
            body,
            cup_diameter_m=cup_diameter_m,
            cup_stroke_m=cup_stroke_m,
        )

    def to_dict(self) -> dict[str, Any]:
        """The YAML mapping of this gripper (mounting offset not included). Poses given as xyz + rpy."""

        def xyz_rpy(pose: FloatArray) -> tuple[list[float], list[float]]:
            rot = pose[:3, :3]
            pitch = math.asin(max(-1.0, min(1.0, -rot[2, 0])))
            roll, yaw = math.atan2(rot[2, 1], rot[2, 2]), math.atan2(rot[1, 0], rot[0, 0])
            return [_r(v) for v in pose[:3, 3]], [_r(roll), _r(pitch), _r(yaw)]

        tcp_xyz, tcp_rpy = xyz_rpy(self.gripper_from_tcp)
        out: dict[str, Any] = {
            "name": self.name,
            "kind": self.kind,
            "mass_kg": self.mass_kg,
            "tcp_xyz_m": tcp_xyz,
            "tcp_rpy_rad": tcp_rpy,
        }
        if self.kind == "parallel" and self.finger is not None:
            out["stroke_m"] = self.stroke_m
            out["min_opening_m"] = self.min_opening_m
            out["finger"] = {k: _r(getattr(self.finger, k)) for k in FingerSpec.__dataclass_fields__}
        else:
            out["cup_diameter_m"] = self.cup_diameter_m
            out["cup_stroke_m"] = self.cup_stroke_m
        body = []
        for s in self.body:
            xyz, rpy = xyz_rpy(s.link_from_shape)
            body.append({"kind": s.kind, "size": [_r(v) for v in s.size], "xyz_m": xyz, "rpy_rad": rpy})
        out["body"] = body
        return out

    # ------------------------------------------------------------------------------------------ geometry
    @property
    def flange_from_tcp(self) -> FloatArray:
        """(4, 4) TCP pose in the flange frame, mounting offset included."""
        return self.flange_from_gripper @ self.gripper_from_tcp

    def mounted(self, flange_offset: ArrayLike) -> Gripper:
        """This gripper mounted through an adapter: flange_from_gripper = flange_offset (4, 4) @ current."""
        offset = np.asarray(flange_offset, dtype=np.float64)
        if offset.shape != (4, 4):
            raise InputError(f"flange_offset: expected (4, 4), got {offset.shape}")
        return replace(self, flange_from_gripper=offset @ self.flange_from_gripper)

    def check_opening(self, opening_m: float) -> float:
        """Return opening_m if within [min_opening_m, stroke_m] (parallel), else raise InputError."""
        if self.kind == "suction":
            return 0.0
        if not (self.min_opening_m - 1e-12 <= opening_m <= self.stroke_m + 1e-12):
            raise InputError(
                f"gripper {self.name}: opening {opening_m} m outside [{self.min_opening_m}, {self.stroke_m}] m"
            )
        return float(opening_m)

    def collision_shapes(self, opening_m: float | None = None) -> list[CollisionShape]:
        """Shapes in the TCP frame (link 'tcp') at jaw opening `opening_m` (default: fully open): body,
        adapter (when mounted with an offset) and two finger boxes or the suction cup."""
        opening = self.stroke_m if opening_m is None else self.check_opening(opening_m)
        tcp_from_flange = np.linalg.inv(self.flange_from_tcp)
        tcp_from_gripper = np.linalg.inv(self.gripper_from_tcp)
        shapes = [CollisionShape("tcp", s.kind, s.size, tcp_from_gripper @ s.link_from_shape) for s in self.body]
        offset = self.flange_from_gripper[:3, 3]
        length = float(np.linalg.norm(offset))
        if length > 1e-6:
            axis = offset / length
            rot = np.eye(3)
            if abs(axis[2]) < 1.0 - 1e-12:
                x = np.cross(axis, [0.0, 0.0, 1.0])
                x /= np.linalg.norm(x)
                rot = np.column_stack([x, np.cross(axis, x), axis])
            elif axis[2] < 0:
                rot = np.diag([1.0, -1.0, -1.0])
            flange_from_adapter = np.eye(4)
            flange_from_adapter[:3, :3] = rot
            flange_from_adapter[:3, 3] = offset / 2.0
            radius = max((s.size[0] for s in self.body if s.kind in ("cylinder", "capsule")), default=0.035)
            shapes.append(CollisionShape("tcp", "cylinder", (radius, length), tcp_from_flange @ flange_from_adapter))
        if self.finger is not None:
            f = self.finger
            z = f.tip_beyond_tcp_m - f.length_m / 2.0
            for side in (-1.0, 1.0):
                pose = np.eye(4)
                pose[:3, 3] = (side * (opening / 2.0 + f.thickness_m / 2.0), 0.0, z)
                shapes.append(CollisionShape("tcp", "box", (f.thickness_m, f.width_m, f.length_m), pose))
        return shapes


def _r(v: float) -> float:
    out = round(float(v), 9)
    return 0.0 if out == 0 else out


def _parallel(
    name: str,
    mass: float,
    stroke: float,
    tip_z: float,
    pad_above_tip: float,
    coupling_r: float,
    coupling_len: float,
    palm: tuple[float, float, float],
    finger: tuple[float, float],
) -> Gripper:
    """A Robotiq-like parallel gripper: coupling cylinder, palm box, two fingers ending at tip_z (m from flange)."""
    palm_z0 = coupling_len
    body = (
        CollisionShape("gripper", "cylinder", (coupling_r, coupling_len), pose_from_xyz_rpy((0, 0, coupling_len / 2))),
        CollisionShape("gripper", "box", palm, pose_from_xyz_rpy((0, 0, palm_z0 + palm[2] / 2))),
    )
    finger_len = tip_z - (palm_z0 + palm[2])
    return Gripper(
        name,
        "parallel",
        pose_from_xyz_rpy((0, 0, tip_z - pad_above_tip)),
        mass,
        stroke,
        0.0,
        body,
        FingerSpec(finger_len, finger[0], finger[1], pad_above_tip),
    )


def packaged_grippers() -> list[Gripper]:
    """The grippers written to robots/grippers/ by the generator (outline approximations, see README)."""
    return [
        _parallel("2f85", 0.925, 0.085, 0.163, 0.013, 0.0375, 0.011, (0.125, 0.075, 0.09), (0.02, 0.027)),
        _parallel("2f140", 1.025, 0.140, 0.232, 0.013, 0.0375, 0.011, (0.195, 0.075, 0.12), (0.02, 0.027)),
        Gripper.suction(),
    ]
