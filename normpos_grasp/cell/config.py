"""Cell YAML: schema, loader and validation. Every error is a `CellConfigError` whose `path` names the key
(for example `gripper.stroke_m`). The schema is documented in docs/cells.md.

Poses in the file are either `{xyz: [x, y, z], rpy_deg: [roll, pitch, yaw]}` (metres; degrees, R = Rz Ry Rx),
`{xyz, rpy}` (radians) or a 4x4 nested list.
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterable
from dataclasses import dataclass, field, replace
from difflib import get_close_matches
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from normpos_grasp.camera.hand_eye_io import read_flange_from_camera
from normpos_grasp.camera.model import ROTATION_TOL, check_rotation, check_world_from_camera
from normpos_grasp.errors import CellConfigError, ExtrinsicsError, InputError, NormposError
from normpos_grasp.io.yaml_safe import load_yaml_file
from normpos_grasp.kinematics.gripper import Gripper
from normpos_grasp.kinematics.ur_params import JOINT_NAMES, UR_PARAMS
from normpos_grasp.records.tool import ToolModel, parallel_gripper, suction_tool, tool_from_gripper, with_idle
from normpos_grasp.typing import FloatArray
from normpos_grasp.validation import short_repr

from .gripper_driver import GripperDriverSpec, parse_gripper_driver
from .places import pattern_slots
from .wrist_camera import D435_BODY_M, WristCamera

# Ceilings of the motion caps. Joint speeds: each joint's rated speed (ur_params, from UR's ROS description).
# UR rates no joint or tool acceleration (the ROS description says has_acceleration_limits: false), so the
# acceleration and tool ceilings are the bounds ur_rtde itself enforces on moveJ / moveL arguments
# (ur_rtde rtde_control_interface.h: UR_JOINT_ACCELERATION_MAX 40.0 rad/s^2, UR_TOOL_VELOCITY_MAX 3.0 m/s,
# UR_TOOL_ACCELERATION_MAX 150.0 m/s^2): a cap above them could never be commanded. execution.SafetyLimits
# applies the same numbers.
MAX_JOINT_ACCELERATION = 40.0  # rad/s^2
MAX_TCP_SPEED = 3.0  # m/s
MAX_TCP_ACCELERATION = 150.0  # m/s^2
# Any coordinate or size in a cell file: a cell is a few metres across; larger values are millimetres.
MAX_EXTENT_M = 20.0
MAX_TEXT = 200  # characters of a name or path

_TOP_KEYS = (
    "name",
    "robot",
    "gripper",
    "camera",
    "floor_z",
    "table",
    "bin",
    "bins",
    "conveyor",
    "fixtures",
    "place",
    "templates",
    "motion",
    "planning",
    "watch",
)
_ROBOT_KEYS = ("model", "serial_number", "world_from_base", "home")
_CAMERA_KEYS = ("mount", "world_from_camera", "from_scene")
_WRIST_CAMERA_KEYS = ("mount", "flange_from_camera", "capture", "body_size_m", "camera_from_body", "cable_clearance_m")
CAMERA_MOUNTS = ("fixed", "wrist")
MAX_CAPTURE_POSES = 16
_POSE_KEYS = ("xyz", "rpy_deg", "rpy")
_BOX_KEYS = ("pose", "size")
_FIXTURE_KEYS = ("name", "pose", "size")
_BIN_KEYS = ("name", "pose", "inner_size", "wall_m", "place", "capture")
MAX_BINS = 16
_PLACE_KEYS = ("name", "world_from_tcp", "approach_m", "pattern", "align_part")
_MOTION_KEYS = ("joint_velocity", "joint_acceleration", "tcp_speed_m_s", "tcp_acceleration_m_s2", "workspace")
_WORKSPACE_KEYS = ("min", "max")
_PLANNING_KEYS = ("entry_clearance_m", "lift_m", "voxel_m")
_PACKAGED_GRIPPER_KEYS = ("model", "kind", "mount", "payload_kg", "driver")
_CUSTOM_COMMON_KEYS = ("model", "kind", "mount", "payload_kg", "flange_to_tcp_m", "body_size_m", "driver")
_CUSTOM_PARALLEL_KEYS = (
    *_CUSTOM_COMMON_KEYS,
    "stroke_m",
    "min_opening_m",
    "finger_length_m",
    "finger_width_m",
    "finger_thickness_m",
    "grip_depth_m",
)
_CUSTOM_SUCTION_KEYS = (*_CUSTOM_COMMON_KEYS, "cup_diameter_m", "stem_diameter_m")
_WATCH_KEYS = (
    "zones",
    "margin_m",
    "arm_margin_m",
    "stop",
    "require_ack",
    "k_sigma",
    "min_blob_px",
    "approach_m",
    "silhouette_pad_m",
    "latency_s",
    "held_radius_m",
    "downsample",
    "static_reference",
    "drift",
)
_ZONE_KEYS = ("name", "min", "max")
_DRIFT_KEYS = ("max_translation_mm", "max_rotation_deg", "max_shift_px")
WATCH_STOP_KINDS = ("stop", "protective")


@dataclass(frozen=True, eq=False)
class BoxSpec:
    """A static box: `world_from_box` (4, 4) at its centre, `size` (3,) full extents, m."""

    name: str
    world_from_box: FloatArray
    size: FloatArray


@dataclass(frozen=True, eq=False)
class BinSpec:
    """An open bin: `world_from_bin` (4, 4) at the centre of the inner floor (z up), `inner_size` (3,) inner
    length, width and wall height, `wall_m` wall and floor thickness, m.

    name: 'bin' for the one-bin spelling (`bin:`), else its name in `bins:`; places: names of the `place:` entries
    its parts go to (a pattern entry stands for all of its slots; empty: every place); capture: the wrist camera's
    capture pose that sees it (an index of `camera.capture`; None: any)."""

    world_from_bin: FloatArray
    inner_size: FloatArray
    wall_m: float = 0.01
    name: str = "bin"
    places: tuple[str, ...] = ()
    capture: int | None = None

    def boxes(self) -> list[BoxSpec]:
        """Floor and four walls as boxes, named 'bin/floor', 'bin/wall_x+', ... for the bin named 'bin', else
        'bin/<name>/floor', ..."""
        lx, ly, h = (float(v) for v in self.inner_size)
        w = self.wall_m
        parts = {
            "floor": ((0.0, 0.0, -w / 2), (lx + 2 * w, ly + 2 * w, w)),
            "wall_x+": ((lx / 2 + w / 2, 0.0, h / 2), (w, ly + 2 * w, h)),
            "wall_x-": ((-lx / 2 - w / 2, 0.0, h / 2), (w, ly + 2 * w, h)),
            "wall_y+": ((0.0, ly / 2 + w / 2, h / 2), (lx, w, h)),
            "wall_y-": ((0.0, -ly / 2 - w / 2, h / 2), (lx, w, h)),
        }
        prefix = "bin" if self.name == "bin" else f"bin/{self.name}"
        out = []
        for name, (centre, size) in parts.items():
            pose = np.eye(4)
            pose[:3, 3] = centre
            out.append(BoxSpec(f"{prefix}/{name}", self.world_from_bin @ pose, np.asarray(size, dtype=np.float64)))
        return out

    def contains(self, point: Any, above_m: float = 0.1, tol_m: float = 0.01) -> bool:
        """Whether world point (3,) lies over the bin's inner floor (within `tol_m` of its footprint), between the
        floor (less `tol_m`) and `above_m` over the rim (a part sticking out of a full bin is still in it), m."""
        return bool(self.contains_points(np.asarray(point, dtype=np.float64).reshape(1, 3), above_m, tol_m)[0])

    def contains_points(self, points: FloatArray, above_m: float = 0.1, tol_m: float = 0.01) -> Any:
        """`contains` for world points (N, 3): a bool array (N,)."""
        inv = np.linalg.inv(np.asarray(self.world_from_bin, dtype=np.float64))
        local = np.asarray(points, dtype=np.float64) @ inv[:3, :3].T + inv[:3, 3]
        lx, ly, h = (float(v) for v in self.inner_size)
        return (
            (np.abs(local[:, 0]) <= lx / 2 + tol_m)
            & (np.abs(local[:, 1]) <= ly / 2 + tol_m)
            & (local[:, 2] >= -tol_m)
            & (local[:, 2] <= h + above_m)
        )

    def outer_bounds(self) -> tuple[FloatArray, FloatArray]:
        """World axis-aligned bounds (lo (3,), hi (3,)) of the bin's floor and walls, m."""
        corners = []
        for box in self.boxes():
            half = np.asarray(box.size) / 2
            signs = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).reshape(3, -1).T
            corners.append((signs * half) @ box.world_from_box[:3, :3].T + box.world_from_box[:3, 3])
        pts = np.concatenate(corners)
        return pts.min(axis=0), pts.max(axis=0)

    @property
    def rim_z(self) -> float:
        """World height of the bin rim, m."""
        return float(self.world_from_bin[2, 3] + self.inner_size[2])


