"""Teach a new part from CAD: check and repair the mesh, find its symmetries and resting poses, synthesize and
validate grasps in MuJoCo, store the fit's preparation, and write a template folder with a report (HTML).

Steps of `teach_part` (all lengths in metres once loaded):
1. `check_cad`: read the mesh (STL/OBJ/PLY/...) or template folder, check the declared units against the size (a
   millimetre file declared as metres, or a part outside 5 mm .. 1 m, is refused with one line), repair it
   (templates.mesh_check: degenerate / duplicate faces, winding, normals, small holes) and refuse what stays open.
   A bare mesh is moved so its centre of mass is the origin (BOP models are centred; the axes are kept).
2. Symmetry (templates.symmetry.detect_symmetry): discrete and continuous, BOP convention.
3. Resting poses, quasi-static on the convex hull: gravity directions drawn uniformly on the sphere; for each the
   part lands on the hull face the ray from its centre of mass meets and topples face to face (across the edge the
   centre's projection lies beyond) until the projection lies inside a face's plane polygon. A pose's probability
   is the share of directions that end in it (poses equivalent under the symmetry are merged). Each pose is then
   dropped in MuJoCo from 1 mm with the convex decomposition the simulator uses (sim.physics.collision_pieces):
   the decomposition must compile and the part must stay (drift and tilt are reported).
4. Grasps: the template's annotated grasps, else grasp.synthesis by the shape class found from the geometry.
   Per resting pose (likeliest first) the top-down grasps (approach within 35 degrees of straight down) are
   replayed in MuJoCo (sim.physics.validate_grasp: approach, close, lift, transfer, hold) in three trials: nominal,
   with a 2 mm / 4 degree placement error, and with a fast transfer (a shake: twice the acceleration). A grasp's
   success rate is held / trials over every pose it was tried in; grasps below `min_success` are dropped, tried
   ones rank by their rate (priority), untried ones (side grasps) are kept with their synthesis quality. The
   validation stops at the wall-time budget (the first grasp is always tried); grasps not reached are kept
   untried and the report says so.
5. The template is written (template.yaml + mesh in mm + obj_id + a `teach:` record of all of the above), read
   back, and its fit preparation stored in its `.prepared/` folder (templates.prepared), so the first fit of a
   process pays no preparation; report.html shows the resting poses and the tried grasps with their rates.
6. With `segmenter_budget_s` > 0 (`extend_segmenter`, once for all parts): the bundled segmentation model is taught
   the library's parts by a head refit on its frozen trunk (training.head_tune, within the budget) and stored as
   OUT/segmenter/normpos_seg.onnx + MODEL_CARD.md, which every command given `--library OUT` uses.

`teach` runs every part (and step 6) in a staging folder inside OUT and moves each finished part folder (and the
model) into OUT only when every part succeeded: bad CAD, a bad budget or a failed step 6 leave OUT as it was.
"""

from __future__ import annotations

import base64
import html
import logging
import os
import re
import shutil
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from normpos_grasp.atomic import atomic_write_text
from normpos_grasp.errors import InputError, MeshError, TemplateError
from normpos_grasp.geometry.transforms import look_at, make_pose, rotation_from_quaternion
from normpos_grasp.perception.factory import LIBRARY_SEGMENTER_DIR
from normpos_grasp.records.template import GraspAnnotation, Template
from normpos_grasp.templates.library import (
    MESH_SUFFIXES,
    TEMPLATE_FILE,
    UNITS,
    load_library,
    load_template,
    save_template,
)
from normpos_grasp.templates.mesh_check import MeshReport, check_mesh
from normpos_grasp.templates.symmetry import SymmetryReport, detect_symmetry
from normpos_grasp.typing import FloatArray

logger = logging.getLogger(__name__)

#: sizes teach accepts (largest extent), metres: smaller or larger parts are a unit mix-up or not for this cell
MIN_PART_M = 0.005
MAX_PART_M = 1.0
#: obj_ids of taught parts start above this (the built-in parts are 1..8, BOP datasets use small ids)
FIRST_OBJ_ID = 101
REPORT_FILE = "report.html"
DENSITY = {"pom": 1410.0, "aluminium": 2700.0, "abs": 1050.0, "steel": 7850.0}

ProgressFn = Callable[[str], None]


@dataclass(frozen=True)
class TeachOptions:
    """Settings of `teach`. Seconds, metres.

    units: units of bare mesh files ('mm' or 'm'; template folders declare their own). budget_s: wall-time budget
    of one part (the grasp validation stops when it is spent). gripper: physics gripper preset or packaged name.
    material: density for the mass of bare meshes (sim.parts.DENSITIES keys). rest_samples: gravity directions of
    the resting-pose estimate. max_poses: resting poses whose grasps are validated (likeliest first).
    grasps_per_pose: grasps tried per resting pose. trials: trials per grasp and pose (1 nominal, 2 displaced,
    3 shaken). min_success: grasps tried with a lower success rate are dropped. max_grasps: most grasps stored
    (every tried and kept one, then untried ones by synthesis quality). seed: every random draw.
    report: write report.html. segmenter_budget_s: wall-time budget of step 6, extending the library's segmenter
    with the new parts (0: skip); segmenter_cell: the cell whose bins it is taught on (packaged name or YAML).
    """

    units: str = "mm"
    budget_s: float = 240.0
    gripper: str = "2f85"
    material: str = "pom"
    rest_samples: int = 2000
    max_poses: int = 4
    grasps_per_pose: int = 5
    trials: int = 3
    min_success: float = 0.5
    max_grasps: int = 300
    seed: int = 0
    report: bool = True
    segmenter_budget_s: float = 0.0
    segmenter_cell: str = "ur5e_bin_parallel"

    def __post_init__(self) -> None:
        if self.units not in UNITS:
            raise InputError(f"units must be one of {sorted(UNITS)}, got {self.units!r}")
        if not self.budget_s > 0:
            raise InputError(f"the budget must be positive, got {self.budget_s} s")
        if self.material not in DENSITY:
            raise InputError(f"material must be one of {sorted(DENSITY)}, got {self.material!r}")
        if not 1 <= self.trials <= 3:
            raise InputError(f"trials must be 1..3, got {self.trials}")
        if not 0.0 <= self.segmenter_budget_s <= 7200.0:  # also refuses NaN
            raise InputError(f"the segmenter budget must lie in 0..7200 s, got {self.segmenter_budget_s} s")


