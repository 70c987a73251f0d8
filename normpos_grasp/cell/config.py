"""Cell YAML: schema, loader and validation. Every error is a `CellConfigError` whose `path` names the key
(for example `gripper.stroke_m`). The schema is documented in docs/cells.md.

Poses in the file are either `{xyz: [x, y, z], rpy_deg: [roll, pitch, yaw]}` (metres; degrees, R = Rz Ry Rx),
`{xyz, rpy}` (radians) or a 4x4 nested list.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from normpos_grasp.collision.tool import ToolModel, parallel_gripper, suction_tool, tool_from_gripper
from normpos_grasp.errors import CellConfigError, NormposError
from normpos_grasp.kinematics.gripper import Gripper
from normpos_grasp.kinematics.ur_params import UR_PARAMS
from normpos_grasp.typing import FloatArray

_TOP_KEYS = {
    "name",
    "robot",
    "gripper",
    "camera",
    "table",
    "bin",
    "conveyor",
    "fixtures",
    "place",
    "templates",
    "motion",
    "planning",
}


@dataclass(frozen=True, eq=False)
class BoxSpec:
    """A static box: `world_from_box` (4, 4) at its centre, `size` (3,) full extents, m."""

    name: str
    world_from_box: FloatArray
    size: FloatArray


@dataclass(frozen=True, eq=False)
class BinSpec:
    """An open bin: `world_from_bin` (4, 4) at the centre of the inner floor (z up), `inner_size` (3,) inner
    length, width and wall height, `wall_m` wall and floor thickness, m."""

    world_from_bin: FloatArray
    inner_size: FloatArray
    wall_m: float = 0.01

    def boxes(self) -> list[BoxSpec]:
        """Floor and four walls as boxes."""
        lx, ly, h = (float(v) for v in self.inner_size)
        w = self.wall_m
        parts = {
            "bin/floor": ((0.0, 0.0, -w / 2), (lx + 2 * w, ly + 2 * w, w)),
            "bin/wall_x+": ((lx / 2 + w / 2, 0.0, h / 2), (w, ly + 2 * w, h)),
            "bin/wall_x-": ((-lx / 2 - w / 2, 0.0, h / 2), (w, ly + 2 * w, h)),
            "bin/wall_y+": ((0.0, ly / 2 + w / 2, h / 2), (lx, w, h)),
            "bin/wall_y-": ((0.0, -ly / 2 - w / 2, h / 2), (lx, w, h)),
        }
        out = []
        for name, (centre, size) in parts.items():
            pose = np.eye(4)
            pose[:3, 3] = centre
            out.append(BoxSpec(name, self.world_from_bin @ pose, np.asarray(size, dtype=np.float64)))
        return out

    @property
    def rim_z(self) -> float:
        """World height of the bin rim, m."""
        return float(self.world_from_bin[2, 3] + self.inner_size[2])


@dataclass(frozen=True, eq=False)
class PlaceSpec:
    """A place pose: `world_from_tcp` (4, 4) at release; `approach_m` straight-line length above it."""

    name: str
    world_from_tcp: FloatArray
    approach_m: float = 0.1


@dataclass(frozen=True, eq=False)
class MotionLimits:
    """Caps for planned motion: joint_velocity (6,) rad/s, joint_acceleration (6,) rad/s^2 (both already the
    smaller of the cell cap and the robot's limit), tcp_speed_m_s for Cartesian segments, workspace box
    (min (3,), max (3,)) the TCP must stay in, m."""

    joint_velocity: FloatArray
    joint_acceleration: FloatArray
    tcp_speed_m_s: float
    workspace_min: FloatArray
    workspace_max: FloatArray


@dataclass(frozen=True, eq=False)
class CellConfig:
    """A validated cell: robot, tool, static geometry, place poses, template library and limits."""

    name: str
    robot_model: str
    world_from_base: FloatArray
    home_q: FloatArray
    tool: ToolModel
    world_from_camera: FloatArray | None
    static_boxes: tuple[BoxSpec, ...]
    bin: BinSpec | None
    places: tuple[PlaceSpec, ...]
    templates_path: Path | None
    motion: MotionLimits
    entry_clearance_m: float = 0.05
    lift_m: float = 0.08
    voxel_m: float = 0.01
    source: Path | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def entry_z(self) -> float:
        """World height of the bin entry / exit poses (rim + clearance), or -inf without a bin."""
        return self.bin.rim_z + self.entry_clearance_m if self.bin is not None else -np.inf


def load_cell(path: str | Path) -> CellConfig:
    """Read and validate a cell YAML file (yaml.safe_load); relative paths inside resolve against its folder."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise CellConfigError(f"cannot read cell file {p}: {exc.strerror}; check the path") from exc
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise CellConfigError(f"{p} is not valid YAML: {exc}") from exc
    return cell_from_dict(data, base_dir=p.parent, source=p)


def _err(path: str, msg: str) -> CellConfigError:
    return CellConfigError(msg, path)


def _req(d: dict[str, Any], key: str, path: str) -> Any:
    if key not in d:
        raise _err(f"{path}.{key}" if path else key, "required key is missing")
    return d[key]


def _num(v: Any, path: str, lo: float = -np.inf, hi: float = np.inf) -> float:
    if isinstance(v, bool) or not isinstance(v, int | float):
        raise _err(path, f"expected a number, got {type(v).__name__} {v!r}")
    f = float(v)
    if not np.isfinite(f) or f < lo or f > hi:
        raise _err(path, f"expected a finite number in [{lo}, {hi}], got {v!r}")
    return f


def _vec(v: Any, path: str, n: int, positive: bool = False) -> FloatArray:
    if not isinstance(v, list | tuple) or len(v) != n:
        raise _err(path, f"expected a list of {n} numbers, got {v!r}")
    arr = np.array([_num(x, f"{path}[{i}]") for i, x in enumerate(v)], dtype=np.float64)
    if positive and np.any(arr <= 0):
        raise _err(path, f"expected positive sizes, got {arr.tolist()}")
    return arr


def _rpy(r: FloatArray) -> FloatArray:
    cr, sr = np.cos(r[0]), np.sin(r[0])
    cp, sp = np.cos(r[1]), np.sin(r[1])
    cy, sy = np.cos(r[2]), np.sin(r[2])
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    return rz @ ry @ rx


def parse_pose(v: Any, path: str) -> FloatArray:
    """A (4, 4) pose from `{xyz, rpy_deg}`, `{xyz, rpy}` or a 4x4 nested list; errors name `path`."""
    if isinstance(v, dict):
        unknown = set(v) - {"xyz", "rpy", "rpy_deg"}
        if unknown:
            raise _err(path, f"unknown pose keys {sorted(unknown)}; use xyz and rpy_deg (or rpy in radians)")
        pose = np.eye(4)
        pose[:3, 3] = _vec(v.get("xyz", [0, 0, 0]), f"{path}.xyz", 3)
        if "rpy_deg" in v and "rpy" in v:
            raise _err(path, "give either rpy_deg or rpy, not both")
        if "rpy_deg" in v:
            pose[:3, :3] = _rpy(np.deg2rad(_vec(v["rpy_deg"], f"{path}.rpy_deg", 3)))
        elif "rpy" in v:
            pose[:3, :3] = _rpy(_vec(v["rpy"], f"{path}.rpy", 3))
        return pose
    if isinstance(v, list) and len(v) == 4:
        pose = np.stack([_vec(row, f"{path}[{i}]", 4) for i, row in enumerate(v)])
        rot = pose[:3, :3]
        if (
            not np.allclose(pose[3], [0, 0, 0, 1])
            or not np.allclose(rot @ rot.T, np.eye(3), atol=1e-6)
            or np.linalg.det(rot) < 0
        ):
            raise _err(path, "4x4 pose must have a proper rotation block and last row [0, 0, 0, 1]")
        return pose
    raise _err(path, f"expected a pose ({{xyz: [..], rpy_deg: [..]}} or a 4x4 list), got {v!r}")


def _box(d: Any, path: str, name: str) -> BoxSpec:
    if not isinstance(d, dict):
        raise _err(path, f"expected a mapping with pose and size, got {d!r}")
    return BoxSpec(
        str(d.get("name", name)),
        parse_pose(_req(d, "pose", path), f"{path}.pose"),
        _vec(_req(d, "size", path), f"{path}.size", 3, positive=True),
    )


def _tool(d: Any, path: str) -> ToolModel:
    if not isinstance(d, dict):
        raise _err(path, f"expected a mapping, got {d!r}")
    model = str(_req(d, "model", path))
    kind = d.get("kind")
    if "flange_to_tcp_m" not in d:
        # a packaged gripper (kinematics.Gripper), optionally mounted through an adapter
        unknown = set(d) - {"model", "kind", "mount", "payload_kg"}
        if unknown:
            raise _err(
                f"{path}.{sorted(unknown)[0]}",
                "custom geometry keys need flange_to_tcp_m as well (a custom "
                "gripper); for a packaged one give only model, mount and payload_kg",
            )
        try:
            gripper = Gripper.load(model)
        except NormposError as exc:
            raise _err(f"{path}.model", str(exc)) from exc
        if "mount" in d:
            gripper = gripper.mounted(parse_pose(d["mount"], f"{path}.mount"))
        tool = tool_from_gripper(gripper)
        if kind is not None and kind != tool.kind:
            raise _err(f"{path}.kind", f"gripper {model!r} is a {tool.kind} gripper, the file says {kind!r}")
        if "payload_kg" in d:
            object.__setattr__(tool, "payload_kg", _num(d["payload_kg"], f"{path}.payload_kg", 0.0))
        return tool
    if kind not in ("parallel", "suction"):
        raise _err(f"{path}.kind", f"expected 'parallel' or 'suction', got {kind!r}")
    flange_to_tcp = _num(d.get("flange_to_tcp_m", 0.15), f"{path}.flange_to_tcp_m", 0.0, 1.0)
    payload = _num(d.get("payload_kg", 2.0), f"{path}.payload_kg", 0.0)
    if kind == "parallel":
        tool = parallel_gripper(
            model,
            stroke_m=_num(_req(d, "stroke_m", path), f"{path}.stroke_m", 1e-3, 1.0),
            finger_length_m=_num(d.get("finger_length_m", 0.045), f"{path}.finger_length_m", 1e-3, 0.5),
            flange_to_tcp_m=flange_to_tcp,
            finger_width_m=_num(d.get("finger_width_m", 0.02), f"{path}.finger_width_m", 1e-3, 0.5),
            finger_thickness_m=_num(d.get("finger_thickness_m", 0.01), f"{path}.finger_thickness_m", 1e-3, 0.5),
            body_size_m=tuple(_vec(d.get("body_size_m", [0.14, 0.06, 0.09]), f"{path}.body_size_m", 3, True)),
            min_opening_m=_num(d.get("min_opening_m", 0.0), f"{path}.min_opening_m", 0.0, 1.0),
            grip_depth_m=_num(d.get("grip_depth_m", 0.015), f"{path}.grip_depth_m", 0.0, 0.5),
            payload_kg=payload,
        )
    else:
        tool = suction_tool(
            model,
            flange_to_tcp_m=flange_to_tcp,
            cup_diameter_m=_num(d.get("cup_diameter_m", 0.03), f"{path}.cup_diameter_m", 1e-3, 0.5),
            stem_diameter_m=_num(d.get("stem_diameter_m", 0.02), f"{path}.stem_diameter_m", 1e-3, 0.5),
            body_size_m=tuple(_vec(d.get("body_size_m", [0.06, 0.06, 0.05]), f"{path}.body_size_m", 3, True)),
            payload_kg=payload,
        )
    if "mount" in d:
        object.__setattr__(tool, "flange_from_tcp", parse_pose(d["mount"], f"{path}.mount") @ tool.flange_from_tcp)
    if tool.min_opening_m > tool.stroke_m:
        raise _err(f"{path}.min_opening_m", f"min_opening_m {tool.min_opening_m} exceeds stroke_m {tool.stroke_m}")
    return tool


def cell_from_dict(data: Any, base_dir: str | Path = ".", source: Path | None = None) -> CellConfig:
    """Validate a parsed cell mapping; see docs/cells.md for the schema."""
    if not isinstance(data, dict):
        raise CellConfigError(f"a cell file must hold a mapping at the top level, got {type(data).__name__}")
    unknown = set(data) - _TOP_KEYS
    if unknown:
        raise _err(sorted(unknown)[0], f"unknown key; expected one of {sorted(_TOP_KEYS)}")
    robot = _req(data, "robot", "")
    if not isinstance(robot, dict):
        raise _err("robot", f"expected a mapping, got {robot!r}")
    model = str(_req(robot, "model", "robot")).lower()
    if model not in UR_PARAMS:
        raise _err("robot.model", f"unknown robot {model!r}; known: {', '.join(UR_PARAMS)}")
    world_from_base = parse_pose(robot.get("world_from_base", {"xyz": [0, 0, 0]}), "robot.world_from_base")
    home = _vec(robot.get("home", [0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0]), "robot.home", 6)
    params = UR_PARAMS[model]
    lim = np.minimum(np.asarray(params.position_limit), 2 * np.pi)
    if np.any(np.abs(home) > lim):
        raise _err("robot.home", f"home {home.tolist()} is outside the joint limits +-{lim.tolist()} rad")
    tool = _tool(_req(data, "gripper", ""), "gripper")

    camera = data.get("camera")
    world_from_camera = None
    if camera is not None:
        if not isinstance(camera, dict):
            raise _err("camera", f"expected a mapping, got {camera!r}")
        if "world_from_camera" in camera:
            world_from_camera = parse_pose(camera["world_from_camera"], "camera.world_from_camera")
        elif camera.get("from_scene", False) is not True:
            raise _err("camera", "give world_from_camera or from_scene: true")

    boxes: list[BoxSpec] = []
    if "table" in data:
        boxes.append(_box(data["table"], "table", "table"))
    bin_spec = None
    if "bin" in data:
        b = data["bin"]
        if not isinstance(b, dict):
            raise _err("bin", f"expected a mapping, got {b!r}")
        bin_spec = BinSpec(
            parse_pose(_req(b, "pose", "bin"), "bin.pose"),
            _vec(_req(b, "inner_size", "bin"), "bin.inner_size", 3, positive=True),
            _num(b.get("wall_m", 0.01), "bin.wall_m", 1e-3, 0.2),
        )
        boxes.extend(bin_spec.boxes())
    if "conveyor" in data:
        boxes.append(_box(data["conveyor"], "conveyor", "conveyor"))
    fixtures = data.get("fixtures", [])
    if not isinstance(fixtures, list):
        raise _err("fixtures", f"expected a list, got {fixtures!r}")
    for i, f in enumerate(fixtures):
        boxes.append(_box(f, f"fixtures[{i}]", f"fixture_{i}"))
    names = [b.name for b in boxes]
    if len(set(names)) != len(names):
        raise _err("fixtures", f"box names must be unique, got {names}")

    places_raw = _req(data, "place", "")
    if not isinstance(places_raw, list) or not places_raw:
        raise _err("place", "expected a non-empty list of place poses")
    places = []
    for i, p in enumerate(places_raw):
        if not isinstance(p, dict):
            raise _err(f"place[{i}]", f"expected a mapping, got {p!r}")
        places.append(
            PlaceSpec(
                str(p.get("name", f"place_{i}")),
                parse_pose(_req(p, "world_from_tcp", f"place[{i}]"), f"place[{i}].world_from_tcp"),
                _num(p.get("approach_m", 0.1), f"place[{i}].approach_m", 0.0, 1.0),
            )
        )

    templates = data.get("templates")
    templates_path = None
    if templates is not None:
        if not isinstance(templates, str):
            raise _err("templates", f"expected a path string, got {templates!r}")
        templates_path = (Path(base_dir) / templates).resolve()

    motion = data.get("motion", {})
    if not isinstance(motion, dict):
        raise _err("motion", f"expected a mapping, got {motion!r}")
    vel_cap = motion.get("joint_velocity", 1.0)
    vel = np.minimum(
        np.full(6, _num(vel_cap, "motion.joint_velocity", 1e-3))
        if not isinstance(vel_cap, list)
        else _vec(vel_cap, "motion.joint_velocity", 6, True),
        np.asarray(params.velocity_limit),
    )
    acc_cap = motion.get("joint_acceleration", 2.0)
    acc = (
        np.full(6, _num(acc_cap, "motion.joint_acceleration", 1e-3))
        if not isinstance(acc_cap, list)
        else _vec(acc_cap, "motion.joint_acceleration", 6, True)
    )
    ws = motion.get("workspace", {"min": [-5, -5, -5], "max": [5, 5, 5]})
    if not isinstance(ws, dict):
        raise _err("motion.workspace", f"expected a mapping with min and max, got {ws!r}")
    ws_min = _vec(_req(ws, "min", "motion.workspace"), "motion.workspace.min", 3)
    ws_max = _vec(_req(ws, "max", "motion.workspace"), "motion.workspace.max", 3)
    if np.any(ws_min >= ws_max):
        raise _err("motion.workspace", f"min {ws_min.tolist()} must be below max {ws_max.tolist()}")
    limits = MotionLimits(
        vel, acc, _num(motion.get("tcp_speed_m_s", 0.25), "motion.tcp_speed_m_s", 1e-3, 5.0), ws_min, ws_max
    )

    planning = data.get("planning", {})
    if not isinstance(planning, dict):
        raise _err("planning", f"expected a mapping, got {planning!r}")
    unknown_p = set(planning) - {"entry_clearance_m", "lift_m", "voxel_m"}
    if unknown_p:
        raise _err(f"planning.{sorted(unknown_p)[0]}", "unknown key; expected entry_clearance_m, lift_m, voxel_m")
    return CellConfig(
        name=str(data.get("name", source.stem if source else "cell")),
        robot_model=model,
        world_from_base=world_from_base,
        home_q=home,
        tool=tool,
        world_from_camera=world_from_camera,
        static_boxes=tuple(boxes),
        bin=bin_spec,
        places=tuple(places),
        templates_path=templates_path,
        motion=limits,
        entry_clearance_m=_num(planning.get("entry_clearance_m", 0.05), "planning.entry_clearance_m", 0.0, 1.0),
        lift_m=_num(planning.get("lift_m", 0.08), "planning.lift_m", 0.0, 1.0),
        voxel_m=_num(planning.get("voxel_m", 0.01), "planning.voxel_m", 1e-3, 0.2),
        source=source,
    )