@dataclass(frozen=True, eq=False)
class ZoneSpec:
    """A watched volume: an axis-aligned box of the world frame from corner `lo` (3,) to corner `hi` (3,), m."""

    name: str
    lo: FloatArray
    hi: FloatArray


@dataclass(frozen=True, eq=False)
class WatchSpec:
    """The `watch:` section (docs/watch.md): zones watched while the arm moves and the per-frame drift check.

    zones: watched boxes; margin_m: each zone grows by this on every side, m; arm_margin_m: also watch everything
    within this distance of the arm's links at the commanded joints, m (0: off); stop: 'stop' (stopJ with the
    driver's deceleration) or 'protective' (a protective stop, unlocked on the pendant); require_ack: after a zone
    stop the loop waits for the operator's acknowledgement before it re-plans; k_sigma: a pixel is nearer than
    expected when it is nearer by more than k_sigma times the sensor's depth noise at that depth; min_blob_px:
    smallest connected blob that counts, in watch pixels (after `downsample`); approach_m: width of the approach
    band around each zone (a blob coming in within it stops the arm before enough of it is inside; 0: off; the
    default is ISO 13855's 2.0 m/s over two frames at 30 fps), m; silhouette_pad_m: the arm's
    predicted silhouette grows by this (tracking error), m; latency_s: the silhouette covers every pose the arm
    took during this window before a frame is checked (the camera's and the stream's delay), s; held_radius_m:
    radius around the TCP ignored for a held part (0: from the plan's part), m; downsample: the depth stream is
    reduced by this factor before the comparison; static_reference: static reference JSON (`calibrate extrinsics
    --image`) checked in every frame before planning (None: no drift check); drift_*: the drift check's tolerances
    (mm, deg, and the largest shift of a reference point, px).
    """

    zones: tuple[ZoneSpec, ...] = ()
    margin_m: float = 0.0
    arm_margin_m: float = 0.0
    stop: str = "stop"
    require_ack: bool = False
    k_sigma: float = 5.0
    min_blob_px: int = 12
    approach_m: float = 0.13
    silhouette_pad_m: float = 0.06
    latency_s: float = 0.1
    held_radius_m: float = 0.0
    downsample: int = 2
    static_reference: Path | None = None
    drift_max_translation_mm: float = 1.0
    drift_max_rotation_deg: float = 0.1
    drift_max_shift_px: float = 0.35


@dataclass(frozen=True, eq=False)
class PlaceSpec:
    """A place pose: `world_from_tcp` (4, 4) at release; `approach_m` straight-line length above it; align_part:
    the TCP turns about the world z axis so the part's x axis (from its fitted pose) lies along this pose's x
    axis (else the TCP keeps this orientation and the part lands as it was grasped). single_use: a slot of a
    place pattern: the loop uses it once and the part left there joins the collision world (a plain place pose is
    reused, e.g. a conveyor that carries parts away)."""

    name: str
    world_from_tcp: FloatArray
    approach_m: float = 0.1
    align_part: bool = False
    single_use: bool = False
    group: str = ""  # the `place:` entry it comes from (a pattern's name for its slots; '': its own name)

    @property
    def entry(self) -> str:
        """The name of the `place:` entry this pose comes from (what a bin's `place:` list names)."""
        return self.group or self.name


@dataclass(frozen=True, eq=False)
class MotionLimits:
    """Caps for planned motion: joint_velocity (6,) rad/s (each within the robot's rated joint speed),
    joint_acceleration (6,) rad/s^2 (each within `MAX_JOINT_ACCELERATION`), tcp_speed_m_s and
    tcp_acceleration_m_s2 for Cartesian segments (within `MAX_TCP_SPEED`, `MAX_TCP_ACCELERATION`), workspace box
    (min (3,), max (3,)) the TCP must stay in, m; workspace_given: the file set it (else a +-5 m default box)."""

    joint_velocity: FloatArray
    joint_acceleration: FloatArray
    tcp_speed_m_s: float
    workspace_min: FloatArray
    workspace_max: FloatArray
    tcp_acceleration_m_s2: float = 2.0
    workspace_given: bool = False