@dataclass(frozen=True, eq=False)
class RestingPose:
    """A stable resting pose: down (3,) the object-frame direction of gravity (the contact face's outward normal),
    probability (share of drops that end here, symmetric equivalents merged), world_from_object (4, 4) on a floor
    at z = 0, and what the MuJoCo drop measured: drift_m (centre-of-mass motion) and tilt_rad."""

    down: FloatArray
    probability: float
    world_from_object: FloatArray
    drift_m: float = float("nan")
    tilt_rad: float = float("nan")

    @property
    def stable_in_physics(self) -> bool:
        return bool(self.drift_m < 0.005 and self.tilt_rad < 0.1)


@dataclass(frozen=True)
class GraspTrial:
    """One grasp tried in one resting pose: outcomes of its trials (sim.physics.OUTCOMES)."""

    grasp_id: str
    pose_index: int
    outcomes: tuple[str, ...]

    @property
    def held(self) -> int:
        return sum(o == "held" for o in self.outcomes)


@dataclass(frozen=True, eq=False)
class TaughtPart:
    """What `teach_part` made: the final template, its checks and measurements, timings (s per step), and the
    folder it was written to."""

    template: Template
    mesh_report: MeshReport
    symmetry: SymmetryReport
    resting: tuple[RestingPose, ...]
    trials: tuple[GraspTrial, ...]
    success: dict[str, float]
    dropped: tuple[str, ...]
    untried: int
    timings: dict[str, float]
    folder: Path
    budget_spent: bool = False
    notes: tuple[str, ...] = field(default_factory=tuple)
    candidates: dict[str, GraspAnnotation] = field(default_factory=dict)


# -- 1. CAD in -------------------------------------------------------------------------------------------------
def part_name(path: Path) -> str:
    """A template name from a file or folder name: lower case letters, digits and underscores."""
    stem = path.name if path.is_dir() else path.stem
    name = re.sub(r"[^a-z0-9_]+", "_", stem.lower()).strip("_")
    if not name:
        raise InputError(f"{path}: cannot make a part name from {stem!r}; rename the file")
    return name


def _check_size(raw_extent: float, units: str, where: str) -> None:
    """Refuse a size that does not match the declared units (one line saying what to pass)."""
    size_m = raw_extent * UNITS[units]
    if units == "m" and raw_extent > 2.0:
        raise MeshError(
            f"{where}: the mesh is {raw_extent:.4g} units across, declared in metres that is a {size_m:.4g} m part; "
            "is the file in millimetres? pass --units mm"
        )
    if units == "mm" and raw_extent < 2.0:
        raise MeshError(
            f"{where}: the mesh is {raw_extent:.4g} units across, declared in millimetres that is {size_m * 1e3:.4g} "
            "mm; is the file in metres? pass --units m"
        )
    if size_m > MAX_PART_M:
        raise MeshError(
            f"{where}: the part is {size_m:.4g} m across; teach takes parts of {MIN_PART_M * 1e3:.0f} mm to "
            f"{MAX_PART_M:.0f} m (check the units: --units mm|m)"
        )
    if size_m < MIN_PART_M:
        raise MeshError(
            f"{where}: the part is {size_m * 1e3:.3g} mm across; teach takes parts of {MIN_PART_M * 1e3:.0f} mm "
            f"to {MAX_PART_M:.0f} m (check the units: --units mm|m)"
        )


def check_cad(source: str | Path, options: TeachOptions | None = None) -> Template:
    """Read and check one mesh file or template folder; a repaired, closed template in metres (step 1).

    Raises:
        MeshError: unreadable or empty file, a size that contradicts the units, a mesh that stays open.
        TemplateError / InputError: a bad template.yaml, an unknown file type.
    """
    from normpos_grasp.templates.library import _load_mesh

    opts = options or TeachOptions()
    path = Path(source)
    if not path.exists():
        raise InputError(f"{path} does not exist")
    if path.is_dir() or path.name == TEMPLATE_FILE:
        folder = path if path.is_dir() else path.parent
        if not (folder / TEMPLATE_FILE).is_file():
            raise InputError(f"{folder} is a folder without {TEMPLATE_FILE}; give a mesh file or a template folder")
        template = load_template(folder)
        _check_size(float(np.max(template.mesh.extents)) / UNITS[template.units], template.units, str(folder))
        if not template.mesh.is_watertight:
            raise MeshError(f"{folder}: the mesh is open (not watertight) after repair; close it in CAD")
        return template
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise InputError(f"{path}: expected a mesh file ({', '.join(MESH_SUFFIXES)}) or a template folder")
    if path.stat().st_size == 0:
        raise MeshError(f"{path}: the file is empty")
    raw = _load_mesh(path, str(path))
    _check_size(float(np.max(raw.extents)), opts.units, str(path))
    raw.apply_scale(UNITS[opts.units])
    name = part_name(path)
    mesh, report = check_mesh(raw, name, repair=True)
    if not mesh.is_watertight or float(mesh.volume) <= 0:
        raise MeshError(
            f"{path}: the mesh is open (not watertight) even after filling small holes; close it in CAD and export "
            "a solid"
        )
    mesh.apply_translation(-np.asarray(mesh.center_mass, dtype=np.float64))
    return Template(
        name=name,
        label=name,
        mesh=mesh,
        shape=classify_shape(mesh),
        mass_kg=float(mesh.volume * DENSITY[opts.material]),
        material=opts.material,
        source=str(path),
        units=opts.units,
        report=report,
    )


