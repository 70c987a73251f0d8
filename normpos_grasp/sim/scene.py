"""Scene composition: a table (world z = 0, z up), an optional bin or conveyor, parts dropped with MuJoCo physics.

`compose_scene(options, library)` spawns parts above the container without overlap, lets them fall and
settle under MuJoCo physics (deterministic for a seed) and returns a `SceneLayout`: every part's
`world_from_object` at rest and the static geometry as boxes others reuse for collision worlds.
"""

from __future__ import annotations

import logging
import os
import sys
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy.spatial import ConvexHull, QhullError

from normpos_grasp.errors import InputError, MeshError, SimulationError
from normpos_grasp.geometry.transforms import make_pose, random_rotation, rotation_from_quaternion
from normpos_grasp.records.template import Template
from normpos_grasp.sim.parts import PART_COLORS
from normpos_grasp.sim.physics_decompose import collision_hulls, convex_decomposition
from normpos_grasp.typing import FloatArray

if TYPE_CHECKING:
    import mujoco
    import trimesh

os.environ.setdefault("MUJOCO_GL", "egl")

logger = logging.getLogger(__name__)

CONTAINERS = ("bin", "table", "conveyor")

_CONTACT = 'friction="0.7 0.005 0.001" solref="0.004 1"'

StaticBox = tuple[str, FloatArray, FloatArray]
"""(name, world_from_box (4, 4), full size (3,) in metres); the box is centred on its pose."""


@dataclass(frozen=True)
class SceneOptions:
    """How to build one scene.

    parts: part names drawn from the library (repeats allowed); empty = every part of the library.
    count: number of parts placed (drawn uniformly from `parts` with the seed).
    container: 'bin' (open box on the table), 'table' (bare table) or 'conveyor' (belt strip with rails).
    bin_inner_size_m: (x, y) inner size of the bin, metres. bin_wall_thickness_m / bin_wall_height_m: walls,
        metres (height above the bin floor). bin_floor_thickness_m: floor slab on the table, metres.
    table_size_m: (x, y) table top size, metres; its top is world z = 0.
    conveyor_width_m / conveyor_height_m: belt width and belt top height above the table, metres.
    clutter: 0 spreads the parts over the whole container, 1 drops them into the central 30 %.
    stack_layers: parts are split into this many layers dropped one above the other (more = more stacking).
    drop_height_m: clearance of the lowest layer above the floor, metres.
    settle_time_s: simulated time limit for settling, seconds; timestep_s: physics step, seconds.
    seed: RNG seed; the same options give the same layout.
    """

    parts: tuple[str, ...] = ()
    count: int = 10
    container: str = "bin"
    bin_inner_size_m: tuple[float, float] = (0.40, 0.30)
    bin_wall_thickness_m: float = 0.01
    bin_wall_height_m: float = 0.12
    bin_floor_thickness_m: float = 0.01
    table_size_m: tuple[float, float] = (1.2, 0.9)
    conveyor_width_m: float = 0.30
    conveyor_height_m: float = 0.02
    clutter: float = 0.3
    stack_layers: int = 2
    drop_height_m: float = 0.01
    settle_time_s: float = 2.5
    timestep_s: float = 0.002
    seed: int = 0

    def __post_init__(self) -> None:
        if self.container not in CONTAINERS:
            raise InputError(f"container must be one of {CONTAINERS}, got {self.container!r}")
        if self.count < 0:
            raise InputError(f"count must be >= 0, got {self.count}")
        if not 0.0 <= self.clutter <= 1.0:
            raise InputError(f"clutter must lie in [0, 1], got {self.clutter}")
        if self.stack_layers < 1:
            raise InputError(f"stack_layers must be >= 1, got {self.stack_layers}")
        if min(self.bin_inner_size_m) <= 0 or self.bin_wall_thickness_m <= 0 or self.bin_wall_height_m <= 0:
            raise InputError("bin sizes, wall thickness and wall height must be positive (metres)")
        if not 0 < self.timestep_s <= 0.01:
            raise InputError(f"timestep_s must lie in (0, 0.01] s, got {self.timestep_s}")
        object.__setattr__(self, "parts", tuple(self.parts))