@dataclass(frozen=True, eq=False)
class CellConfig:
    """A validated cell: robot, tool, static geometry, place poses, template library and limits.

    robot_serial: the controller's serial number when the file names one (execution compares it);
    floor_z: world height of the floor when the file gives one, m.
    bins: every bin of the cell (`bins:`, or the one `bin:`), their walls among `static_boxes`; bin: the bin a plan
    picks from first (`plan_pick` tries the others after it, in turn): the one bin, or the first of `bins` unless
    `picking_from` chose another. A cell built with only `bin` gets bins = (bin,)."""

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
    robot_serial: str | None = None
    floor_z: float | None = None
    gripper_driver: GripperDriverSpec | None = None  # `gripper.driver` (None: not configured)
    source_sha256: str = ""  # of the file it was read from ('' for a cell built from a mapping)
    watch: WatchSpec | None = None  # the `watch:` section (None: no zone watch, no drift check)
    wrist_camera: WristCamera | None = None  # `camera: {mount: wrist, ...}` (world_from_camera is then None)
    bins: tuple[BinSpec, ...] = ()
    # every tool on the flange (`gripper:` as a list), the first = `tool`, each with the others' bodies among its
    # shapes (`records.tool.with_idle`); a one-tool cell has (tool,). gripper_drivers: each tool's `driver`
    tools: tuple[ToolModel, ...] = ()
    gripper_drivers: tuple[GripperDriverSpec | None, ...] = ()

    def __post_init__(self) -> None:
        if not self.tools or self.tools[0] is not self.tool:
            # a cell built with one tool, or whose `tool` was replaced (`dataclasses.replace`): that tool alone
            object.__setattr__(self, "tools", (self.tool,))
            object.__setattr__(self, "gripper_drivers", ())
        if len(self.gripper_drivers) != len(self.tools) or self.gripper_drivers[0] is not self.gripper_driver:
            rest = self.gripper_drivers[1:] if len(self.gripper_drivers) == len(self.tools) else ()
            object.__setattr__(
                self, "gripper_drivers", (self.gripper_driver, *rest) + (None,) * (len(self.tools) - 1 - len(rest))
            )
        bins = tuple(self.bins)
        if not bins and self.bin is not None:
            bins = (self.bin,)
        if bins and self.bin is None:
            object.__setattr__(self, "bin", bins[0])
        if self.bin is not None and all(b.name != self.bin.name for b in bins):
            raise CellConfigError(f"bin {self.bin.name!r} is not one of the cell's bins {[b.name for b in bins]}")
        object.__setattr__(self, "bins", bins)

    def with_tool(self, tool: ToolModel) -> CellConfig:
        """This cell planning with `tool` (one of `tools`) alone: `tool` and `tools` = (tool,), its driver."""
        driver = self.tool_named(tool.name)[1]
        return replace(self, tool=tool, tools=(tool,), gripper_driver=driver, gripper_drivers=(driver,))

    def tool_named(self, name: str) -> tuple[ToolModel, GripperDriverSpec | None]:
        """The tool called `name` (a plan's `tool.name`) and its `driver`; InputError naming the cell's tools."""
        for tool, driver in zip(self.tools, self.gripper_drivers, strict=True):
            if tool.name == name:
                return tool, driver
        names = ", ".join(t.name for t in self.tools)
        raise InputError(f"cell {self.name!r} has no tool {name!r}; its tools: {names}")

    def refuse_dual_tool(self, what: str) -> None:
        """InputError when the cell has several tools on its flange: `what` (a real controller's driver) switches
        one gripper's wiring only, so it cannot actuate the tool a plan chose."""
        if len(self.tools) > 1:
            names = ", ".join(t.name for t in self.tools)
            raise InputError(
                f"cell {self.name!r} has {len(self.tools)} tools on its flange ({names}); {what} actuates one gripper "
                "and cannot switch to the tool a plan chose: use --robot sim, or a cell with one gripper"
            )

    def bin_named(self, name: str) -> BinSpec:
        """The bin called `name`; InputError naming the cell's bins otherwise."""
        for b in self.bins:
            if b.name == name:
                return b
        raise InputError(f"cell {self.name!r} has no bin {name!r}; its bins: {', '.join(b.name for b in self.bins)}")

    def picking_from(self, name: str) -> CellConfig:
        """This cell with bin `name` as the one plans pick from first (the others keep their walls and turns)."""
        chosen = self.bin_named(name)
        return self if self.bin is chosen else replace(self, bin=chosen)

    def next_bin(self, name: str) -> str:
        """The name of the bin after `name` in `bins` (the first after the last)."""
        names = [b.name for b in self.bins]
        return names[(names.index(name) + 1) % len(names)] if name in names else names[0]

    def places_for(self, bin_spec: BinSpec | None) -> tuple[PlaceSpec, ...]:
        """The places (slots still free) the parts of `bin_spec` go to: those of its `place:` list, else all."""
        if bin_spec is None or not bin_spec.places:
            return self.places
        return tuple(p for p in self.places if p.entry in bin_spec.places)

    def bins_region(self, above_m: float = 0.15) -> tuple[FloatArray, FloatArray] | None:
        """(world_from_box (4, 4), size (3,)) of the box holding every bin's interior up to `above_m` over its rim,
        in the first bin's orientation (for one bin: its interior), m; None without a bin."""
        if not self.bins:
            return None
        frame = np.asarray(self.bins[0].world_from_bin, dtype=np.float64)
        inv = np.linalg.inv(frame)
        signs = np.array(np.meshgrid([-0.5, 0.5], [-0.5, 0.5], [0.0, 1.0])).reshape(3, -1).T
        corners = []
        for b in self.bins:
            lx, ly, h = (float(v) for v in b.inner_size)
            local = signs * np.array([lx, ly, h + above_m])
            world = local @ b.world_from_bin[:3, :3].T + b.world_from_bin[:3, 3]
            corners.append(world @ inv[:3, :3].T + inv[:3, 3])
        pts = np.concatenate(corners)
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        centre = np.eye(4)
        centre[:3, 3] = (lo + hi) / 2
        return frame @ centre, hi - lo

    def bin_of(self, point: Any) -> BinSpec | None:
        """The bin whose interior holds world point (3,) (`BinSpec.contains`), None when none does."""
        return next((b for b in self.bins if b.contains(point)), None)

    def record(self) -> dict[str, str]:
        """What a plan records of the cell it was made in: name, file path and the file's SHA-256."""
        out = {"name": self.name}
        if self.source is not None:
            out["path"] = str(Path(self.source).resolve())
            out["sha256"] = self.source_sha256
        return out

    @property
    def entry_z(self) -> float:
        """World height of the bin entry / exit poses (rim + clearance), or -inf without a bin."""
        return self.bin.rim_z + self.entry_clearance_m if self.bin is not None else -np.inf

    @property
    def camera_floor_z(self) -> float | None:
        """Lowest plausible camera height, m: above `floor_z` and above the lowest surface parts rest on (table
        top, bin floors, conveyor belt), since a camera below all of them cannot see a part; None when the cell
        gives neither."""
        return _camera_floor(self.floor_z, self.static_boxes, self.bins)

    def check_camera(self, world_from_camera: Any, name: str = "world_from_camera") -> FloatArray:
        """Validate extrinsics against this cell (camera.model.check_world_from_camera with `camera_floor_z`, and
        a camera strictly inside a given `motion.workspace` refused); for cameras that come from a dataset
        (`camera: {from_scene: true}`). Raises ExtrinsicsError."""
        pose = check_world_from_camera(world_from_camera, name, floor_z_m=self.camera_floor_z)
        _check_outside_workspace(pose, self.motion, name)
        return pose


# packaged in normpos_grasp/examples/cells
BUILTIN_CELLS = (
    "ur5e_bin_parallel",
    "ur10e_conveyor_suction",
    "ur5e_wrist_camera",
    "ur5e_two_bins",
    "ur5e_bin_dual",
)


def resolve_cell(name_or_path: str | Path) -> CellConfig:
    """A packaged example cell by name (one of BUILTIN_CELLS) or a cell YAML path: every command takes either."""
    path = Path(name_or_path)
    if path.suffix in (".yaml", ".yml") or path.exists():
        return load_cell(path)
    packaged = resources.files("normpos_grasp.examples").joinpath("cells", f"{name_or_path}.yaml")
    if not packaged.is_file():
        raise InputError(f"unknown cell {str(name_or_path)!r}: give a YAML path or one of {', '.join(BUILTIN_CELLS)}")
    with resources.as_file(packaged) as file:
        return load_cell(file)


def load_cell(path: str | Path) -> CellConfig:
    """Read and validate a cell YAML file; relative paths inside resolve against its folder.

    The file is parsed by io.yaml_safe (no anchors, aliases, merge keys or duplicate keys; errors in one line)."""
    p = Path(path)
    try:
        data = load_yaml_file(p)
    except InputError as exc:
        raise CellConfigError(str(exc)) from exc
    cell = cell_from_dict(data, base_dir=p.parent, source=p)
    return replace(cell, source_sha256=hashlib.sha256(p.read_bytes()).hexdigest())


def _err(path: str, msg: str) -> CellConfigError:
    return CellConfigError(msg, path)


def _join(path: str, key: str) -> str:
    return f"{path}.{key}" if path else key