def classify_shape(mesh: Any, symmetry: SymmetryReport | None = None) -> str:
    """The grasp-synthesis shape class of a closed mesh (records.template.SHAPE_CLASSES) from its geometry:
    'sphere' (every rotation a symmetry), 'cylinder' / 'ring' (one continuous axis, solid / with a through hole),
    'box' / 'plate' (fills its oriented box; 'plate' when the thinnest side is under a quarter of the next),
    else 'irregular' (antipodal grasps)."""
    cont = [a for a, n in symmetry.axes if n == 0] if symmetry is not None else []
    if len(cont) >= 2:
        return "sphere"
    if cont:
        return "ring" if int(mesh.euler_number) == 0 else "cylinder"
    obb = mesh.bounding_box_oriented
    ext = np.sort(np.asarray(obb.primitive.extents, dtype=np.float64))
    if float(mesh.volume) > 0.97 * float(np.prod(ext)):
        return "plate" if ext[0] < 0.25 * ext[1] else "box"
    return "irregular"


# -- 3. resting poses ------------------------------------------------------------------------------------------
def resting_poses(template: Template, samples: int = 2000, seed: int = 0) -> list[RestingPose]:
    """Quasi-static resting poses of `template` on a plane with their probabilities (see the module docstring)."""
    from scipy.spatial import Delaunay, QhullError

    mesh = template.mesh
    hull = mesh.convex_hull
    c = np.asarray(mesh.center_mass, dtype=np.float64)
    verts = np.asarray(hull.vertices, dtype=np.float64)
    faces = np.asarray(hull.faces, dtype=np.int64)
    normals = np.asarray(hull.face_normals, dtype=np.float64)
    offsets = np.einsum("ij,ij->i", verts[faces[:, 0]] - c, normals)  # distance of each face plane from c
    adjacency = np.full((len(faces), 3), -1, dtype=np.int64)  # neighbour across the edge opposite vertex k
    for (fa, fb), edge in zip(hull.face_adjacency, hull.face_adjacency_edges, strict=True):
        for f, g in ((fa, fb), (fb, fa)):
            k = [i for i in range(3) if faces[f, i] not in edge][0]
            adjacency[f, k] = g
    diameter = float(np.linalg.norm(mesh.extents))
    plane_cache: dict[int, bool] = {}

    def plane_key(f: int) -> int:
        same = np.where((normals @ normals[f] > 1 - 1e-6) & (np.abs(offsets - offsets[f]) < 1e-6 * diameter))[0]
        return int(same.min())

    def stable(f: int) -> bool:
        key = plane_key(f)
        if key not in plane_cache:
            n = normals[f]
            on = np.abs((verts - c) @ n - offsets[f]) < 1e-6 * diameter
            p = c + n * offsets[f]
            u = np.cross(n, [1.0, 0, 0] if abs(n[0]) < 0.9 else [0, 1.0, 0])
            u /= np.linalg.norm(u)
            w = np.cross(n, u)
            pts2 = np.column_stack([(verts[on] - p) @ u, (verts[on] - p) @ w])
            try:
                inside = bool(Delaunay(pts2).find_simplex(np.zeros((1, 2)))[0] >= 0)
            except (QhullError, ValueError):  # fewer than 3 points off a line: no support polygon
                inside = False
            plane_cache[key] = inside
        return plane_cache[key]

    rng = np.random.default_rng(seed)
    g = rng.normal(size=(samples, 3))
    g /= np.linalg.norm(g, axis=1, keepdims=True)
    dots = g @ normals.T
    t = np.where(dots > 1e-9, offsets[None, :] / np.maximum(dots, 1e-12), np.inf)
    start = np.argmin(t, axis=1)
    ends: dict[int, int] = {}
    memo: dict[int, int] = {}
    for f0 in start:
        f = int(f0)
        path = []
        for _ in range(4 * len(faces)):
            if f in memo:
                f = memo[f]
                break
            path.append(f)
            if stable(f):
                break
            n = normals[f]
            proj = c + n * offsets[f]  # the centre of mass projected on the face plane
            tri = verts[faces[f]]
            bary = _barycentric(proj, tri)
            f = int(adjacency[f, int(np.argmin(bary))])
            if f < 0:
                break
        for p in path:
            memo[p] = f
        key = plane_key(f)
        ends[key] = ends.get(key, 0) + 1
    transforms = template.symmetry.transforms(continuous_steps=72)[:, :3, :3]
    merged: list[tuple[FloatArray, int]] = []
    for key, count in sorted(ends.items(), key=lambda kv: -kv[1]):
        n = normals[key]
        for i, (m, k) in enumerate(merged):
            if np.max(transforms @ m @ n) > np.cos(np.deg2rad(4.0)):
                merged[i] = (m, k + count)
                break
        else:
            merged.append((n, count))
    merged.sort(key=lambda mk: -mk[1])
    out = []
    for n, count in merged:
        out.append(RestingPose(n.copy(), count / samples, _rest_pose(mesh, n)))
    return out


def _barycentric(p: FloatArray, tri: FloatArray) -> FloatArray:
    v0, v1 = tri[1] - tri[0], tri[2] - tri[0]
    v2 = p - tri[0]
    d00, d01, d11 = v0 @ v0, v0 @ v1, v1 @ v1
    d20, d21 = v2 @ v0, v2 @ v1
    den = d00 * d11 - d01 * d01
    if abs(den) < 1e-300:
        return np.array([1.0, 0.0, 0.0])
    b1 = (d11 * d20 - d01 * d21) / den
    b2 = (d00 * d21 - d01 * d20) / den
    return np.array([1.0 - b1 - b2, b1, b2])