@dataclass(frozen=True, eq=False)
class SceneLayout:
    """A settled scene.

    templates: one Template per placed part (part index k has instance id k + 1 in renderings).
    world_from_object: (N, 4, 4) rest poses, metres.
    static_boxes: static geometry as (name, world_from_box (4, 4), full size (3,)) boxes; the table top is z = 0.
    max_penetration_m: deepest contact penetration left after settling (>= 0), metres.
    settle_time_s: simulated time until the parts came to rest, seconds; settled: whether they did.
    """

    templates: tuple[Template, ...]
    world_from_object: FloatArray
    static_boxes: tuple[StaticBox, ...]
    options: SceneOptions = field(default_factory=SceneOptions)
    max_penetration_m: float = 0.0
    settle_time_s: float = 0.0
    settled: bool = True

    def __post_init__(self) -> None:
        poses = np.asarray(self.world_from_object, dtype=np.float64).reshape(-1, 4, 4)
        if len(poses) != len(self.templates):
            raise InputError(f"need one pose per template: {len(self.templates)} templates, {len(poses)} poses")
        for i, (name, pose, size) in enumerate(self.static_boxes):
            if np.shape(pose) != (4, 4) or np.shape(size) != (3,):
                raise InputError(f"static box {i} ({name!r}) needs a (4, 4) pose and a (3,) size")
        object.__setattr__(self, "templates", tuple(self.templates))
        object.__setattr__(self, "world_from_object", poses)
        object.__setattr__(self, "static_boxes", tuple(self.static_boxes))

    @property
    def part_names(self) -> list[str]:
        return [t.name for t in self.templates]

    @property
    def n_parts(self) -> int:
        return len(self.templates)

    def part_mesh_world(self, index: int) -> trimesh.Trimesh:
        """The mesh of part `index` in the world frame (a copy)."""
        mesh = self.templates[index].mesh.copy()
        mesh.apply_transform(self.world_from_object[index])
        return mesh

    def container_centre(self) -> FloatArray:
        """(3,) world point at the middle of the container floor, metres (a camera target)."""
        o = self.options
        z = (
            o.bin_floor_thickness_m
            if o.container == "bin"
            else (o.conveyor_height_m if o.container == "conveyor" else 0)
        )
        return np.array([0.0, 0.0, float(z)])


def import_mujoco() -> Any:
    """Import `mujoco`; if its OpenGL backend (MUJOCO_GL) cannot even load, retry with rendering disabled.

    Physics then still works and the renderer falls back to ray casting. Raises SimulationError when MuJoCo
    itself is missing.
    """
    try:
        import mujoco

        return mujoco
    except ModuleNotFoundError as exc:
        raise SimulationError(f"the mujoco package is needed for scene physics: {exc}") from exc
    except Exception as exc:  # a broken GL backend raises AttributeError/OSError/RuntimeError at import time
        backend = os.environ.get("MUJOCO_GL", "")
        logger.warning("import mujoco failed with MUJOCO_GL=%r (%s); retrying with OpenGL disabled", backend, exc)
        for name in [m for m in sys.modules if m == "mujoco" or m.startswith("mujoco.")]:
            del sys.modules[name]
        os.environ["MUJOCO_GL"] = "disable"
        import mujoco

        return mujoco