def _mapping(v: Any, path: str, allowed: Iterable[str], what: str = "a mapping") -> dict[str, Any]:
    """`v` as a mapping whose keys are all in `allowed`; an unknown key is an error naming its full path."""
    if not isinstance(v, dict):
        raise _err(path, f"expected {what}, got {type(v).__name__} {short_repr(v)}")
    names = tuple(allowed)
    for key in v:
        if not isinstance(key, str):
            raise _err(path or "(top level)", f"keys must be text, got {type(key).__name__} {key!r}")
        if key not in names:
            close = get_close_matches(key, names, n=1, cutoff=0.75)
            hint = f"did you mean {close[0]!r}? " if close else ""
            raise _err(_join(path, key), f"unknown key; {hint}allowed here: {', '.join(names)}")
    return v


def _req(d: dict[str, Any], key: str, path: str) -> Any:
    if key not in d:
        raise _err(_join(path, key), "required key is missing")
    return d[key]


def _text(v: Any, path: str, max_len: int = MAX_TEXT) -> str:
    if not isinstance(v, str) or not v.strip():
        raise _err(path, f"expected non-empty text, got {type(v).__name__} {short_repr(v)}")
    if len(v) > max_len or any(ord(c) < 32 for c in v):
        raise _err(path, f"expected one line of at most {max_len} characters, got {len(v)} characters")
    return v


def _num(v: Any, path: str, lo: float = -np.inf, hi: float = np.inf, unit: str = "") -> float:
    """A finite number in [lo, hi]; `unit` names it in the message."""
    u = f" {unit}" if unit else ""
    if isinstance(v, bool) or not isinstance(v, int | float):
        hint = ""
        if isinstance(v, str):
            try:
                float(v)
                hint = " (YAML reads an exponent without a dot, such as 1e3, as text: write 1.0e3)"
            except ValueError:
                pass
        raise _err(path, f"expected a number{u}, got {type(v).__name__} {short_repr(v)}{hint}")
    f = float(v)
    if not np.isfinite(f):
        raise _err(path, f"expected a finite number{u}, got {v!r}")
    if f < lo or f > hi:
        raise _err(path, f"{v!r}{u} is outside [{lo:g}, {hi:g}]{u}")
    return f


def _length(v: Any, path: str, lo: float = -MAX_EXTENT_M, hi: float = MAX_EXTENT_M) -> float:
    """A length or coordinate in metres; beyond `MAX_EXTENT_M` the message says it looks like millimetres."""
    f = _num(v, path, unit="m")
    if abs(f) > MAX_EXTENT_M:
        raise _err(path, f"{v!r} m is more than {MAX_EXTENT_M:g} m: looks like millimetres; cell files are in metres")
    if f < lo or f > hi:
        raise _err(path, f"{v!r} m is outside [{lo:g}, {hi:g}] m")
    return f


def _list(v: Any, path: str, n: int) -> list[Any]:
    if not isinstance(v, list) or len(v) != n:
        raise _err(path, f"expected a list of {n} numbers, got {short_repr(v)}")
    return v


def _vec(v: Any, path: str, n: int, lo: float = -np.inf, hi: float = np.inf, unit: str = "") -> FloatArray:
    return np.array([_num(x, f"{path}[{i}]", lo, hi, unit) for i, x in enumerate(_list(v, path, n))])


def _lengths(v: Any, path: str, n: int, positive: bool = False) -> FloatArray:
    lo = 1e-4 if positive else -MAX_EXTENT_M
    return np.array([_length(x, f"{path}[{i}]", lo=lo) for i, x in enumerate(_list(v, path, n))])


def _rpy(r: FloatArray) -> FloatArray:
    cr, sr = np.cos(r[0]), np.sin(r[0])
    cp, sp = np.cos(r[1]), np.sin(r[1])
    cy, sy = np.cos(r[2]), np.sin(r[2])
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    return rz @ ry @ rx


def parse_pose(v: Any, path: str) -> FloatArray:
    """A (4, 4) pose from `{xyz, rpy_deg}`, `{xyz, rpy}` or a 4x4 nested list; errors name `path`.

    Translations are metres within `MAX_EXTENT_M`; a 4x4 rotation block must be orthonormal within
    camera.model.ROTATION_TOL (it is then projected onto the nearest rotation) with determinant +1."""
    if isinstance(v, dict):
        d = _mapping(v, path, _POSE_KEYS, "a pose")
        pose = np.eye(4)
        pose[:3, 3] = _lengths(d.get("xyz", [0, 0, 0]), f"{path}.xyz", 3)
        if "rpy_deg" in d and "rpy" in d:
            raise _err(path, "give either rpy_deg or rpy, not both")
        if "rpy_deg" in d:
            pose[:3, :3] = _rpy(np.deg2rad(_vec(d["rpy_deg"], f"{path}.rpy_deg", 3, -360.0, 360.0, "deg")))
        elif "rpy" in d:
            pose[:3, :3] = _rpy(_vec(d["rpy"], f"{path}.rpy", 3, -2 * np.pi, 2 * np.pi, "rad"))
        return pose
    if isinstance(v, list) and len(v) == 4:
        rows = [_vec(row, f"{path}[{i}]", 4) for i, row in enumerate(v)]
        pose = np.stack(rows)
        if not np.allclose(pose[3], [0, 0, 0, 1], atol=1e-9):
            raise _err(f"{path}[3]", f"the last row must be [0, 0, 0, 1], got {pose[3].tolist()}")
        for i in range(3):
            _length(pose[i, 3], f"{path}[{i}][3]")
        try:
            pose[:3, :3] = check_rotation(pose[:3, :3], "the rotation block", ROTATION_TOL)
        except InputError as exc:
            raise _err(path, str(exc)) from exc
        return pose
    raise _err(path, f"expected a pose ({{xyz: [..], rpy_deg: [..]}} or a 4x4 list), got {short_repr(v)}")


def _box(v: Any, path: str, name: str, keys: tuple[str, ...] = _BOX_KEYS) -> BoxSpec:
    d = _mapping(v, path, keys, "a mapping with pose and size")
    return BoxSpec(
        _text(d["name"], f"{path}.name") if "name" in d else name,
        parse_pose(_req(d, "pose", path), f"{path}.pose"),
        _lengths(_req(d, "size", path), f"{path}.size", 3, positive=True),
    )


def _payload(v: Any, path: str, robot: str) -> float:
    rated = UR_PARAMS[robot].payload_kg
    f = _num(v, path, 0.0, unit="kg")
    if f > rated:
        raise _err(path, f"{f:g} kg is above the {robot}'s rated payload {rated:g} kg")
    return f