def _rest_pose(mesh: Any, down: FloatArray) -> FloatArray:
    """world_from_object resting on z = 0 with object direction `down` along world -z, centre of mass over x=y=0."""
    d = down / np.linalg.norm(down)
    target = np.array([0.0, 0.0, -1.0])
    axis = np.cross(d, target)
    s, cth = float(np.linalg.norm(axis)), float(d @ target)
    if s < 1e-9:
        rot = np.eye(3) if cth > 0 else np.diag([1.0, -1.0, -1.0])
    else:
        from normpos_grasp.geometry.transforms import rotation_from_rotvec

        rot = rotation_from_rotvec(axis / s * np.arctan2(s, cth))
    v = np.asarray(mesh.vertices, dtype=np.float64) @ rot.T
    com = rot @ np.asarray(mesh.center_mass, dtype=np.float64)
    return make_pose(rot, [-com[0], -com[1], -float(v[:, 2].min())])


def drop_check(template: Template, world_from_object: FloatArray, seconds: float = 0.6) -> tuple[float, float]:
    """(drift_m, tilt_rad) of the part set 1 mm above a floor in MuJoCo at `world_from_object` and let go for
    `seconds`. The part collides as sim.physics.collision_pieces (what every simulation uses): MuJoCo must accept
    that decomposition. Raises SimulationError when it does not."""
    from normpos_grasp.errors import SimulationError
    from normpos_grasp.sim.physics import collision_pieces
    from normpos_grasp.sim.scene import import_mujoco

    mujoco = import_mujoco()
    pieces = collision_pieces(template)
    mesh = template.mesh
    assets, geoms = [], []
    for j, (kind, data) in enumerate(pieces):
        if kind == "box":
            geoms.append(f'<geom type="box" size="{_fmt(np.asarray(data) / 2.0)}" mass="0"/>')
        elif kind == "sphere":
            geoms.append(f'<geom type="sphere" size="{float(data[0]):.9g}" mass="0"/>')
        else:
            assets.append(f'<mesh name="m{j}" vertex="{_fmt(data)}" inertia="convex"/>')
            geoms.append(f'<geom type="mesh" mesh="m{j}" mass="0"/>')
    inertia = np.asarray(mesh.moment_inertia, dtype=np.float64) * (template.mass_kg / max(float(mesh.volume), 1e-12))
    eig = np.linalg.eigvalsh(inertia)
    inertia = inertia + np.eye(3) * max(0.0, float(eig.max()) * 1e-3 - float(eig.min()))
    full = _fmt([inertia[0, 0], inertia[1, 1], inertia[2, 2], inertia[0, 1], inertia[0, 2], inertia[1, 2]])
    pose = np.array(world_from_object, dtype=np.float64)
    pose[2, 3] += 0.001
    quat = _quat_wxyz(pose[:3, :3])
    xml = (
        '<mujoco><option timestep="0.002"/><asset>' + "".join(assets) + "</asset><worldbody>"
        '<geom type="plane" size="1 1 0.1" friction="0.5 0.005 0.0001"/>'
        f'<body pos="{_fmt(pose[:3, 3])}" quat="{_fmt(quat)}"><freejoint/>'
        f'<inertial pos="{_fmt(mesh.center_mass)}" mass="{template.mass_kg:.9g}" fullinertia="{full}"/>'
        + "".join(geoms)
        + "</body></worldbody></mujoco>"
    )
    try:
        model = mujoco.MjModel.from_xml_string(xml)
    except ValueError as exc:
        raise SimulationError(f"MuJoCo rejected the convex decomposition of '{template.name}': {exc}") from exc
    data = mujoco.MjData(model)
    for _ in range(int(seconds / model.opt.timestep)):
        mujoco.mj_step(model, data)
    if not np.all(np.isfinite(data.qpos)):
        raise SimulationError(f"the MuJoCo drop of '{template.name}' diverged")
    qw, qx, qy, qz = (float(v) for v in data.qpos[3:7])
    final = make_pose(rotation_from_quaternion([qx, qy, qz, qw]), np.asarray(data.qpos[:3]))
    rest = np.asarray(world_from_object, dtype=np.float64)  # where it should lie, on the floor
    com0 = rest[:3, :3] @ np.asarray(mesh.center_mass) + rest[:3, 3]
    com1 = final[:3, :3] @ np.asarray(mesh.center_mass) + final[:3, 3]
    rel = pose[:3, :3].T @ final[:3, :3]
    tilt = float(np.arccos(np.clip((np.trace(rel) - 1) / 2, -1, 1)))
    return float(np.linalg.norm(com1 - com0)), tilt


def _fmt(values: Any) -> str:
    return " ".join(f"{float(v):.9g}" for v in np.asarray(values, dtype=np.float64).reshape(-1))


def _quat_wxyz(rot: FloatArray) -> FloatArray:
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(np.asarray(rot, dtype=np.float64)).as_quat()
    return np.array([w, x, y, z])


# -- 4. grasps ---------------------------------------------------------------------------------------------------
def candidate_grasps(template: Template, finger_tip_m: float) -> list[GraspAnnotation]:
    """The template's annotated parallel grasps, else those grasp.synthesis makes for its shape class."""
    from normpos_grasp.grasp.synthesis import SynthesisOptions, synthesize

    annotated = [g for g in template.grasps if g.scheme == "parallel"]
    if annotated:
        return annotated
    return synthesize(template, ("parallel",), SynthesisOptions(finger_tip_m=finger_tip_m))