# -- static geometry -------------------------------------------------------------------------
def static_boxes(options: SceneOptions) -> tuple[StaticBox, ...]:
    """The table and the container as boxes (name, world_from_box, full size), metres."""
    tx, ty = options.table_size_m
    table_t = 0.04
    boxes: list[StaticBox] = [("table", make_pose(translation=[0, 0, -table_t / 2]), np.array([tx, ty, table_t]))]
    if options.container == "bin":
        ix, iy = options.bin_inner_size_m
        w, h, f = options.bin_wall_thickness_m, options.bin_wall_height_m, options.bin_floor_thickness_m
        ox, oy = ix + 2 * w, iy + 2 * w
        zc = f + h / 2
        boxes.append(("bin_floor", make_pose(translation=[0, 0, f / 2]), np.array([ox, oy, f])))
        boxes.append(("bin_wall_px", make_pose(translation=[(ix + w) / 2, 0, zc]), np.array([w, oy, h])))
        boxes.append(("bin_wall_mx", make_pose(translation=[-(ix + w) / 2, 0, zc]), np.array([w, oy, h])))
        boxes.append(("bin_wall_py", make_pose(translation=[0, (iy + w) / 2, zc]), np.array([ix, w, h])))
        boxes.append(("bin_wall_my", make_pose(translation=[0, -(iy + w) / 2, zc]), np.array([ix, w, h])))
    elif options.container == "conveyor":
        bw, bh = options.conveyor_width_m, options.conveyor_height_m
        rail_h, rail_w = 0.03, 0.015
        boxes.append(("conveyor_belt", make_pose(translation=[0, 0, bh / 2]), np.array([tx, bw, bh])))
        for side, sgn in (("py", 1.0), ("my", -1.0)):
            y = sgn * (bw / 2 + rail_w / 2)
            boxes.append(
                (
                    f"conveyor_rail_{side}",
                    make_pose(translation=[0, y, (bh + rail_h) / 2]),
                    np.array([tx, rail_w, bh + rail_h]),
                )
            )
    return tuple(boxes)


def _spawn_region(options: SceneOptions) -> tuple[FloatArray, FloatArray, float]:
    """(lo (2,), hi (2,), floor z) of the region parts are dropped into."""
    if options.container == "bin":
        half = np.asarray(options.bin_inner_size_m, dtype=np.float64) / 2
        floor = options.bin_floor_thickness_m
    elif options.container == "conveyor":
        half = np.array([0.25, options.conveyor_width_m / 2])
        floor = options.conveyor_height_m
    else:
        half = np.array([0.20, 0.15])
        floor = 0.0
    half = half * (1.0 - 0.7 * options.clutter)
    return -half, half, float(floor)


# -- MJCF ------------------------------------------------------------------------------------
def _fmt(values: Any) -> str:
    return " ".join(f"{float(v):.17g}" for v in np.asarray(values, dtype=np.float64).reshape(-1))


def _ifmt(values: Any) -> str:
    return " ".join(str(int(v)) for v in np.asarray(values).reshape(-1))


def _quat_wxyz(rotation: FloatArray) -> FloatArray:
    mujoco = import_mujoco()
    q = np.zeros(4)
    mujoco.mju_mat2Quat(q, np.ascontiguousarray(rotation, dtype=np.float64).reshape(-1))
    return q


def convex_pieces(template: Template) -> list[tuple[str, Any]]:
    """Collision pieces of a part in its object frame: ('box', full size (3,)), ('sphere', r), ('mesh', (V, 3)).

    Boxes and spheres use exact primitives; rings are cut into 16 convex sectors, L-brackets along their
    bisector plane into two convex halves, when those pieces make up the part (their hulls' volumes add up to
    the part's); other convex parts collide as their hull, other non-convex parts as their convex decomposition
    (`physics_decompose`). Every mesh piece is one MuJoCo accepts (`collision_hulls`: flat or thin pieces
    thickened, pieces without area dropped), for any mesh.
    """
    mesh = template.mesh
    v = np.asarray(mesh.vertices, dtype=np.float64)
    ext = np.asarray(mesh.extents, dtype=np.float64)
    centred = np.allclose(mesh.bounds.mean(axis=0), 0.0, atol=1e-9)
    if template.shape in ("box", "plate") and centred and abs(mesh.volume - np.prod(ext)) < 1e-3 * np.prod(ext):
        return [("box", ext)]
    if template.shape == "sphere" and centred:
        r = float(np.linalg.norm(v, axis=1).max())
        if abs(mesh.volume - 4 / 3 * np.pi * r**3) < 0.02 * mesh.volume:
            return [("sphere", r)]
    return [("mesh", h) for h in collision_hulls(_mesh_pieces(template))]