def _tool(v: Any, path: str, robot: str) -> ToolModel:
    if not isinstance(v, dict):
        raise _err(path, f"expected a mapping, got {short_repr(v)}")
    kind = v.get("kind")
    if kind is not None and kind not in ("parallel", "suction"):
        raise _err(f"{path}.kind", f"expected 'parallel' or 'suction', got {short_repr(kind)}")
    if "flange_to_tcp_m" not in v:
        # a packaged gripper (kinematics.Gripper), optionally mounted through an adapter
        extra = sorted(set(v) - set(_PACKAGED_GRIPPER_KEYS))
        if extra and all(k in _CUSTOM_PARALLEL_KEYS or k in _CUSTOM_SUCTION_KEYS for k in extra):
            raise _err(
                _join(path, extra[0]),
                "custom geometry keys need flange_to_tcp_m as well (a custom "
                "gripper); for a packaged one give only model, kind, mount, payload_kg and driver",
            )
        d = _mapping(v, path, _PACKAGED_GRIPPER_KEYS)
        model = _text(_req(d, "model", path), f"{path}.model")
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
            object.__setattr__(tool, "payload_kg", _payload(d["payload_kg"], f"{path}.payload_kg", robot))
        return tool
    if kind is None:
        raise _err(f"{path}.kind", "a custom gripper (flange_to_tcp_m given) needs kind: parallel or suction")
    d = _mapping(v, path, _CUSTOM_PARALLEL_KEYS if kind == "parallel" else _CUSTOM_SUCTION_KEYS)
    model = _text(_req(d, "model", path), f"{path}.model")

    def length(key: str, default: float | None, lo: float, hi: float) -> float:
        value = _req(d, key, path) if default is None else d.get(key, default)
        return _length(value, f"{path}.{key}", lo, hi)

    def body(default: list[float]) -> tuple[float, float, float]:
        b = [
            _length(x, f"{path}.body_size_m[{i}]", 1e-3, 2.0)
            for i, x in enumerate(_list(d.get("body_size_m", default), f"{path}.body_size_m", 3))
        ]
        return (b[0], b[1], b[2])

    flange_to_tcp = length("flange_to_tcp_m", 0.15, 0.0, 1.0)
    payload = _payload(d.get("payload_kg", 2.0), f"{path}.payload_kg", robot)
    if kind == "parallel":
        tool = parallel_gripper(
            model,
            stroke_m=length("stroke_m", None, 1e-3, 1.0),
            finger_length_m=length("finger_length_m", 0.045, 1e-3, 0.5),
            flange_to_tcp_m=flange_to_tcp,
            finger_width_m=length("finger_width_m", 0.02, 1e-3, 0.5),
            finger_thickness_m=length("finger_thickness_m", 0.01, 1e-3, 0.5),
            body_size_m=body([0.14, 0.06, 0.09]),
            min_opening_m=length("min_opening_m", 0.0, 0.0, 1.0),
            grip_depth_m=length("grip_depth_m", 0.015, 0.0, 0.5),
            payload_kg=payload,
        )
    else:
        tool = suction_tool(
            model,
            flange_to_tcp_m=flange_to_tcp,
            cup_diameter_m=length("cup_diameter_m", 0.03, 1e-3, 0.5),
            stem_diameter_m=length("stem_diameter_m", 0.02, 1e-3, 0.5),
            body_size_m=body([0.06, 0.06, 0.05]),
            payload_kg=payload,
        )
    if "mount" in d:
        object.__setattr__(tool, "flange_from_tcp", parse_pose(d["mount"], f"{path}.mount") @ tool.flange_from_tcp)
    if tool.min_opening_m > tool.stroke_m:
        raise _err(f"{path}.min_opening_m", f"min_opening_m {tool.min_opening_m} exceeds stroke_m {tool.stroke_m}")
    return tool


def _joint_caps(v: Any, path: str, ceiling: FloatArray, unit: str, source: str) -> FloatArray:
    """Per-joint caps from one number or 6; each in [1e-3, ceiling_j]."""
    caps = np.full(6, _num(v, path, unit=unit)) if not isinstance(v, list) else _vec(v, path, 6, unit=unit)
    for j in range(6):
        where = path if not isinstance(v, list) else f"{path}[{j}]"
        if caps[j] < 1e-3:
            raise _err(where, f"{caps[j]:g} {unit} is below the smallest cap 0.001 {unit}")
        if caps[j] > ceiling[j] * (1 + 1e-9):
            scalar = not isinstance(v, list)
            if scalar and np.all(ceiling == ceiling[0]):
                whose = "the ceiling"
                one = ""
            else:
                whose = f"{JOINT_NAMES[j]}'s ceiling"
                one = " (one number caps every joint; give 6)" if scalar else ""
            raise _err(where, f"{caps[j]:g} {unit} is above {whose} {ceiling[j]:.4g} {unit} ({source}){one}")
    return caps


def _motion(v: Any, model: str) -> MotionLimits:
    d = _mapping(v, "motion", _MOTION_KEYS)
    rated = np.asarray(UR_PARAMS[model].velocity_limit, dtype=np.float64)
    vel = _joint_caps(d.get("joint_velocity", 1.0), "motion.joint_velocity", rated, "rad/s", f"{model} rated speed")
    acc = _joint_caps(
        d.get("joint_acceleration", 2.0),
        "motion.joint_acceleration",
        np.full(6, MAX_JOINT_ACCELERATION),
        "rad/s^2",
        "ur_rtde's UR_JOINT_ACCELERATION_MAX; UR rates no higher joint acceleration",
    )
    tcp_v = d.get("tcp_speed_m_s", 0.25)
    tcp_speed = _num(tcp_v, "motion.tcp_speed_m_s", unit="m/s")
    if not 1e-3 <= tcp_speed <= MAX_TCP_SPEED:
        raise _err(
            "motion.tcp_speed_m_s",
            f"{tcp_v!r} m/s is outside [0.001, {MAX_TCP_SPEED:g}] m/s (ur_rtde's UR_TOOL_VELOCITY_MAX)",
        )
    tcp_a = d.get("tcp_acceleration_m_s2", 2.0)
    tcp_acc = _num(tcp_a, "motion.tcp_acceleration_m_s2", unit="m/s^2")
    if not 1e-3 <= tcp_acc <= MAX_TCP_ACCELERATION:
        raise _err(
            "motion.tcp_acceleration_m_s2",
            f"{tcp_a!r} m/s^2 is outside [0.001, {MAX_TCP_ACCELERATION:g}] m/s^2 (ur_rtde's UR_TOOL_ACCELERATION_MAX)",
        )
    ws = _mapping(d.get("workspace", {"min": [-5, -5, -5], "max": [5, 5, 5]}), "motion.workspace", _WORKSPACE_KEYS)
    ws_min = _lengths(_req(ws, "min", "motion.workspace"), "motion.workspace.min", 3)
    ws_max = _lengths(_req(ws, "max", "motion.workspace"), "motion.workspace.max", 3)
    if np.any(ws_min >= ws_max):
        raise _err("motion.workspace", f"min {ws_min.tolist()} must be below max {ws_max.tolist()}")
    return MotionLimits(vel, acc, tcp_speed, ws_min, ws_max, tcp_acc, "workspace" in d)


def _check_outside_bounds(world_from_tcp: FloatArray, motion: MotionLimits, path: str) -> None:
    """A place (slot) whose TCP lies outside a given motion.workspace in x or y can never be planned: refuse it
    here (its z is the surface height; the planner raises the TCP above it)."""
    pos = world_from_tcp[:3, 3]
    lo, hi = motion.workspace_min[:2], motion.workspace_max[:2]
    if motion.workspace_given and (np.any(pos[:2] < lo) or np.any(pos[:2] > hi)):
        raise _err(
            path,
            f"the place TCP at {np.round(pos, 3).tolist()} m is outside motion.workspace in x or y (min "
            f"{motion.workspace_min.tolist()}, max {motion.workspace_max.tolist()}): move it or shrink the pattern",
        )


def _check_outside_workspace(world_from_camera: FloatArray, motion: MotionLimits, name: str) -> None:
    """A camera strictly inside the box the TCP may move in could be driven into: refuse it (ExtrinsicsError)."""
    pos = world_from_camera[:3, 3]
    if motion.workspace_given and np.all(pos > motion.workspace_min) and np.all(pos < motion.workspace_max):
        raise ExtrinsicsError(
            f"{name}: the camera at {np.round(pos, 3).tolist()} m is inside motion.workspace "
            f"(min {motion.workspace_min.tolist()}, max {motion.workspace_max.tolist()}), where the arm may be "
            "planned into it; shrink the workspace below or beside the camera, or check the extrinsics",
            float(np.min(np.minimum(pos - motion.workspace_min, motion.workspace_max - pos))),
        )


