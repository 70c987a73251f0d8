"""`CollisionWorld`: the cell as python-fcl sees it, and the collision queries the planner runs.

Contents by category, each in its own broad-phase manager so a hit names what was hit:
'cell' (table, bin walls, conveyor, fixtures, camera mount: boxes), 'object' (fitted objects: BVH meshes of their
templates), 'clutter' (measured points that no accepted fit explains: voxel boxes, so unknown clutter is never
ignored). The arm (`ArmModel`, links posed from FK), the tool at a given opening and a held object are the moving
parts. Collision queries stop at the first contact (early-exit callback); distance queries are offered for reports
but cost 15-100x a collision test, so the planner checks clearances with inflated shapes instead.
Scoped state changes (`without`, `holding`, `empty_handed`) restore what was there on exit.
"""

from __future__ import annotations

import logging
import weakref
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import fcl
import numpy as np

from normpos_grasp.collision.obb import aligned_box_hits, obb_overlap_pairs
from normpos_grasp.collision.spheres import spheres_apart, spheres_near_boxes, spheres_off_boxes
from normpos_grasp.errors import InputError
from normpos_grasp.typing import ArrayLike, BoolArray, FloatArray, IntArray

if TYPE_CHECKING:
    import trimesh

    from normpos_grasp.kinematics.arm import ArmModel
    from normpos_grasp.records.tool import ToolModel

logger = logging.getLogger(__name__)

CATEGORIES = ("cell", "object", "clutter")


@dataclass(frozen=True)
class Hit:
    """First contact found: `part` is the moving part ('arm', 'tool', 'held', 'self'), `what` the category hit
    ('cell', 'object', 'clutter', 'arm', 'tool') and `name` the element when known ('' otherwise)."""

    part: str
    what: str
    name: str = ""

    @property
    def reason(self) -> str:
        """Rejection reason: 'collision_<what>' (self-collision: 'collision_self')."""
        return "collision_self" if self.part == "self" else f"collision_{self.what}"


_REQUEST = fcl.CollisionRequest(num_max_contacts=1)


def _tf(pose: FloatArray) -> fcl.Transform:
    return fcl.Transform(pose[:3, :3], pose[:3, 3])


def _first_contact(o1: Any, o2: Any, cdata: Any) -> bool:
    """Early-exit callback: stop the broad phase at the first colliding pair."""
    if cdata.done:
        return True
    fcl.collide(o1, o2, cdata.request, cdata.result)
    if cdata.result.is_collision:
        cdata.done = True
    return bool(cdata.done)


def _geometry(kind: str, size: Any) -> Any:
    """fcl geometry of a primitive: box (full extents), capsule / cylinder (radius, length), sphere (radius)."""
    v = [float(x) for x in size]
    if kind == "box":
        return fcl.Box(v[0], v[1], v[2])
    if kind == "capsule":
        return fcl.Capsule(v[0], v[1])
    if kind == "cylinder":
        return fcl.Cylinder(v[0], v[1])
    if kind == "sphere":
        return fcl.Sphere(v[0])
    raise InputError(f"unknown primitive kind {kind!r}; expected box, capsule, cylinder or sphere")


_BVH_CACHE: dict[int, tuple[weakref.ref[Any], fcl.BVHModel]] = {}


def bvh_for(mesh: trimesh.Trimesh) -> fcl.BVHModel:
    """The BVH of `mesh`, built once per mesh object for the life of the process (templates persist between
    frames; the entry goes when the mesh is garbage-collected)."""
    key = id(mesh)
    hit = _BVH_CACHE.get(key)
    if hit is not None and hit[0]() is mesh:
        return hit[1]
    model = bvh_from_mesh(mesh.vertices, mesh.faces)

    def _forget(_ref: weakref.ref[Any], k: int = key) -> None:
        _BVH_CACHE.pop(k, None)

    _BVH_CACHE[key] = (weakref.ref(mesh, _forget), model)
    return model


def bvh_from_mesh(vertices: ArrayLike, faces: ArrayLike) -> fcl.BVHModel:
    """An fcl BVH model of a triangle mesh (vertices (V, 3) m, faces (F, 3))."""
    model = fcl.BVHModel()
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    model.beginModel(len(v), len(f))
    model.addSubModel(v, f)
    model.endModel()
    return model


@dataclass
class _Element:
    name: str
    category: str
    obj: fcl.CollisionObject
    geom: Any
    lo: FloatArray
    hi: FloatArray
    box: tuple[FloatArray, FloatArray] | None = None  # (world_from_box (4, 4), half extents (3,)) for boxes