def validate_grasps(
    template: Template,
    grasps: Sequence[GraspAnnotation],
    poses: Sequence[RestingPose],
    options: TeachOptions,
    deadline: float,
    progress: ProgressFn | None = None,
) -> tuple[list[GraspTrial], bool]:
    """Replay the top-down grasps of each resting pose in MuJoCo (step 4); (trials, whether the budget ran out)."""
    from normpos_grasp.errors import NormposError
    from normpos_grasp.sim.physics import PhysicsOptions, validate_grasp

    spec = gripper_spec(options.gripper)
    floor = (("floor", make_pose(translation=[0.0, 0.0, -0.01]), np.array([0.6, 0.6, 0.02])),)
    nominal = PhysicsOptions()
    shaken = replace(nominal, move_s=nominal.move_s / np.sqrt(2.0))  # twice the peak acceleration
    rng = np.random.default_rng(options.seed)
    out: list[GraspTrial] = []
    cos_down = np.cos(np.deg2rad(35.0))
    clear = [g for g in grasps if 0 < g.opening_m <= spec.stroke_m and jaws_clear(template, g, spec)]
    for p_idx, pose in enumerate(poses[: options.max_poses]):
        world = pose.world_from_object
        ranked = []
        for g in clear:
            w_tcp = world @ g.object_from_tcp
            if -w_tcp[2, 2] < cos_down:
                continue
            if _lowest_jaw_z(spec, w_tcp, g.opening_m) < 0.0:  # the jaws would dig into the floor
                continue
            ranked.append((g.priority, g.id, g, w_tcp))
        ranked.sort(key=lambda r: (-r[0], r[1]))
        for _, gid, g, w_tcp in ranked[: options.grasps_per_pose]:
            outcomes: list[str] = []
            for k in range(options.trials):
                if time.perf_counter() > deadline and out:  # the first grasp always gets all its trials
                    if outcomes:
                        out.append(GraspTrial(gid, p_idx, tuple(outcomes)))
                    return out, True
                tcp = w_tcp
                physics = nominal
                if k == 1:  # where perception puts the part 2 mm and 4 degrees off
                    shift = rng.normal(size=2)
                    shift = 0.002 * shift / np.linalg.norm(shift)
                    yaw = np.deg2rad(4.0) * (1 if rng.random() < 0.5 else -1)
                    c, s = np.cos(yaw), np.sin(yaw)
                    err = make_pose(np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]]), [shift[0], shift[1], 0.0])
                    tcp = err @ w_tcp
                elif k == 2:
                    physics = shaken
                try:
                    result = validate_grasp(template, world, (), floor, spec, tcp, g.opening_m, physics)
                    outcomes.append(result.outcome)
                except NormposError as exc:
                    logger.warning("grasp %s in pose %d: %s", gid, p_idx, exc)
                    outcomes.append("error")
            out.append(GraspTrial(gid, p_idx, tuple(outcomes)))
            if progress is not None:
                progress(f"pose {p_idx + 1}: grasp {gid} held {sum(o == 'held' for o in outcomes)}/{len(outcomes)}")
    return out, False


def jaws_clear(template: Template, grasp: GraspAnnotation, spec: Any, approach_m: float = 0.06) -> bool:
    """Whether the open jaws, swept along the approach over `approach_m`, stay clear of the part: no surface sample
    (every vertex and 3000 area-weighted samples) lies inside either finger's swept box shrunk by 0.5 mm. Grasps that
    fail would hit the part before closing."""
    pts = _surface_points(template)
    local = (pts - grasp.object_from_tcp[:3, 3]) @ grasp.object_from_tcp[:3, :3]  # in the TCP frame
    m = 0.0005
    cx = grasp.opening_m / 2.0 + spec.finger_thickness_m / 2.0
    in_y = np.abs(local[:, 1]) < spec.finger_width_m / 2.0 - m
    z_hi = spec.tip_beyond_tcp_m - m
    z_lo = spec.tip_beyond_tcp_m - spec.finger_length_m - approach_m
    in_z = (local[:, 2] < z_hi) & (local[:, 2] > z_lo)
    for side in (-1.0, 1.0):
        in_x = np.abs(local[:, 0] - side * cx) < spec.finger_thickness_m / 2.0 - m
        if np.any(in_x & in_y & in_z):
            return False
    return True


_SURFACE: dict[int, tuple[Any, FloatArray]] = {}


def _surface_points(template: Template) -> FloatArray:
    """(N, 3) vertices and 3000 seeded surface samples of the template's mesh (cached per mesh object)."""
    hit = _SURFACE.get(id(template.mesh))
    if hit is None or hit[0] is not template.mesh:
        from normpos_grasp.templates.symmetry import sample_surface

        samples = sample_surface(template.mesh, 3000, np.random.default_rng(0))
        hit = (template.mesh, np.vstack([samples, np.asarray(template.mesh.vertices, dtype=np.float64)]))
        _SURFACE.clear()
        _SURFACE[id(template.mesh)] = hit
    return hit[1]


def _lowest_jaw_z(spec: Any, world_from_tcp: FloatArray, opening_m: float) -> float:
    """World height of the lowest corner of the open jaws' tips at `world_from_tcp`, metres."""
    x = opening_m / 2.0 + spec.finger_thickness_m
    y = spec.finger_width_m / 2.0
    corners = np.array([[sx * x, sy * y, spec.tip_beyond_tcp_m, 1.0] for sx in (-1, 1) for sy in (-1, 1)])
    return float((corners @ world_from_tcp.T)[:, 2].min())


def gripper_spec(name: str) -> Any:
    """The physics GripperSpec of a preset ('2f85', '2f140') or a packaged gripper name."""
    from normpos_grasp.errors import NormposError
    from normpos_grasp.kinematics.gripper import Gripper
    from normpos_grasp.sim.physics import GripperSpec

    if name in ("2f85", "2f140"):
        return GripperSpec.preset(name)
    try:
        spec = GripperSpec.from_gripper(Gripper.load(name))
    except NormposError as exc:
        raise InputError(f"unknown gripper {name!r}: give 2f85, 2f140 or a packaged parallel gripper ({exc})") from exc
    if spec.kind != "parallel":
        raise InputError(f"gripper {name!r} is a {spec.kind} tool; teach validates parallel-jaw grasps")
    return spec