def _bin(v: Any, path: str, name: str) -> BinSpec:
    """One bin mapping {name, pose, inner_size, wall_m, place, capture} at `path` ('bin' or 'bins[i]')."""
    b = _mapping(v, path, _BIN_KEYS)
    places = b.get("place", [])
    if isinstance(places, str):
        places = [places]
    if not isinstance(places, list) or not places and "place" in b:
        raise _err(_join(path, "place"), f"expected a place name or a non-empty list of them, got {short_repr(places)}")
    capture = b.get("capture")
    if capture is not None and (isinstance(capture, bool) or not isinstance(capture, int) or capture < 0):
        raise _err(
            _join(path, "capture"),
            f"expected the index of a camera.capture pose (0, 1, ...), got {short_repr(capture)}",
        )
    return BinSpec(
        parse_pose(_req(b, "pose", path), _join(path, "pose")),
        _lengths(_req(b, "inner_size", path), _join(path, "inner_size"), 3, positive=True),
        _length(b.get("wall_m", 0.01), _join(path, "wall_m"), 1e-3, 0.2),
        _text(b["name"], _join(path, "name")) if "name" in b else name,
        tuple(_text(p, f"{_join(path, 'place')}[{i}]") for i, p in enumerate(places)),
        capture,
    )


def _bins(data: dict[str, Any]) -> list[BinSpec]:
    """`bin:` (one bin, named 'bin' unless it says) or `bins:` (a list of named bins), never both; names unique and
    not 'bin' twice, and no two bins' floors and walls overlapping."""
    if "bin" in data and "bins" in data:
        raise _err("bins", "give `bin:` (one bin) or `bins:` (a list of named bins), not both")
    if "bin" in data:
        return [_bin(data["bin"], "bin", "bin")]
    if "bins" not in data:
        return []
    raw = data["bins"]
    if not isinstance(raw, list) or not 1 <= len(raw) <= MAX_BINS:
        raise _err(
            "bins", f"expected a list of 1 to {MAX_BINS} bins {{name, pose, inner_size, ...}}, got {short_repr(raw)}"
        )
    bins = []
    for i, v in enumerate(raw):
        if isinstance(v, dict) and "name" not in v:
            raise _err(f"bins[{i}].name", "required key is missing: every bin of a list has a name")
        bins.append(_bin(v, f"bins[{i}]", ""))
    names = [b.name for b in bins]
    if len(set(names)) != len(names):
        raise _err("bins", f"bin names must be unique, got {names}")
    for i, a in enumerate(bins):
        lo_a, hi_a = a.outer_bounds()
        for j in range(i):
            lo_b, hi_b = bins[j].outer_bounds()
            depth = np.minimum(hi_a, hi_b) - np.maximum(lo_a, lo_b)
            if np.all(depth > 1e-6):
                raise _err(
                    f"bins[{i}]",
                    f"bin {a.name!r} overlaps bin {bins[j].name!r} by {np.round(depth, 3).tolist()} m: move one",
                )
    return bins


def _check_bin_links(bins: list[BinSpec], places: list[PlaceSpec], wrist: WristCamera | None, key: str) -> None:
    """Each bin's `place:` names entries of `place:`; its `capture:` is a capture pose of a wrist camera."""
    entries = list(dict.fromkeys(p.entry for p in places))
    for i, b in enumerate(bins):
        path = key if key == "bin" else f"bins[{i}]"
        for k, name in enumerate(b.places):
            if name not in entries:
                close = get_close_matches(name, entries, n=1, cutoff=0.75)
                hint = f"did you mean {close[0]!r}? " if close else ""
                raise _err(f"{path}.place[{k}]", f"no place named {name!r}; {hint}places: {', '.join(entries)}")
        if b.capture is not None:
            if wrist is None:
                raise _err(f"{path}.capture", "a capture pose needs a wrist camera (camera: {mount: wrist, ...})")
            if b.capture >= len(wrist.capture_q):
                raise _err(
                    f"{path}.capture", f"is {b.capture}, but camera.capture holds {len(wrist.capture_q)} pose(s)"
                )


def _camera_floor(floor_z: float | None, boxes: Iterable[BoxSpec], bins: Iterable[BinSpec]) -> float | None:
    supports = [float(b.world_from_box[2, 3] + b.size[2] / 2) for b in boxes if b.name in ("table", "conveyor")]
    supports.extend(float(b.world_from_bin[2, 3]) for b in bins)
    levels = ([] if floor_z is None else [floor_z]) + ([min(supports)] if supports else [])
    return max(levels) if levels else None


def _watch(v: Any, base_dir: str | Path) -> WatchSpec:
    d = _mapping(v, "watch", _WATCH_KEYS)
    raw = d.get("zones", [])
    if not isinstance(raw, list):
        raise _err("watch.zones", f"expected a list of boxes {{name, min, max}}, got {short_repr(raw)}")
    zones = []
    for i, z in enumerate(raw):
        zd = _mapping(z, f"watch.zones[{i}]", _ZONE_KEYS)
        lo = _lengths(_req(zd, "min", f"watch.zones[{i}]"), f"watch.zones[{i}].min", 3)
        hi = _lengths(_req(zd, "max", f"watch.zones[{i}]"), f"watch.zones[{i}].max", 3)
        if np.any(hi <= lo):
            raise _err(f"watch.zones[{i}]", f"max {hi.tolist()} must exceed min {lo.tolist()} on every axis")
        name = _text(zd["name"], f"watch.zones[{i}].name") if "name" in zd else f"zone_{i}"
        zones.append(ZoneSpec(name, lo, hi))
    if len({z.name for z in zones}) != len(zones):
        raise _err("watch.zones", f"zone names must be unique, got {[z.name for z in zones]}")
    arm_margin = _length(d.get("arm_margin_m", 0.0), "watch.arm_margin_m", 0.0, 2.0)
    if not zones and arm_margin == 0.0:
        raise _err("watch", "nothing to watch: give zones or an arm_margin_m above 0")
    stop = d.get("stop", "stop")
    if stop not in WATCH_STOP_KINDS:
        raise _err("watch.stop", f"expected one of {', '.join(WATCH_STOP_KINDS)}, got {short_repr(stop)}")
    ack = d.get("require_ack", False)
    if not isinstance(ack, bool):
        raise _err("watch.require_ack", f"expected true or false, got {short_repr(ack)}")
    blob = _num(d.get("min_blob_px", 12), "watch.min_blob_px", 1, 10_000, "px")
    down = _num(d.get("downsample", 2), "watch.downsample", 1, 8)
    for key, value in (("min_blob_px", blob), ("downsample", down)):
        if value != int(value):
            raise _err(f"watch.{key}", f"expected a whole number, got {value:g}")
    reference = None
    if "static_reference" in d:
        reference = (Path(base_dir) / _text(d["static_reference"], "watch.static_reference", 4096)).resolve()
    drift = _mapping(d.get("drift", {}), "watch.drift", _DRIFT_KEYS)
    return WatchSpec(
        zones=tuple(zones),
        margin_m=_length(d.get("margin_m", 0.0), "watch.margin_m", 0.0, 1.0),
        arm_margin_m=arm_margin,
        stop=str(stop),
        require_ack=ack,
        k_sigma=_num(d.get("k_sigma", 5.0), "watch.k_sigma", 2.0, 50.0),
        min_blob_px=int(blob),
        approach_m=_length(d.get("approach_m", 0.13), "watch.approach_m", 0.0, 1.0),
        silhouette_pad_m=_length(d.get("silhouette_pad_m", 0.06), "watch.silhouette_pad_m", 0.0, 0.5),
        latency_s=_num(d.get("latency_s", 0.1), "watch.latency_s", 0.0, 1.0, "s"),
        held_radius_m=_length(d.get("held_radius_m", 0.0), "watch.held_radius_m", 0.0, 1.0),
        downsample=int(down),
        static_reference=reference,
        drift_max_translation_mm=_num(
            drift.get("max_translation_mm", 1.0), "watch.drift.max_translation_mm", 0.01, 100.0, "mm"
        ),
        drift_max_rotation_deg=_num(
            drift.get("max_rotation_deg", 0.1), "watch.drift.max_rotation_deg", 0.001, 10.0, "deg"
        ),
        drift_max_shift_px=_num(drift.get("max_shift_px", 0.35), "watch.drift.max_shift_px", 0.01, 50.0, "px"),
    )