def _mesh_pieces(template: Template) -> list[FloatArray]:
    """Convex point sets covering the part (object frame, metres): the shape heuristics of `convex_pieces` when
    they fit the mesh, else its hull (convex parts) or its convex decomposition."""
    mesh = template.mesh
    v = np.asarray(mesh.vertices, dtype=np.float64)
    volume = float(mesh.volume)
    pieces: list[FloatArray] = []
    if template.shape == "ring":
        ang = np.arctan2(v[:, 1], v[:, 0])
        n = 16
        for k in range(n):
            a0 = -np.pi + 2 * np.pi * k / n
            a1 = a0 + 2 * np.pi / n
            d0 = np.angle(np.exp(1j * (ang - a0)))
            d1 = np.angle(np.exp(1j * (ang - a1)))
            sel = (d0 >= -1e-6) & (d1 <= 1e-6)
            if sel.sum() >= 4:
                pieces.append(v[sel])
    elif template.shape == "bracket":
        pieces = [v[v[:, 1] >= -1e-9], v[v[:, 1] <= 1e-9]]
    if pieces and _fills(pieces, volume):
        return pieces
    hull = np.asarray(mesh.convex_hull.vertices, dtype=np.float64)
    if volume >= 0.97 * float(mesh.convex_hull.volume):
        return [hull]
    try:
        return [p.vertices for p in convex_decomposition(v, np.asarray(mesh.faces))]
    except MeshError as exc:  # not a closed mesh: collide as its hull
        logger.warning("part '%s' collides as its convex hull: %s", template.name, exc)
        return [hull]


def _fills(pieces: list[FloatArray], volume: float) -> bool:
    """Whether the hulls of `pieces` all have volume and add up to the solid's `volume` (m^3) within -2 / +5 %."""
    total = 0.0
    for p in pieces:
        if len(p) < 4:
            return False
        try:
            total += float(ConvexHull(p).volume)
        except QhullError:  # flat or collinear piece
            return False
    return 0.98 * volume <= total <= 1.05 * volume