# -- the whole part --------------------------------------------------------------------------------------------
def teach_part(
    template: Template,
    folder: Path,
    obj_id: int,
    options: TeachOptions | None = None,
    progress: ProgressFn | None = None,
) -> TaughtPart:
    """Teach one checked template (from `check_cad`) into `folder` (created; it must not exist): steps 2-5."""
    from normpos_grasp.templates.prepared import prepare

    opts = options or TeachOptions()
    say = progress or (lambda _m: None)
    t0 = time.perf_counter()
    deadline = t0 + opts.budget_s
    timings: dict[str, float] = {}
    notes: list[str] = []
    say(f"{template.name}: symmetry")
    sym = detect_symmetry(template.mesh)
    shape = template.shape
    if template.shape == "irregular" or not template.grasps:
        shape = classify_shape(template.mesh, sym)
    template = replace(template, symmetry=sym.symmetry, shape=shape, obj_id=obj_id)
    timings["symmetry"] = time.perf_counter() - t0
    t = time.perf_counter()
    say(f"{template.name}: resting poses")
    rest = resting_poses(template, opts.rest_samples, opts.seed)
    checked = []
    for pose in rest:
        drift, tilt = drop_check(template, pose.world_from_object)
        checked.append(replace(pose, drift_m=drift, tilt_rad=tilt))
    unstable = [i for i, p in enumerate(checked) if not p.stable_in_physics]
    if unstable:
        notes.append(f"resting poses {[i + 1 for i in unstable]} moved in the MuJoCo drop (see drift and tilt)")
    timings["resting_poses"] = time.perf_counter() - t
    t = time.perf_counter()
    say(f"{template.name}: grasps")
    spec = gripper_spec(opts.gripper)
    grasps = candidate_grasps(template, spec.tip_beyond_tcp_m)
    if not grasps:
        raise TemplateError(f"'{template.name}': no parallel grasp fits the part (synthesis found none)")
    stable_poses = [p for p in checked if p.stable_in_physics] or checked
    trials, spent = validate_grasps(template, grasps, stable_poses, opts, deadline, say)
    if spent:
        notes.append(f"the budget of {opts.budget_s:.0f} s ran out during grasp validation")
    success: dict[str, float] = {}
    counts: dict[str, list[int]] = {}
    for tr in trials:
        c = counts.setdefault(tr.grasp_id, [0, 0])
        c[0] += tr.held
        c[1] += len(tr.outcomes)
    success = {gid: held / n for gid, (held, n) in counts.items() if n}
    kept: list[GraspAnnotation] = []
    dropped: list[str] = []
    untried: list[GraspAnnotation] = []
    for g in grasps:
        rate = success.get(g.id)
        if rate is not None and rate < opts.min_success:
            dropped.append(g.id)
        elif rate is None:
            untried.append(g)
        else:
            kept.append(replace(g, priority=float(g.priority) + 2.0 * rate))
    untried.sort(key=lambda g: (-g.priority, g.id))
    kept.extend(untried[: max(0, opts.max_grasps - len(kept))])  # the best untried ones, for the other poses
    if not kept:
        raise TemplateError(
            f"'{template.name}': every grasp tried failed in physics ({len(dropped)} grasps); is the part too heavy, "
            "too big for the gripper, or too slippery?"
        )
    template = replace(template, grasps=tuple(kept))
    timings["grasps"] = time.perf_counter() - t
    t = time.perf_counter()
    say(f"{template.name}: writing and preparing")
    folder.mkdir(parents=True)
    save_template(template, folder, units="mm")
    record = _teach_record(template, sym, checked, trials, success, dropped, timings, notes)
    _amend_yaml(folder / TEMPLATE_FILE, record, success, counts)
    written = load_template(folder)
    prepare(written)  # stored under folder/.prepared: the first fit of a process loads it
    timings["write_prepare"] = time.perf_counter() - t
    timings["total"] = time.perf_counter() - t0
    n_untried = sum(1 for g in kept if g.id not in success)
    part = TaughtPart(
        written,
        template.report if isinstance(template.report, MeshReport) else check_mesh(template.mesh, template.name)[1],
        sym,
        tuple(checked),
        tuple(trials),
        success,
        tuple(dropped),
        n_untried,
        timings,
        folder,
        spent,
        tuple(notes),
        {g.id: g for g in grasps},
    )
    if opts.report:
        atomic_write_text(folder / REPORT_FILE, render_report(part, spec))
    return part


def _teach_record(
    template: Template,
    sym: SymmetryReport,
    rest: Sequence[RestingPose],
    trials: Sequence[GraspTrial],
    success: dict[str, float],
    dropped: Sequence[str],
    timings: dict[str, float],
    notes: Sequence[str],
) -> dict[str, Any]:
    return {
        "symmetry": sym.summary,
        "shape": template.shape,
        "resting_poses": [
            {
                "down": [round(float(x), 6) for x in p.down],
                "probability": round(p.probability, 4),
                "drift_mm": round(p.drift_m * 1e3, 3),
                "tilt_deg": round(float(np.rad2deg(p.tilt_rad)), 3),
            }
            for p in rest
        ],
        "grasps_tried": len(success),
        "grasps_dropped": list(dropped),
        "trials": [{"grasp": tr.grasp_id, "pose": tr.pose_index + 1, "outcomes": list(tr.outcomes)} for tr in trials],
        "timings_s": {k: round(v, 3) for k, v in timings.items()},
        "notes": list(notes),
    }


def _amend_yaml(path: Path, record: dict[str, Any], success: dict[str, float], counts: dict[str, list[int]]) -> None:
    """Add the teach record and each tried grasp's measured success rate to a written template.yaml."""
    import yaml

    from normpos_grasp.io.yaml_safe import load_yaml_file

    spec = load_yaml_file(path)
    for g in spec.get("grasps") or []:
        if g["id"] in success:
            g["success_rate"] = round(success[g["id"]], 4)
            g["trials"] = int(counts[g["id"]][1])
    spec["teach"] = record
    atomic_write_text(path, yaml.safe_dump(spec, sort_keys=False, default_flow_style=None))  # vectors on one line