def _wrist_camera(
    v: Any,
    base_dir: str | Path,
    model: str,
    world_from_base: FloatArray,
    flange_from_tcp: FloatArray,
    motion: MotionLimits,
    floor: float | None,
) -> WristCamera:
    """`camera: {mount: wrist, flange_from_camera, capture, body_size_m, camera_from_body, cable_clearance_m}`.

    flange_from_camera: the camera JSON `calibrate hand-eye --mode eye-in-hand` wrote (a path, relative to the cell
    file) or a pose. capture: a list of joint positions (rad), each within the joint limits, with its TCP inside
    motion.workspace and its camera above the lowest surface parts rest on (`floor`, m); the caller checks that
    the arm and the tool with the housing are clear of the static boxes there (`WristCamera.capture_contacts`)."""
    d = _mapping(v, "camera", _WRIST_CAMERA_KEYS)
    raw = _req(d, "flange_from_camera", "camera")
    source = None
    if isinstance(raw, str):
        source = (Path(base_dir) / _text(raw, "camera.flange_from_camera", 4096)).resolve()
        try:
            flange_from_camera = read_flange_from_camera(source)
        except InputError as exc:
            raise _err("camera.flange_from_camera", str(exc)) from exc
    else:
        flange_from_camera = parse_pose(raw, "camera.flange_from_camera")
    reach = float(np.linalg.norm(flange_from_camera[:3, 3]))
    if reach > 0.5:
        raise _err("camera.flange_from_camera", f"puts the camera {reach:.3g} m from the flange (more than 0.5 m)")
    captures = _req(d, "capture", "camera")
    if not isinstance(captures, list) or not captures or len(captures) > MAX_CAPTURE_POSES:
        raise _err("camera.capture", f"expected a list of 1 to {MAX_CAPTURE_POSES} joint positions (6 numbers, rad)")
    size = _lengths(d.get("body_size_m", list(D435_BODY_M)), "camera.body_size_m", 3, positive=True)
    if np.any(size > 0.5):
        raise _err("camera.body_size_m", f"{size.tolist()} m: a camera housing is at most 0.5 m on a side")
    default_body = {"xyz": [0.0, 0.0, -float(size[2]) / 2.0]}  # the housing behind its optical centre
    wrist = WristCamera(
        flange_from_camera=flange_from_camera,
        capture_q=np.stack([_vec(q, f"camera.capture[{i}]", 6, unit="rad") for i, q in enumerate(captures)]),
        body_size_m=size,
        camera_from_body=parse_pose(d.get("camera_from_body", default_body), "camera.camera_from_body"),
        cable_clearance_m=_length(d.get("cable_clearance_m", 0.02), "camera.cable_clearance_m", 0.0, 0.2),
        source=source,
    )
    lim = np.minimum(np.asarray(UR_PARAMS[model].position_limit), 2 * np.pi)
    for i, q in enumerate(wrist.capture_q):
        where = f"camera.capture[{i}]"
        if np.any(np.abs(q) > lim):
            raise _err(where, f"{q.tolist()} is outside the joint limits +-{lim.tolist()} rad")
        world_from_camera = wrist.world_from_camera(world_from_base, model, q)
        tcp = (world_from_camera @ np.linalg.inv(flange_from_camera) @ flange_from_tcp)[:3, 3]
        if np.any(tcp < motion.workspace_min) or np.any(tcp > motion.workspace_max):
            raise _err(where, f"the TCP at {np.round(tcp, 3).tolist()} m is outside motion.workspace")
        try:
            check_world_from_camera(world_from_camera, where, floor_z_m=floor)
        except InputError as exc:
            raise CellConfigError(str(exc)) from exc
    return wrist