def _grown_tool(tool: ToolModel, by_m: float) -> list[tuple[fcl.CollisionObject, FloatArray, FloatArray, int]]:
    """(object, tcp_from_shape at zero opening, size, moves) of the tool's shapes grown by `by_m` on every side;
    jaw fingers grow outwards only (their inner faces stay where they are)."""
    out = []
    for s in tool.shapes:
        size = np.asarray(s.size, dtype=np.float64)
        grown = size + (2 * by_m if s.kind == "box" else np.array([by_m, 2 * by_m])[: len(size)])
        pose = np.array(s.tcp_from_shape, dtype=np.float64)
        if s.moves:  # thicker by by_m and shifted out by half of it: the outer face moves by_m, the inner stays
            grown[0] = size[0] + by_m
            pose[0, 3] += s.moves * by_m / 2.0
        out.append((fcl.CollisionObject(_geometry(s.kind, grown), fcl.Transform()), pose, grown, s.moves))
    return out


def _manager(objects: list[fcl.CollisionObject]) -> fcl.DynamicAABBTreeCollisionManager:
    mgr = fcl.DynamicAABBTreeCollisionManager()
    mgr.registerObjects(objects)
    mgr.setup()
    return mgr


def held_radius(mesh: Any) -> float:
    """A held object's bounding radius about its own origin (not its centre), m: what `CollisionWorld.holding`
    and `configs_clear(held_rows=...)` give it."""
    verts = np.asarray(mesh.vertices, dtype=np.float64)
    return float(np.linalg.norm(verts, axis=1).max()) if len(verts) else 0.0


def bounding_radius(kind: str, size: Any) -> float:
    """Radius of the sphere about a primitive's centre that encloses it, m."""
    v = [float(x) for x in size]
    if kind == "box":
        return 0.5 * float(np.linalg.norm(v[:3]))
    if kind == "capsule":
        return v[0] + v[1] / 2.0
    if kind == "cylinder":
        return float(np.hypot(v[0], v[1] / 2.0))
    return v[0]


@dataclass(frozen=True)
class _ToolShapes:
    """One copy of the tool's shapes as fcl objects: exact, or grown by a clearance or a noise margin."""

    objects: tuple[fcl.CollisionObject, ...]
    tcp_from_shape: FloatArray  # (S, 4, 4) at zero opening
    radii: FloatArray  # (S,) bounding-sphere radii about each shape's centre, m


@dataclass(frozen=True)
class _ArmShapes:
    """The arm's link shapes as fcl objects, their bounding radii (m), the link pairs checked for self-collision
    and the links (base, shoulder, upper arm) that the tool and the held object are checked against."""

    objects: tuple[fcl.CollisionObject, ...]
    radii: FloatArray
    pair_mask: BoolArray  # (S, S): non-adjacent pairs on different joints
    low_links: IntArray
    joints: IntArray  # (S,) the DH frame each shape rides on
    local_centres: FloatArray  # (S, 3) each shape's centre in its DH frame, m


@dataclass(frozen=True)
class _Held:
    """The object held rigidly in the tool: its fcl object, pose in the TCP frame and radius about its origin (m)."""

    name: str
    obj: fcl.CollisionObject
    tcp_from_object: FloatArray
    radius: float


@dataclass(frozen=True)
class _BroadPhase:
    """The broad-phase managers of one set of enabled elements: one per category and one over everything, plus
    every enabled element's AABB (lo, hi: (E, 3) m) for the numpy pre-tests."""

    managers: dict[str, fcl.DynamicAABBTreeCollisionManager]
    everything: fcl.DynamicAABBTreeCollisionManager | None
    lo: FloatArray
    hi: FloatArray
    index: dict[str, int]  # element name -> its row of lo / hi