def next_obj_id(out: Path, taken: Sequence[int] = ()) -> int:
    """The first obj_id above FIRST_OBJ_ID - 1 that neither the library in `out` nor `taken` uses."""
    used = set(int(i) for i in taken)
    if out.is_dir() and any((p / TEMPLATE_FILE).is_file() for p in out.iterdir() if p.is_dir()):
        used.update(t.obj_id for t in load_library(out))
    k = FIRST_OBJ_ID
    while k in used:
        k += 1
    return k


def teach(
    sources: Sequence[str | Path],
    out: str | Path,
    options: TeachOptions | None = None,
    progress: ProgressFn | None = None,
    overwrite: bool = False,
) -> list[TaughtPart]:
    """Teach every mesh / template of `sources` into the library folder `out` (one sub-folder per part).

    Every input is read and checked first (bad CAD raises before anything is written); the parts are taught in a
    staging folder inside `out` and moved into place together once all succeeded. A part folder that exists in
    `out` is refused unless `overwrite`.
    """
    opts = options or TeachOptions()
    if not sources:
        raise InputError("give at least one mesh file or template folder to teach")
    root = Path(out)
    if root.exists() and not root.is_dir():
        raise InputError(f"--out {root} is a file; give the library folder")
    checked = [check_cad(s, opts) for s in sources]
    names = [t.name for t in checked]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise InputError(f"two inputs give the same part name {dup}; rename one of the files")
    for t in checked:
        if t.name == LIBRARY_SEGMENTER_DIR:  # the library's model folder
            raise InputError(f"a part may not be named '{t.name}' (the library keeps its segmenter there); rename it")
        if (root / t.name).exists() and not overwrite:
            raise InputError(f"{root / t.name} exists already; pass --overwrite to teach '{t.name}' again")
    staging = root / f".teach-{os.getpid()}.partial"
    parts: list[TaughtPart] = []
    created_root = not root.exists()
    root.mkdir(parents=True, exist_ok=True)
    try:
        taken: list[int] = []
        for t in checked:
            obj_id = t.obj_id if t.obj_id >= 0 else next_obj_id(root, taken)
            taken.append(obj_id)
            parts.append(teach_part(t, staging / t.name, obj_id, opts, progress))
        segmenter = staging / LIBRARY_SEGMENTER_DIR
        if opts.segmenter_budget_s > 0:
            extend_segmenter(root, [p.folder for p in parts], segmenter, opts, progress)
        for part in parts:  # all parts are complete: move them into the library
            final = root / part.folder.name
            if final.exists():
                shutil.rmtree(final)
            os.replace(part.folder, final)
        if segmenter.is_dir():  # the segmenter taught the whole library replaces the one taught before
            final = root / LIBRARY_SEGMENTER_DIR
            if final.exists():
                shutil.rmtree(final)
            os.replace(segmenter, final)
        shutil.rmtree(staging, ignore_errors=True)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        if created_root and root.is_dir() and not any(root.iterdir()):
            root.rmdir()
        raise
    moved = []
    for part in parts:
        final = root / part.folder.name
        moved.append(replace(part, folder=final, template=load_template(final)))
    return moved


# -- 5. the report -----------------------------------------------------------------------------------------------
def _picture(template: Template, world_from_object: FloatArray, tcp: FloatArray | None, opening: float,
             spec: Any, size: tuple[int, int] = (320, 240)) -> str:  # fmt: skip
    """A shaded PNG (base64) of the part on a floor, with the jaws of a grasp at world_from_tcp `tcp`."""
    import cv2
    import trimesh

    from normpos_grasp.camera.model import Camera
    from normpos_grasp.camera.render import render

    mesh = template.mesh
    r = float(np.linalg.norm(mesh.extents))
    w, h = size
    f = 0.9 * w
    k = np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1.0]])
    centre = world_from_object[:3, :3] @ np.asarray(mesh.centroid) + world_from_object[:3, 3]
    eye = centre + np.array([1.2, -1.6, 1.3]) * r * 1.1
    wfc = look_at(eye, centre)
    cam = Camera(k, w, h, np.zeros(5), 0.001, wfc)
    cfw = np.linalg.inv(wfc)
    floor = trimesh.creation.box(extents=[6 * r, 6 * r, 0.002])
    items = [(mesh, cfw @ world_from_object), (floor, cfw @ make_pose(translation=[0, 0, -0.001]))]
    if tcp is not None:
        for side in (-1.0, 1.0):
            finger = trimesh.creation.box(extents=[spec.finger_thickness_m, spec.finger_width_m, spec.finger_length_m])
            x = side * (opening / 2.0 + spec.finger_thickness_m / 2.0)
            z = spec.tip_beyond_tcp_m - spec.finger_length_m / 2.0
            items.append((finger, cfw @ tcp @ make_pose(translation=[x, 0.0, z])))
    ren = render(cam, items)
    light = np.array([-0.3, -0.5, -0.8])
    light /= np.linalg.norm(light)
    shade = np.clip(-(ren.normals_camera @ (cfw[:3, :3] @ -light)), 0.0, 1.0) * 0.7 + 0.3
    colours = np.array([[40, 120, 230], [200, 200, 200], [60, 60, 60], [60, 60, 60]], dtype=np.float64)  # BGR
    img = np.full((h, w, 3), 255.0)
    for i in range(len(items)):
        m = ren.index == i
        img[m] = colours[min(i, 3)] * np.abs(shade[m])[:, None]
    ok, buf = cv2.imencode(".png", img.astype(np.uint8))
    if not ok:
        raise InputError("cannot encode a report picture")
    return base64.b64encode(buf.tobytes()).decode()