def cell_from_dict(data: Any, base_dir: str | Path = ".", source: Path | None = None) -> CellConfig:
    """Validate a parsed cell mapping; see docs/cells.md for the schema. Every key at every level is checked
    (unknown keys are errors naming their full path), every number for type, finiteness and range."""
    if not isinstance(data, dict):
        raise CellConfigError(f"a cell file must hold a mapping at the top level, got {type(data).__name__}")
    _mapping(data, "", _TOP_KEYS)
    robot = _mapping(_req(data, "robot", ""), "robot", _ROBOT_KEYS)
    model = _text(_req(robot, "model", "robot"), "robot.model").lower()
    if model not in UR_PARAMS:
        raise _err("robot.model", f"unknown robot {model!r}; known: {', '.join(UR_PARAMS)}")
    serial = robot.get("serial_number")
    if serial is not None:
        if isinstance(serial, bool) or not isinstance(serial, str | int):
            raise _err("robot.serial_number", f"expected text, got {type(serial).__name__} {short_repr(serial)}")
        serial = _text(str(serial), "robot.serial_number")
    floor_z = None if "floor_z" not in data else _length(data["floor_z"], "floor_z")
    world_from_base = parse_pose(robot.get("world_from_base", {"xyz": [0, 0, 0]}), "robot.world_from_base")
    if floor_z is not None and world_from_base[2, 3] < floor_z:
        raise _err("robot.world_from_base", f"the base at z = {world_from_base[2, 3]:g} m is under floor_z {floor_z:g}")
    params = UR_PARAMS[model]
    home = _vec(robot.get("home", [0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0]), "robot.home", 6, unit="rad")
    lim = np.minimum(np.asarray(params.position_limit), 2 * np.pi)
    if np.any(np.abs(home) > lim):
        raise _err("robot.home", f"home {home.tolist()} is outside the joint limits +-{lim.tolist()} rad")
    tools, drivers = _tools(_req(data, "gripper", ""), model)
    tool = tools[0]

    boxes: list[BoxSpec] = []
    if "table" in data:
        boxes.append(_box(data["table"], "table", "table"))
    bins = _bins(data)
    for bin_spec in bins:
        boxes.extend(bin_spec.boxes())
    if "conveyor" in data:
        boxes.append(_box(data["conveyor"], "conveyor", "conveyor"))
    fixtures = data.get("fixtures", [])
    if not isinstance(fixtures, list):
        raise _err("fixtures", f"expected a list, got {short_repr(fixtures)}")
    for i, f in enumerate(fixtures):
        boxes.append(_box(f, f"fixtures[{i}]", f"fixture_{i}", _FIXTURE_KEYS))
    names = [b.name for b in boxes]
    if len(set(names)) != len(names):
        raise _err("fixtures", f"box names must be unique, got {names}")

    limits = _motion(data.get("motion", {}), model)
    world_from_camera = None
    wrist = None
    mount = data["camera"].get("mount", "fixed") if isinstance(data.get("camera"), dict) else "fixed"
    if mount not in CAMERA_MOUNTS:
        raise _err("camera.mount", f"expected one of {', '.join(CAMERA_MOUNTS)}, got {short_repr(mount)}")
    if mount == "wrist":
        if len(tools) > 1:
            raise _err("gripper", "a wrist camera with two tools on the flange is not supported: give one gripper")
        floor = _camera_floor(floor_z, boxes, bins)
        wrist = _wrist_camera(data["camera"], base_dir, model, world_from_base, tool.flange_from_tcp, limits, floor)
        tool = wrist.mounted_on(tool)
        statics = [(b.name, b.world_from_box, b.size) for b in boxes]
        for i, contact in enumerate(wrist.capture_contacts(model, world_from_base, tool, statics)):
            if contact:
                raise _err(f"camera.capture[{i}]", f"at this pose {contact}: teach a capture pose clear of the cell")
        if "watch" in data:
            raise _err("watch", "the zone watch and drift check need a fixed camera; this cell's is on the wrist")
    elif "camera" in data:
        camera = _mapping(data["camera"], "camera", _CAMERA_KEYS)
        from_scene = camera.get("from_scene", False)
        if not isinstance(from_scene, bool):
            raise _err("camera.from_scene", f"expected true or false, got {short_repr(from_scene)}")
        if "world_from_camera" in camera and from_scene:
            raise _err("camera", "give world_from_camera or from_scene: true, not both")
        if "world_from_camera" in camera:
            pose = parse_pose(camera["world_from_camera"], "camera.world_from_camera")
            try:
                world_from_camera = check_world_from_camera(
                    pose, "camera.world_from_camera", floor_z_m=_camera_floor(floor_z, boxes, bins)
                )
                _check_outside_workspace(world_from_camera, limits, "camera.world_from_camera")
            except InputError as exc:
                raise CellConfigError(str(exc)) from exc
        elif not from_scene:
            raise _err("camera", "give world_from_camera or from_scene: true")

    places_raw = _req(data, "place", "")
    if not isinstance(places_raw, list) or not places_raw:
        raise _err("place", "expected a non-empty list of place poses")
    places = []
    for i, p in enumerate(places_raw):
        pd = _mapping(p, f"place[{i}]", _PLACE_KEYS)
        pose = parse_pose(_req(pd, "world_from_tcp", f"place[{i}]"), f"place[{i}].world_from_tcp")
        if floor_z is not None and pose[2, 3] < floor_z:
            raise _err(f"place[{i}].world_from_tcp", f"z = {pose[2, 3]:g} m is under floor_z {floor_z:g} m")
        place_name = _text(pd["name"], f"place[{i}].name") if "name" in pd else f"place_{i}"
        approach = _length(pd.get("approach_m", 0.1), f"place[{i}].approach_m", 0.0, 1.0)
        align = pd.get("align_part", False)
        if not isinstance(align, bool):
            raise _err(f"place[{i}].align_part", f"expected true or false, got {short_repr(align)}")
        slots = (
            pattern_slots(pd["pattern"], f"place[{i}].pattern", pose, place_name)
            if "pattern" in pd
            else [(place_name, pose)]
        )
        for slot_name, slot_pose in slots:
            _check_outside_bounds(slot_pose, limits, f"place[{i}].pattern" if "pattern" in pd else f"place[{i}]")
            group = place_name if "pattern" in pd else ""
            places.append(PlaceSpec(slot_name, slot_pose, approach, align, "pattern" in pd, group))
    if len({p.name for p in places}) != len(places):
        raise _err("place", f"place names must be unique, got {[p.name for p in places]}")
    _check_bin_links(bins, places, wrist, "bins" if "bins" in data else "bin")

    templates_path = None
    if "templates" in data:
        templates_path = (Path(base_dir) / _text(data["templates"], "templates", 4096)).resolve()

    planning = _mapping(data.get("planning", {}), "planning", _PLANNING_KEYS)
    return CellConfig(
        name=_text(data["name"], "name") if "name" in data else (source.stem if source else "cell"),
        robot_model=model,
        world_from_base=world_from_base,
        home_q=home,
        tool=tool,
        world_from_camera=world_from_camera,
        static_boxes=tuple(boxes),
        bin=bins[0] if bins else None,
        places=tuple(places),
        templates_path=templates_path,
        motion=limits,
        entry_clearance_m=_length(planning.get("entry_clearance_m", 0.05), "planning.entry_clearance_m", 0.0, 1.0),
        lift_m=_length(planning.get("lift_m", 0.08), "planning.lift_m", 0.0, 1.0),
        voxel_m=_length(planning.get("voxel_m", 0.01), "planning.voxel_m", 1e-3, 0.2),
        source=source,
        robot_serial=serial,
        floor_z=floor_z,
        gripper_driver=drivers[0],
        watch=_watch(data["watch"], base_dir) if "watch" in data else None,
        wrist_camera=wrist,
        bins=tuple(bins),
        tools=(tool, *tools[1:]),
        gripper_drivers=drivers,
    )


MAX_TOOLS = 2  # tools on one flange (`gripper:` as a list)


def _tools(v: Any, robot: str) -> tuple[list[ToolModel], tuple[GripperDriverSpec | None, ...]]:
    """The cell's tools and their drivers: `gripper:` as one mapping, or a list of 1-2 mappings (a dual-tool
    flange: each tool's shapes then include the other's body, `with_idle`, drawn back by its `retract_m` along its
    approach axis when it sits on a slide: a suction cup that extends past the jaws only when it is used)."""
    if isinstance(v, dict):
        tool = _tool(v, "gripper", robot)
        driver = (
            parse_gripper_driver(v["driver"], "gripper.driver", tool.kind, tool.stroke_m) if "driver" in v else None
        )
        return [tool], (driver,)
    if not isinstance(v, list) or not 1 <= len(v) <= MAX_TOOLS:
        raise _err(
            "gripper",
            f"expected a mapping or a list of 1-{MAX_TOOLS} mappings (tools on one flange), got {short_repr(v)}",
        )
    tools: list[ToolModel] = []
    drivers: list[GripperDriverSpec | None] = []
    retracts: list[float] = []
    for i, entry in enumerate(v):
        path = f"gripper[{i}]"
        if isinstance(entry, dict) and "retract_m" in entry:
            if len(v) < 2:
                raise _err(f"{path}.retract_m", "a tool is drawn back only beside another tool on the flange")
            retracts.append(_length(entry["retract_m"], f"{path}.retract_m", 0.0, 0.5))
            entry = {k: x for k, x in entry.items() if k != "retract_m"}
        else:
            retracts.append(0.0)
        tool = _tool(entry, path, robot)
        if any(t.name == tool.name for t in tools):
            raise _err(
                f"{path}.model", f"tool {tool.name!r} is given twice; each tool on the flange needs its own model name"
            )
        tools.append(tool)
        drivers.append(
            parse_gripper_driver(entry["driver"], f"{path}.driver", tool.kind, tool.stroke_m)
            if "driver" in entry
            else None
        )
    if len(tools) > 1:
        tools = [with_idle(tools[0], tools[1], retracts[1]), with_idle(tools[1], tools[0], retracts[0])]
    return tools, tuple(drivers)