def build_mjcf(
    templates: tuple[Template, ...] | list[Template],
    boxes: tuple[StaticBox, ...],
    poses: FloatArray,
    free: bool,
    offscreen_size: tuple[int, int] = (640, 480),
    timestep_s: float = 0.002,
    offscreen_samples: int = 4,
) -> str:
    """MJCF text of the scene: static boxes, one body per part (visual mesh + collision pieces in group 3).

    free: parts get free joints (physics) or are fixed at `poses` (rendering). offscreen_size: (W, H) of the
    offscreen framebuffer, pixels; offscreen_samples: multisampling of that framebuffer (0 = none).
    """
    assets: list[str] = []
    bodies: list[str] = []
    names: dict[str, str] = {}
    for i, t in enumerate(templates):
        if t.name not in names:
            key = f"m{len(names)}"
            names[t.name] = key
            mesh = t.mesh
            assets.append(f'<mesh name="{key}_vis" vertex="{_fmt(mesh.vertices)}" face="{_ifmt(mesh.faces)}"/>')
            for j, (kind, data) in enumerate(convex_pieces(t)):
                if kind == "mesh":
                    assets.append(f'<mesh name="{key}_c{j}" vertex="{_fmt(data)}"/>')
            rgba = PART_COLORS.get(t.name, (0.6, 0.6, 0.6, 1.0))
            assets.append(f'<material name="{key}_mat" rgba="{_fmt(rgba)}" specular="0.3" shininess="0.3"/>')
        key = names[t.name]
        pose = poses[i]
        vis_attrs = f'material="{key}_mat" contype="0" conaffinity="0" group="0" mass="0"'
        geoms = [f'<geom name="p{i}_vis" type="mesh" mesh="{key}_vis" {vis_attrs}/>']
        for j, (kind, data) in enumerate(convex_pieces(t)):
            common = f'name="p{i}_c{j}" group="3" rgba="0 0 0 0" condim="6" {_CONTACT} mass="0"'
            if kind == "box":
                geoms.append(f'<geom type="box" size="{_fmt(np.asarray(data) / 2)}" {common}/>')
            elif kind == "sphere":
                geoms.append(f'<geom type="sphere" size="{float(data):.17g}" {common}/>')
            else:
                geoms.append(f'<geom type="mesh" mesh="{key}_c{j}" {common}/>')
        inertia = np.asarray(t.mesh.moment_inertia, dtype=np.float64) * (t.mass_kg / max(t.mesh.volume, 1e-12))
        com = np.asarray(t.mesh.center_mass, dtype=np.float64)
        full = _fmt([inertia[0, 0], inertia[1, 1], inertia[2, 2], inertia[0, 1], inertia[0, 2], inertia[1, 2]])
        inertial = f'<inertial pos="{_fmt(com)}" mass="{t.mass_kg:.17g}" fullinertia="{full}"/>' if free else ""
        joint = f'<freejoint name="p{i}_joint"/>' if free else ""
        bodies.append(
            f'<body name="p{i}" pos="{_fmt(pose[:3, 3])}" quat="{_fmt(_quat_wxyz(pose[:3, :3]))}">'
            f"{joint}{inertial}{''.join(geoms)}</body>"
        )
    statics = []
    for name, pose, size in boxes:
        box_rgba = (
            "0.55 0.45 0.35 1" if name == "table" else ("0.2 0.2 0.22 1" if "belt" in name else "0.45 0.5 0.58 1")
        )
        statics.append(
            f'<geom name="static_{name}" type="box" size="{_fmt(np.asarray(size) / 2)}" pos="{_fmt(pose[:3, 3])}" '
            f'quat="{_fmt(_quat_wxyz(pose[:3, :3]))}" rgba="{box_rgba}" {_CONTACT}/>'
        )
    w, h = offscreen_size
    return (
        '<mujoco model="normpos_scene"><compiler angle="radian" boundmass="1e-6" boundinertia="1e-12"/>'
        f'<option timestep="{timestep_s:.17g}" integrator="implicitfast" cone="elliptic"/>'
        '<statistic extent="2" center="0 0 0"/>'
        f'<visual><global offwidth="{int(w)}" offheight="{int(h)}"/>'
        f'<quality shadowsize="0" offsamples="{int(offscreen_samples)}"/>'
        '<headlight ambient="0.35 0.35 0.35" diffuse="0.45 0.45 0.45" specular="0.1 0.1 0.1"/></visual>'
        f"<asset>{''.join(assets)}</asset>"
        '<worldbody><light directional="true" pos="0 0 3" dir="0.3 0.2 -1" diffuse="0.5 0.5 0.5" castshadow="false"/>'
        f"{''.join(statics)}{''.join(bodies)}</worldbody></mujoco>"
    )


def load_model(xml: str) -> mujoco.MjModel:
    mujoco = import_mujoco()
    try:
        return mujoco.MjModel.from_xml_string(xml)
    except ValueError as exc:
        raise SimulationError(f"MuJoCo rejected the generated scene: {exc}") from exc


# -- composition -----------------------------------------------------------------------------
def _choose_parts(options: SceneOptions, library: list[Template], rng: np.random.Generator) -> list[Template]:
    if options.count == 0:
        return []
    by_name = {t.name: t for t in library}
    names = list(options.parts) or [t.name for t in library]
    missing = [n for n in names if n not in by_name]
    if missing:
        raise InputError(f"unknown part names {missing}; the library holds {sorted(by_name)}")
    if not names:
        raise InputError("the part library is empty; pass at least one Template")
    picks = rng.integers(0, len(names), size=options.count)
    return [by_name[names[int(k)]] for k in picks]