def render_report(part: TaughtPart, spec: Any) -> str:
    """report.html of one taught part: mesh check, symmetry, resting poses and tried grasps (pictures), timings."""
    t = part.template
    e = html.escape
    by_id = {g.id: g for g in t.grasps}
    rows = []
    for i, p in enumerate(part.resting):
        img = _picture(t, p.world_from_object, None, 0.0, spec)
        rows.append(
            f"<figure><img src='data:image/png;base64,{img}'><figcaption>pose {i + 1}: probability "
            f"{p.probability:.1%}; MuJoCo drop: drift {p.drift_m * 1e3:.2f} mm, tilt {np.rad2deg(p.tilt_rad):.2f} deg"
            f"</figcaption></figure>"
        )
    grasp_figs = []
    for tr in part.trials:
        g = by_id.get(tr.grasp_id) or part.candidates.get(tr.grasp_id)
        pose = part.resting[tr.pose_index]
        rate = part.success.get(tr.grasp_id, 0.0)
        rate_txt = f"success {rate:.0%} over all poses" + ("" if tr.grasp_id in by_id else ", dropped")
        img = ""
        if g is not None:
            img = _picture(t, pose.world_from_object, pose.world_from_object @ g.object_from_tcp, g.opening_m, spec)
        grasp_figs.append(
            f"<figure>{f'<img src=data:image/png;base64,{img}>' if img else ''}<figcaption>{e(tr.grasp_id)} in pose "
            f"{tr.pose_index + 1}: held {tr.held}/{len(tr.outcomes)} ({e(', '.join(tr.outcomes))}); {rate_txt}"
            "</figcaption></figure>"
        )
    rep = part.mesh_report
    timings = ", ".join(f"{k} {v:.1f} s" for k, v in part.timings.items())
    notes = "".join(f"<li>{e(n)}</li>" for n in part.notes) or "<li>none</li>"
    return f"""<!doctype html><html><head><meta charset="utf-8"><title>teach: {e(t.name)}</title>
<style>body{{font-family:sans-serif;margin:2em}} figure{{display:inline-block;margin:.5em;width:330px}}
figcaption{{font-size:90%}} td,th{{padding:2px 8px;text-align:left}}</style></head><body>
<h1>Part '{e(t.name)}' (obj_id {t.obj_id})</h1>
<table>
<tr><th>source</th><td>{e(str(t.source))}</td></tr>
<tr><th>size</th><td>{" x ".join(f"{x * 1e3:.1f}" for x in t.extents_m)} mm, mass {t.mass_kg * 1e3:.1f} g</td></tr>
<tr><th>mesh</th><td>{e(rep.summary())}</td></tr>
<tr><th>symmetry</th><td>{e(part.symmetry.summary)} ({len(t.symmetry.discrete)} discrete transforms,
{len(t.symmetry.continuous)} continuous axes)</td></tr>
<tr><th>shape class</th><td>{e(t.shape)}</td></tr>
<tr><th>grasps</th><td>{len(t.grasps)} kept, {len(part.success)} tried in MuJoCo, {len(part.dropped)} dropped,
{part.untried} kept untried</td></tr>
<tr><th>timings</th><td>{e(timings)}</td></tr>
</table><h2>Notes</h2><ul>{notes}</ul>
<h2>Resting poses (quasi-static on the convex hull, checked by a MuJoCo drop)</h2>{"".join(rows)}
<h2>Grasps tried (lift, transfer, hold; trial 2 displaced 2 mm / 4 deg, trial 3 shaken)</h2>{"".join(grasp_figs)}
</body></html>
"""


# -- 6. the segmenter ---------------------------------------------------------------------------------------------
#: validation bins per minute of the segmenter budget (at least 1, at most 20)
VAL_SCENES_PER_MIN = 2.0


def extend_segmenter(
    root: Path, staged: Sequence[Path], out: Path, opts: TeachOptions, progress: ProgressFn | None = None
) -> Path | None:
    """Step 6: teach the segmentation model the library's parts (`training.head_tune.tune_segmenter`, within
    `opts.segmenter_budget_s`): the parts in the `staged` folders and those already in the library `root`, mixed
    with the built-in parts, on bins of `opts.segmenter_cell`; writes out/normpos_seg.onnx and out/MODEL_CARD.md.
    None (and nothing written) when the bundled model already knows every label of the library."""
    from normpos_grasp.cell import resolve_cell
    from normpos_grasp.perception.onnx_segmenter import BUNDLED_MODEL
    from normpos_grasp.templates.library import resolve_library
    from normpos_grasp.training.head_tune import Trunk, tune_segmenter

    note = progress or (lambda _msg: None)
    templates = [load_template(p) for p in staged]
    names = {t.name for t in templates}
    if root.is_dir() and any((p / TEMPLATE_FILE).is_file() for p in root.iterdir() if p.is_dir()):
        templates += [t for t in load_library(root) if t.name not in names]
    names = {t.name for t in templates}
    templates += [t for t in resolve_library(["builtin"]) if t.name not in names]
    known = set(Trunk(BUNDLED_MODEL).names)
    if all(t.label in known for t in templates):
        note("segmenter: the bundled model knows every label of the library; not extended")
        return None
    budget = opts.segmenter_budget_s
    val_scenes = int(min(20, max(1, round(budget / 60.0 * VAL_SCENES_PER_MIN))))
    report = tune_segmenter(
        templates, out, resolve_cell(opts.segmenter_cell), scenes=100_000, val_scenes=val_scenes,
        budget_s=budget, log=lambda msg: note(f"segmenter: {msg}"),
    )  # fmt: skip
    new = report.figures.get("tuned new", {})
    checked = (
        f"on {report.val_frames} held-back frames recall {new['recall']:.2f}, precision {new['precision']:.2f} of "
        f"{new['gt']:.0f} new-part instances"
        if new.get("gt", 0) > 0
        else f"no new part large enough to count in its {report.val_frames} held-back frames (a larger budget "
        "validates on more)"
    )
    note(f"segmenter: taught {', '.join(report.new_labels)} on {report.frames} frames; {checked}")
    return report.model_path