class CollisionWorld:
    """Static cell, fitted objects and clutter in broad-phase managers; arm, tool and held object as movers.

    Build with `add_box`, `add_mesh`, `add_points`; then `set_arm`, `set_tool`. Query with `check_tool`,
    `check_arm`, `check_config`, `configs_clear`. State changes are scoped: `with world.without(name):` leaves an
    element out of the queries (the target while its own grasp is checked), `with world.holding(name, mesh,
    tcp_from_object):` holds it in the tool and takes it out of the world, `with world.empty_handed():` releases
    it for the block; each restores the previous state on exit, exceptions included. The broad phase of each set of
    enabled elements is built once and kept until an element is added, removed or moved.
    """

    def __init__(self) -> None:
        self.elements: dict[str, _Element] = {}
        self.arm: ArmModel | None = None
        self.tool: ToolModel | None = None
        self.n_checks = 0  # fcl broad-phase queries run (for profiling)
        self._disabled: frozenset[str] = frozenset()
        self._phases: dict[frozenset[str], _BroadPhase] = {}
        self._arm: _ArmShapes | None = None
        self._tools: dict[str, _ToolShapes] = {}  # 'exact', 'inflated', 'margin'
        self._tool_moves: FloatArray = np.zeros(0)  # (S,) -1 / 0 / +1: how each shape moves with the opening
        self._tool_moving = False  # some shape moves with the opening
        self._tool_finger_half: FloatArray = np.zeros(0)  # (S,) half thickness of the moving fingers, m
        self._tool_centres: FloatArray = np.zeros((0, 3))  # where the exact tool was last posed, m
        self._last_opening = 0.0  # m
        self._tool_posed_by_config = False
        self._held: _Held | None = None

    # -- building -----------------------------------------------------------------------------------------------
    def add_box(self, name: str, world_from_box: ArrayLike, size: ArrayLike, category: str = "cell") -> None:
        """Add a box of full extents `size` (3,) m at `world_from_box` (4, 4)."""
        ext = np.asarray(size, dtype=np.float64).reshape(3)
        if np.any(ext <= 0):
            raise InputError(f"box {name!r}: extents must be positive, got {ext.tolist()}")
        geom = fcl.Box(*ext)
        pose = np.asarray(world_from_box, dtype=np.float64)
        half = np.abs(pose[:3, :3]) @ (ext / 2.0)
        self._add(name, category, geom, pose, pose[:3, 3] - half, pose[:3, 3] + half)
        self.elements[name].box = (pose.copy(), ext / 2.0)

    def add_mesh(self, name: str, mesh: trimesh.Trimesh, world_from_mesh: ArrayLike, category: str = "object") -> None:
        """Add a triangle mesh (metres) as a BVH model; meshes are shared between instances of one template."""
        geom = bvh_for(mesh)
        pose = np.asarray(world_from_mesh, dtype=np.float64)
        verts = np.asarray(mesh.vertices, dtype=np.float64) @ pose[:3, :3].T + pose[:3, 3]
        self._add(name, category, geom, pose, verts.min(axis=0), verts.max(axis=0))

    def add_points(self, name: str, points: ArrayLike, voxel_m: float = 0.01, category: str = "clutter") -> int:
        """Add measured points (N, 3) m as occupied voxel boxes of edge `voxel_m`; returns the voxel count."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if len(pts) == 0:
            return 0
        if voxel_m <= 0:
            raise InputError(f"voxel_m must be positive, got {voxel_m}")
        keys = np.unique(np.floor(pts / voxel_m).astype(np.int64), axis=0)
        box = fcl.Box(voxel_m, voxel_m, voxel_m)
        for i, key in enumerate(keys):
            pose = np.eye(4)
            pose[:3, 3] = (key + 0.5) * voxel_m
            self._add(f"{name}/{i}", category, box, pose, key * voxel_m, (key + 1) * voxel_m)
        return len(keys)

    def _add(self, name: str, category: str, geom: Any, pose: FloatArray, lo: FloatArray, hi: FloatArray) -> None:
        if category not in CATEGORIES:
            raise InputError(f"category must be one of {CATEGORIES}, got {category!r}")
        if name in self.elements:
            raise InputError(f"world element {name!r} already exists; names must be unique")
        obj = fcl.CollisionObject(geom, _tf(pose))
        self.elements[name] = _Element(
            name, category, obj, geom, np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
        )
        self._phases.clear()

    def remove(self, name: str) -> None:
        """Remove an element by name."""
        if self.elements.pop(name, None) is not None:
            self._phases.clear()

    def move(self, name: str, world_from_element: ArrayLike) -> None:
        """Move an element to `world_from_element` (4, 4); the broad phase is rebuilt at the next query."""
        el = self.elements[name]
        pose = np.asarray(world_from_element, dtype=np.float64)
        old = el.obj.getTransform()
        old_pose = np.eye(4)
        old_pose[:3, :3] = old.getRotation()
        old_pose[:3, 3] = old.getTranslation()
        delta = pose @ np.linalg.inv(old_pose)
        corners = (
            np.array(
                [[x, y, z] for x in (el.lo[0], el.hi[0]) for y in (el.lo[1], el.hi[1]) for z in (el.lo[2], el.hi[2])]
            )
            @ delta[:3, :3].T
            + delta[:3, 3]
        )
        el.lo, el.hi = corners.min(axis=0), corners.max(axis=0)
        el.obj.setTransform(_tf(pose))
        if el.box is not None:
            el.box = (pose.copy(), el.box[1])
        self._phases.clear()

    def update(self) -> None:
        """Build the broad phase of the enabled elements now (queries otherwise build it when first needed)."""
        self._phase()

    def _phase(self) -> _BroadPhase:
        """The broad phase of the elements enabled now, built once per set of disabled names."""
        phase = self._phases.get(self._disabled)
        if phase is not None:
            return phase
        enabled = [e for e in self.elements.values() if e.name not in self._disabled]
        managers = {}
        for cat in CATEGORIES:
            objs = [e.obj for e in enabled if e.category == cat]
            if objs:
                managers[cat] = _manager(objs)
        phase = _BroadPhase(
            managers,
            _manager([e.obj for e in enabled]) if enabled else None,
            np.array([e.lo for e in enabled]).reshape(-1, 3),
            np.array([e.hi for e in enabled]).reshape(-1, 3),
            {e.name: k for k, e in enumerate(enabled)},
        )
        self._phases[self._disabled] = phase
        return phase

    # -- scoped state -------------------------------------------------------------------------------------------
    @contextmanager
    def without(self, *names: str) -> Iterator[None]:
        """Leave the named elements (unknown names are ignored) out of every query inside the block."""
        before = self._disabled
        self._disabled = before | {n for n in names if n in self.elements}
        try:
            yield
        finally:
            self._disabled = before

    @contextmanager
    def holding(self, name: str, mesh: trimesh.Trimesh, tcp_from_object: ArrayLike) -> Iterator[None]:
        """Inside the block the tool holds `mesh` rigidly at `tcp_from_object` (4, 4) (after a grasp): it moves
        with the TCP in arm and config queries, and the world element `name` (the object where it lay) is left out."""
        held = _Held(
            name,
            fcl.CollisionObject(bvh_for(mesh), fcl.Transform()),
            np.asarray(tcp_from_object, dtype=np.float64),
            held_radius(mesh),
        )
        before = self._held
        self._held = held
        try:
            with self.without(name):
                yield
        finally:
            self._held = before

    @contextmanager
    def empty_handed(self) -> Iterator[None]:
        """Inside the block the tool holds nothing (the object stays out of the world if it was held)."""
        before = self._held
        self._held = None
        try:
            yield
        finally:
            self._held = before

    @property
    def held_name(self) -> str:
        """Name of the held object, '' when the tool is empty."""
        return self._held.name if self._held else ""

    def is_enabled(self, name: str) -> bool:
        """Whether the element `name` exists and takes part in queries now."""
        return name in self.elements and name not in self._disabled

    # -- movers -------------------------------------------------------------------------------------------------
    def set_arm(self, arm: ArmModel) -> None:
        """Use `arm`'s link shapes (capsules, boxes, spheres, cylinders) as moving collision objects."""
        n = len(arm.shapes)
        mask = np.zeros((n, n), dtype=bool)
        for i in range(n):
            for j in range(i + 1, n):
                a, b = sorted((arm.shapes[i].joint, arm.shapes[j].joint))
                mask[i, j] = a != b and (a, b) not in arm.adjacent
        self.arm = arm
        self._arm = _ArmShapes(
            tuple(fcl.CollisionObject(_geometry(s.kind, s.size), fcl.Transform()) for s in arm.shapes),
            np.array([bounding_radius(s.kind, s.size) for s in arm.shapes]),
            mask,
            np.array([i for i, s in enumerate(arm.shapes) if s.joint < 3], dtype=np.int64),
            np.array([s.joint for s in arm.shapes], dtype=np.int64),
            np.stack([np.asarray(s.link_from_shape, dtype=np.float64)[:3, 3] for s in arm.shapes]),
        )

    def set_tool(self, tool: ToolModel, clearance_m: float = 0.01, noise_margin_m: float = 0.002) -> None:
        """Use `tool`'s shapes as moving collision objects; a copy grown by `clearance_m` on every side answers
        clearance questions (`check_tool(..., inflated=True)`) without distance queries, and one grown by
        `noise_margin_m` keeps the tool that far from neighbours despite fitted-pose noise
        (`check_tool(..., margin=True)`). Jaw fingers grow outwards only (their inner faces stay put)."""
        radii = np.array([bounding_radius(s.kind, s.size) for s in tool.shapes])
        self.tool = tool
        self._tools = {
            variant: _ToolShapes(
                tuple(o for o, *_ in grown), np.stack([g[1] for g in grown]), radii + np.sqrt(3) * by_m
            )
            for variant, by_m in (("exact", 0.0), ("inflated", clearance_m), ("margin", noise_margin_m))
            for grown in [_grown_tool(tool, by_m)]
        }
        self._tool_moves = np.array([float(s.moves) for s in tool.shapes])
        self._tool_moving = bool(self._tool_moves.any())
        self._tool_finger_half = np.array([s.size[0] / 2.0 if s.moves else 0.0 for s in tool.shapes])

    # -- queries ------------------------------------------------------------------------------------------------
    def tool_box_hits(self, world_from_tcp: FloatArray, opening_m: FloatArray, category: str = "cell") -> FloatArray:
        """(N,) bool: where a box of the tool, at poses (N, 4, 4) and openings (N,), overlaps a box element of
        `category` (exact box-box test in numpy; the tool's non-box shapes are left to `check_tool`). A vectorised
        early exit in front of the fcl checks."""
        if self.tool is None:
            raise InputError("tool_box_hits needs a tool: call set_tool first")
        els = [
            e
            for e in self.elements.values()
            if e.category == category and e.box is not None and e.name not in self._disabled
        ]
        poses = np.asarray(world_from_tcp, dtype=np.float64).reshape(-1, 4, 4)
        n = len(poses)
        hits = np.zeros(n, dtype=bool)
        if not els:
            return hits
        boxes = [e.box for e in els if e.box is not None]
        bc = np.stack([b[0][:3, 3] for b in boxes])
        br = np.stack([b[0][:3, :3] for b in boxes])
        bh = np.stack([b[1] for b in boxes])
        openings = np.broadcast_to(np.asarray(opening_m, dtype=np.float64), (n,))
        box_from_world = np.swapaxes(br, 1, 2)[None]  # (1, B, 3, 3)
        aligned = bool(np.all(br == np.eye(3)))
        for s in self.tool.shapes:
            if s.kind != "box":
                continue
            rows = np.flatnonzero(~hits)  # poses already hit need no further shape
            if len(rows) == 0:
                break
            at = poses if len(rows) == n else poses[rows]
            shape = np.asarray(s.tcp_from_shape, dtype=np.float64)
            if s.moves:
                local = np.broadcast_to(shape, (len(rows), 4, 4)).copy()
                local[:, 0, 3] += s.moves * (openings[rows] / 2.0 + s.size[0] / 2.0)
                world = at @ local
            else:  # one shape pose for every row: the same products, broadcast
                world = at @ shape
            half = np.asarray(s.size, dtype=np.float64) / 2.0
            # the separating-axis tests along each cell box's own axes first (the tool box's extent there against
            # the centres' distance, 1 nm of slack for rounding): the full test only runs on pairs they cannot part
            if aligned:  # boxes along the world axes (the usual cell): the tool box's world AABB, both tests compiled
                hits[rows[aligned_box_hits(world, half, bc, br, bh)]] = True
                continue
            d = (box_from_world @ (world[:, None, :3, 3] - bc[None])[..., None])[..., 0]  # (R, B, 3) box frames
            ext = (np.abs(box_from_world @ world[:, None, :3, :3]) * half).sum(axis=3)
            ii, bb = np.nonzero(np.all(np.abs(d) <= bh[None] + ext + 1e-9, axis=2))
            if len(ii) == 0:
                continue
            over = obb_overlap_pairs(world[ii, :3, 3], world[ii, :3, :3], half, bc[bb], br[bb], bh[bb])
            hits[rows[ii[over]]] = True
        return hits

    def near(self, centres: FloatArray, radii: FloatArray) -> BoolArray:
        """(K,) bool: which bounding spheres (centres (K, 3), radii (K,) m) touch some enabled element's AABB.
        A cheap broad phase in front of fcl (`collision.spheres`): shapes far from everything skip the fcl call."""
        phase = self._phase()
        if len(phase.lo) == 0:
            return np.zeros(len(centres), dtype=bool)
        return spheres_near_boxes(centres, radii, phase.lo, phase.hi)  # compiled, the numpy pass's arithmetic

    def _query(self, obj: fcl.CollisionObject, skip: Iterable[str] = ()) -> str:
        """Category hit by `obj` ('' when free), checking categories in order."""
        phase = self._phase()
        if not skip:
            # one broad phase over everything; only a hit pays for finding its category
            if phase.everything is None:
                return ""
            cdata = fcl.CollisionData(_REQUEST, fcl.CollisionResult())
            phase.everything.collide(obj, cdata, _first_contact)
            self.n_checks += 1
            if not cdata.result.is_collision:
                return ""
        for cat, mgr in phase.managers.items():
            if cat in skip:
                continue
            cdata = fcl.CollisionData(_REQUEST, fcl.CollisionResult())
            mgr.collide(obj, cdata, _first_contact)
            self.n_checks += 1
            if cdata.result.is_collision:
                return cat
        return ""

    def _pose_tool(
        self,
        world_from_tcp: FloatArray,
        opening_m: float,
        inflated: bool = False,
        only_near: bool = False,
        margin: bool = False,
    ) -> list[fcl.CollisionObject]:
        """Pose all tool shapes (self-collision reads them); return those to query: with `only_near`, only shapes
        whose bounding sphere touches some element's box. `inflated` / `margin`: the grown copies instead."""
        shapes = self._tools["inflated" if inflated else "margin" if margin else "exact"]
        objs, radii, local = shapes.objects, shapes.radii, shapes.tcp_from_shape
        grown = inflated or margin
        if not grown:
            self._last_opening = opening_m
        if self._tool_moving:
            local = local.copy()
            local[:, 0, 3] += self._tool_moves * (opening_m / 2.0 + self._tool_finger_half)
        poses = world_from_tcp @ local
        centres = poses[:, :3, 3]
        rotations = poses[:, :3, :3]
        if not grown:
            self._tool_centres = centres
        for i, obj in enumerate(objs):
            obj.setTransform(fcl.Transform(rotations[i], centres[i]))
        if not only_near:
            return list(objs)
        return [obj for obj, k in zip(objs, self.near(centres, radii).tolist(), strict=True) if k]

    def check_tool(
        self,
        world_from_tcp: ArrayLike,
        opening_m: float = 0.0,
        skip: Sequence[str] = (),
        inflated: bool = False,
        margin: bool = False,
    ) -> Hit | None:
        """First hit of the tool at `world_from_tcp` (4, 4) and jaw opening `opening_m` (m), or None; `inflated`
        uses the tool grown by the clearance given to `set_tool` (a hit then means 'closer than the clearance'),
        `margin` the one grown by the noise margin."""
        if self.tool is None:
            raise InputError("check_tool needs a tool: call set_tool first")
        pose = np.asarray(world_from_tcp, dtype=np.float64)
        for obj in self._pose_tool(pose, opening_m, inflated, False, margin):
            what = self._query(obj, skip)
            if what:
                return Hit("tool", what)
        return None

    def check_held(self, world_from_tcp: ArrayLike, skip: Sequence[str] = ()) -> Hit | None:
        """First hit of the held object when the TCP is at `world_from_tcp`, or None (nothing held: None)."""
        held = self._held
        if held is None:
            return None
        pose = np.asarray(world_from_tcp, dtype=np.float64) @ held.tcp_from_object
        held.obj.setTransform(_tf(pose))
        if not self.near(pose[None, :3, 3], np.array([held.radius]))[0]:
            return None
        what = self._query(held.obj, skip)
        return Hit("held", what) if what else None

    def check_arm(self, q: ArrayLike, skip: Sequence[str] = (), self_collision: bool = True) -> Hit | None:
        """First hit of the arm links at joint angles q (6,) rad against the world, then self-collision."""
        if self.arm is None:
            raise InputError("check_arm needs an arm: call set_arm first")
        return self._check_arm(q, self.arm.frames(q), skip, self_collision)

    def _check_arm(self, q: ArrayLike, frames: FloatArray, skip: Sequence[str], self_collision: bool) -> Hit | None:
        if self.arm is None or self._arm is None:
            raise InputError("check_arm needs an arm: call set_arm first")
        poses = self.arm.shape_poses(q, frames)
        centres = np.array([p[:3, 3] for p in poses])
        near = self.near(centres, self._arm.radii)
        near[0] = False  # the base stands on its mount: never checked against the cell
        posed = np.zeros(len(poses), dtype=bool)
        for i in np.flatnonzero(near):
            self._arm.objects[i].setTransform(_tf(poses[i]))
            posed[i] = True
            what = self._query(self._arm.objects[i], skip)
            if what:
                return Hit("arm", what, self.arm.shapes[i].link)
        if self_collision:
            if self.tool is not None and not self._tool_posed_by_config:
                # pose the tool (last opening) and held object at this configuration for the arm-vs-tool pairs
                world_from_tcp = frames[6] @ self.tool.flange_from_tcp
                self._pose_tool(world_from_tcp, self._last_opening)
                if self._held is not None:
                    self._held.obj.setTransform(_tf(world_from_tcp @ self._held.tcp_from_object))
            return self._self_collision(poses, centres, posed)
        return None

    def _self_collision(self, poses: list[FloatArray], centres: FloatArray, posed: FloatArray) -> Hit | None:
        """Non-adjacent link pairs, and the tool / held object against base, shoulder and upper arm; pairs whose
        bounding spheres are apart are skipped without calling fcl."""
        if self.arm is None or self._arm is None:
            return None
        arm = self._arm
        shapes = self.arm.shapes
        r = arm.radii
        gap = np.linalg.norm(centres[:, None] - centres[None], axis=-1) - (r[:, None] + r[None])

        def obj(i: int) -> fcl.CollisionObject:
            if not posed[i]:
                arm.objects[i].setTransform(_tf(poses[i]))
                posed[i] = True
            return arm.objects[i]

        for i, j in zip(*np.nonzero((gap <= 0) & arm.pair_mask), strict=True):
            if fcl.collide(obj(int(i)), obj(int(j)), _REQUEST, fcl.CollisionResult()):
                return Hit("self", "arm", f"{shapes[i].link}-{shapes[j].link}")
        exact = self._tools["exact"]
        movers = list(exact.objects)
        mover_centres = list(self._tool_centres)
        mover_radii = list(exact.radii)
        if self._held is not None:
            movers.append(self._held.obj)
            mover_centres.append(self._held.obj.getTranslation())
            mover_radii.append(self._held.radius)
        low = arm.low_links
        mc = np.asarray(mover_centres).reshape(-1, 3)
        gap_m = np.linalg.norm(centres[low][:, None] - mc[None], axis=-1) - (r[low][:, None] + np.asarray(mover_radii))
        for a, m in zip(*np.nonzero(gap_m <= 0), strict=True):
            i = int(low[a])
            if fcl.collide(obj(i), movers[int(m)], _REQUEST, fcl.CollisionResult()):
                return Hit("self", "tool", shapes[i].link)
        return None

    def check_config(
        self,
        q: ArrayLike,
        opening_m: float = 0.0,
        skip: Sequence[str] = (),
        skip_tool: Sequence[str] = (),
        skip_held: Sequence[str] = (),
    ) -> Hit | None:
        """Arm, tool (at `opening_m`) and held object at configuration q (6,): the first hit or None.

        `skip` leaves categories out for every part; `skip_tool` / `skip_held` only for the tool / held object
        (for example the clutter the gripper is allowed to push through at contact)."""
        if self.arm is None or self.tool is None:
            raise InputError("check_config needs set_arm and set_tool first")
        frames = self.arm.frames(q)
        world_from_tcp = frames[6] @ self.tool.flange_from_tcp
        hit = self.check_tool(world_from_tcp, opening_m, tuple(skip) + tuple(skip_tool))
        if hit is None:
            hit = self.check_held(world_from_tcp, tuple(skip) + tuple(skip_held))
        if hit is None:
            self._tool_posed_by_config = True
            try:
                hit = self._check_arm(q, frames, skip, True)
            finally:
                self._tool_posed_by_config = False
        return hit

    def configs_clear(
        self,
        qs: ArrayLike,
        opening_m: float = 0.0,
        held_rows: BoolArray | None = None,
        tcp_from_held: ArrayLike | None = None,
        held_name: str = "",
        held_radius: float = 0.0,
    ) -> BoolArray:
        """(K,) bool for configurations qs (K, 6) rad: True where bounding spheres alone prove `check_config(q,
        opening_m)` finds nothing (no arm, tool or held-object sphere touches an enabled element's box, no
        self-collision pair's spheres touch). False means 'not proven': run `check_config`. One vectorised pass, so
        dense edge checks pay fcl only near contacts.

        held_rows (K,) bool: those configurations are judged as inside `holding(held_name, mesh, tcp_from_held)`
        (an object of bounding radius `held_radius` m about its origin at `tcp_from_held` (4, 4), the element
        `held_name` left out), the others as the world stands, which must then hold nothing: an empty-handed
        approach and a held lift in one pass."""
        if self.arm is None or self.tool is None or self._arm is None:
            raise InputError("configs_clear needs set_arm and set_tool first")
        q = np.asarray(qs, dtype=np.float64).reshape(-1, 6)
        k = len(q)
        if k == 0:
            return np.zeros(0, dtype=bool)
        phase = self._phase()
        exact = self._tools["exact"]
        frames = self.arm.frames(q)  # (K, 7, 4, 4)
        f = frames[:, self._arm.joints]  # (K, S, 4, 4)
        arm_c = np.einsum("ksij,sj->ksi", f[..., :3, :3], self._arm.local_centres) + f[..., :3, 3]
        world_from_tcp = frames[:, 6] @ self.tool.flange_from_tcp
        local = exact.tcp_from_shape.copy()
        local[:, 0, 3] += self._tool_moves * (opening_m / 2.0 + self._tool_finger_half)
        tool_c = np.einsum("kij,sj->ksi", world_from_tcp[:, :3, :3], local[:, :3, 3]) + world_from_tcp[:, None, :3, 3]
        movers_c = [arm_c[:, 1:], tool_c]
        movers_r = [self._arm.radii[1:], exact.radii]
        held_radii: FloatArray | None = None  # (K,) per configuration, when some hold and some do not
        if held_rows is not None:
            if self._held is not None:
                raise InputError("configs_clear with held_rows needs an empty-handed world")
            rows = np.asarray(held_rows, dtype=bool).reshape(k)
            held = world_from_tcp @ np.asarray(tcp_from_held, dtype=np.float64)
            # rows without the object: a point at the first tool sphere's centre, which that sphere already covers
            movers_c.append(np.where(rows[:, None], held[:, :3, 3], tool_c[:, 0])[:, None])
            held_radii = np.where(rows, float(held_radius), 0.0)
            movers_r.append(np.zeros(1))
        elif self._held is not None:
            held = world_from_tcp @ self._held.tcp_from_object
            movers_c.append(held[:, None, :3, 3])
            movers_r.append(np.array([self._held.radius]))
        centres = np.concatenate(movers_c, axis=1)  # (K, M, 3)
        radii = np.broadcast_to(np.concatenate(movers_r), (k, centres.shape[1])).copy()  # (K, M)
        if held_radii is not None:
            radii[:, -1] = held_radii
        # the spheres against the enabled elements' boxes, then the arm's spheres against each other and against the
        # tool's and the held object's (collision.spheres: compiled, the numpy passes' arithmetic)
        held_index = -1
        if held_rows is not None and held_name in phase.index:
            held_index = phase.index[held_name]
        rows_held = np.zeros(k, dtype=bool) if held_rows is None else np.asarray(held_rows, dtype=bool).reshape(k)
        clear = spheres_off_boxes(centres, radii, phase.lo, phase.hi, rows_held, held_index)
        r = self._arm.radii
        extra_c = np.concatenate(movers_c[1:], axis=1)
        extra_r = radii[:, len(r) - 1 :]  # (K, tool and held)
        clear &= spheres_apart(arm_c, r, self._arm.pair_mask, self._arm.low_links, extra_c, extra_r)
        return clear

    def which(self, world_from_tcp: ArrayLike, opening_m: float = 0.0) -> list[str]:
        """Names of the enabled elements the tool touches at `world_from_tcp` (for diagnostics; slower)."""
        self._pose_tool(np.asarray(world_from_tcp, dtype=np.float64), opening_m)
        req = fcl.CollisionRequest(num_max_contacts=1)
        names = []
        for el in self.elements.values():
            if el.name in self._disabled:
                continue
            for obj in self._tools["exact"].objects:
                if fcl.collide(obj, el.obj, req, fcl.CollisionResult()):
                    names.append(el.name)
                    break
        return names

    def tool_distance(self, world_from_tcp: ArrayLike, opening_m: float = 0.0) -> float:
        """Smallest distance (m) from the tool to any enabled element (0 when touching). Slow: reports only."""
        phase = self._phase()
        self._pose_tool(np.asarray(world_from_tcp, dtype=np.float64), opening_m)
        best = np.inf
        for mgr in phase.managers.values():
            for obj in self._tools["exact"].objects:
                ddata = fcl.DistanceData(fcl.DistanceRequest(), fcl.DistanceResult())
                mgr.distance(obj, ddata, fcl.defaultDistanceCallback)
                best = min(best, max(float(ddata.result.min_distance), 0.0))
        return float(best)