def _spawn_poses(templates: list[Template], options: SceneOptions, rng: np.random.Generator) -> FloatArray:
    lo, hi, floor = _spawn_region(options)
    radii = [float(np.linalg.norm(np.asarray(t.mesh.vertices), axis=1).max()) for t in templates]
    n = len(templates)
    per_layer = max(1, int(np.ceil(n / options.stack_layers)))
    placed: list[tuple[FloatArray, float]] = []
    poses = np.zeros((n, 4, 4))
    layer_top = floor + options.drop_height_m
    for start in range(0, n, per_layer):
        idx = list(range(start, min(n, start + per_layer)))
        layer_r = max(radii[i] for i in idx)
        z = layer_top + layer_r
        for i in idx:
            r = radii[i]
            pos = None
            for attempt in range(400):
                span_lo = np.minimum(lo + r, 0.0)
                span_hi = np.maximum(hi - r, 0.0)
                xy = rng.uniform(span_lo, span_hi)
                cand = np.array([xy[0], xy[1], z + (attempt // 100) * 2 * layer_r])
                if all(np.linalg.norm(cand - p) > r + q + 0.003 for p, q in placed):
                    pos = cand
                    break
            if pos is None:  # no room in this layer: put it above everything placed so far
                top = max((p[2] + q for p, q in placed), default=z)
                pos = np.array([0.0, 0.0, top + r + 0.003])
            placed.append((pos, r))
            poses[i] = make_pose(random_rotation(rng), pos)
        layer_top = max(p[2] + q for p, q in placed) + 0.005
    return poses


def compose_scene(options: SceneOptions, library: list[Template]) -> SceneLayout:
    """Drop `options.count` parts from `library` into the container and let them settle (MuJoCo physics).

    Deterministic for `options.seed`. Parts that roll off the table are left out of the layout (logged).
    Raises SimulationError when the physics blows up.
    """
    mujoco = import_mujoco()

    rng = np.random.default_rng(options.seed)
    templates = _choose_parts(options, library, rng)
    boxes = static_boxes(options)
    if not templates:
        return SceneLayout((), np.zeros((0, 4, 4)), boxes, options)
    poses = _spawn_poses(templates, options, rng)
    model = load_model(build_mjcf(templates, boxes, poses, free=True, timestep_s=options.timestep_s))
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    n_steps = int(np.ceil(options.settle_time_s / options.timestep_s))
    check_every = max(1, int(round(0.05 / options.timestep_s)))
    calm_needed = max(1, int(round(0.25 / options.timestep_s)))
    calm = 0
    settled = False
    step = 0
    for step in range(1, n_steps + 1):
        mujoco.mj_step(model, data)
        if step % check_every:
            continue
        if not np.all(np.isfinite(data.qpos)):
            raise SimulationError(
                f"physics diverged while settling scene seed {options.seed}; try a smaller timestep_s"
            )
        qv = data.qvel.reshape(-1, 6)
        lin = float(np.linalg.norm(qv[:, :3], axis=1).max())
        ang = float(np.linalg.norm(qv[:, 3:], axis=1).max())
        calm = calm + check_every if lin < 0.005 and ang < 0.1 else 0
        if calm >= calm_needed and step * options.timestep_s > 0.3:
            settled = True
            break
    if not settled:
        logger.info("scene seed %d: parts still moving after %.2f s of settling", options.seed, options.settle_time_s)
    out = np.zeros((len(templates), 4, 4))
    for i in range(len(templates)):
        q = data.qpos[7 * i : 7 * i + 7]
        out[i] = make_pose(rotation_from_quaternion([q[4], q[5], q[6], q[3]]), q[:3])
    penetration = max((-float(data.contact[c].dist) for c in range(data.ncon)), default=0.0)
    fallen = [i for i in range(len(templates)) if out[i, 2, 3] < -0.02]
    if fallen:  # rolled off the table: not at rest anywhere, leave them out
        logger.warning("scene seed %d: %d part(s) fell off the table and were removed", options.seed, len(fallen))
        keep = [i for i in range(len(templates)) if i not in fallen]
        templates = [templates[i] for i in keep]
        out = out[keep]
    return SceneLayout(
        templates=tuple(templates),
        world_from_object=out,
        static_boxes=boxes,
        options=options,
        max_penetration_m=max(0.0, penetration),
        settle_time_s=step * options.timestep_s,
        settled=settled,
    )
