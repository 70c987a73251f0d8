"""Grasp candidates in the world: template-annotated pick frames (expanded about free symmetry axes, over the
tilt cone and through the template's symmetries) plus automatic synthesis, for one fitted object and one tool;
primitive templates for objects that matched no template."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy.spatial import ConvexHull, QhullError

from normpos_grasp.geometry.transforms import rotation_from_rotvec, transform_points
from normpos_grasp.grasp.synthesis import SynthesisOptions, _cylinder_axis, _obb, synthesize, tcp_frame
from normpos_grasp.records.grasp import GraspCandidate
from normpos_grasp.records.normpos import NormPosition
from normpos_grasp.records.template import GraspAnnotation, Symmetry, Template
from normpos_grasp.typing import FloatArray

logger = logging.getLogger(__name__)

#: most elements of a discrete symmetry group built by closing a template's listed transforms under products
MAX_GROUP = 120
#: (m, rad) within which a symmetric image of a synthesized grasp counts as one already sampled
SYNTHESIZED_TOLERANCE = (5e-3, float(np.deg2rad(15.0)))


@dataclass(frozen=True)
class CandidateOptions:
    """free_axis_steps: rotations sampled about an annotation's free axis. tilt_steps: directions sampled on the
    tilt cone's rim (0: nominal only). synthesize: 'missing' (only when a template has no annotations), 'always'
    or 'never'. synthesis: settings of automatic synthesis. snap_to_vertical: for parts with a continuous symmetry
    (cylinders, spheres, annotated free axes) also offer each grasp rotated about the symmetry axis so that it
    approaches as close to straight down as the symmetry allows (an equivalent grasp, usually the reachable one).
    vertical_prism: for prism-like parts (bars, boxes, cylinders) lying tilted (leaning on a neighbour), also offer
    straight-down pinches closing horizontally across the part's long axis (`vertical_prism_grasps`).
    symmetric: carry every grasp through the template's symmetries (`symmetric_grasps`), so a part fitted in any
    equivalent pose keeps all of its grasps: annotated grasps through the discrete group combined with each
    continuous axis sampled in `symmetry_steps` turns, synthesized ones through the discrete group (synthesis
    already samples around continuous axes; an image within `SYNTHESIZED_TOLERANCE` of a sampled grasp is dropped).
    level_within_rad: grasps approaching within this angle of straight down (but not straight down) are also offered
    levelled (`level_candidates`, `@level` in the id): a plate fitted 2 degrees off flat keeps its fingertips level
    above the floor; 0: off."""

    free_axis_steps: int = 8
    tilt_steps: int = 4
    synthesize: str = "missing"
    synthesis: SynthesisOptions = SynthesisOptions()
    snap_to_vertical: bool = True
    vertical_prism: bool = True
    symmetric: bool = True
    symmetry_steps: int = 4
    level_within_rad: float = float(np.deg2rad(8.0))


def expand_annotation(g: GraspAnnotation, options: CandidateOptions) -> list[tuple[str, FloatArray]]:
    """(id, object_from_tcp) variants of an annotation: rotations about its free axis and tilts in its cone."""
    base = np.asarray(g.object_from_tcp, dtype=np.float64)
    poses = [(g.id, base)]
    if g.free_axis is not None and options.free_axis_steps > 1:
        axis = np.asarray(g.free_axis, dtype=np.float64)
        axis = axis / np.linalg.norm(axis)
        poses = []
        for k in range(options.free_axis_steps):
            rot = np.eye(4)
            rot[:3, :3] = rotation_from_rotvec(axis * 2 * np.pi * k / options.free_axis_steps)
            poses.append((f"{g.id}@r{k}", rot @ base))  # about the object-frame axis through the origin
    if g.tilt_cone_rad > 0 and options.tilt_steps > 0:
        tilted = []
        for gid, pose in poses:
            tilted.append((gid, pose))
            for k in range(options.tilt_steps):
                ang = 2 * np.pi * k / options.tilt_steps
                local_axis = np.array([np.cos(ang), np.sin(ang), 0.0])
                tilt = np.eye(4)
                tilt[:3, :3] = rotation_from_rotvec(local_axis * g.tilt_cone_rad)
                tilted.append((f"{gid}@t{k}", pose @ tilt))  # about the TCP origin
        poses = tilted
    return poses


@lru_cache(maxsize=256)
def _synthesize_cached(
    template: Template, kinds: tuple[str, ...], options: SynthesisOptions
) -> tuple[GraspAnnotation, ...]:
    """Synthesis depends only on the template (by identity), the tool kinds and the options: cache it."""
    return tuple(synthesize(template, kinds, options))


def symmetry_group(symmetry: Symmetry, continuous_steps: int = 1) -> FloatArray:
    """(M, 4, 4) object_from_object transforms mapping the part onto itself, identity first: the discrete transforms
    closed under products (a list of generators, or a BOP `symmetries_discrete` list, gives the whole group; at
    most `MAX_GROUP` elements), each combined with every continuous axis sampled in `continuous_steps` turns
    (1: discrete only)."""
    gens = np.asarray([np.asarray(t, dtype=np.float64) for t in symmetry.discrete]).reshape(-1, 4, 4)
    group = np.eye(4)[None]
    frontier = gens
    while len(frontier) and len(group) <= MAX_GROUP:
        fresh: list[FloatArray] = []
        for t in frontier:  # keep products not yet in the group (nor already among the fresh ones)
            known = group if not fresh else np.concatenate([group, np.stack(fresh)])
            if not np.any(np.abs(known - t).max(axis=(1, 2)) < 1e-6):
                fresh.append(t)
        if not fresh:
            break
        new = np.stack(fresh)
        group = np.concatenate([group, new])
        frontier = np.einsum("aij,bjk->abik", new, gens).reshape(-1, 4, 4)
    if len(group) > MAX_GROUP:
        logger.warning("symmetry group has over %d elements; using the first %d", MAX_GROUP, MAX_GROUP)
        group = group[:MAX_GROUP]
    closed = Symmetry(continuous=symmetry.continuous, discrete=tuple(group[1:]))
    return closed.transforms(continuous_steps=max(int(continuous_steps), 1))


def _same_grasp(pose: FloatArray, kept: FloatArray, suction: bool, pos_tol: float, cos_tol: float) -> bool:
    """Whether `pose` (4, 4) is the same grasp as any of `kept` (K, 4, 4): TCP within `pos_tol` m, the same
    approach axis within the angle of `cos_tol` and, for a parallel gripper, the same closing line (jaws closing
    along x or -x touch the same contacts); for suction the approach alone counts (the cup is round)."""
    near = np.linalg.norm(kept[:, :3, 3] - pose[:3, 3], axis=1) <= pos_tol
    if not near.any():
        return False
    same = kept[near, :3, 2] @ pose[:3, 2] >= cos_tol
    if not suction:
        same &= np.abs(kept[near, :3, 0] @ pose[:3, 0]) >= cos_tol
    return bool(same.any())


def symmetric_grasps(
    grasps: list[tuple[GraspAnnotation, str, str, FloatArray]],
    transforms: FloatArray,
    pos_tol_m: float = 1e-3,
    angle_tol_rad: float = np.deg2rad(2.0),
) -> list[tuple[GraspAnnotation, str, str, FloatArray]]:
    """`grasps` (annotation, source, id, object_from_tcp) carried through the symmetry `transforms` (M, 4, 4),
    identity first: the given grasps, then each image `transforms[k] @ object_from_tcp` (id suffixed `@s<k>`)
    that is the same grasp as none kept before it (`_same_grasp`: TCP within `pos_tol_m`, axes within
    `angle_tol_rad`). The given grasps are all kept."""
    if len(transforms) <= 1 or not grasps:
        return list(grasps)
    out = list(grasps)
    cos_tol = float(np.cos(angle_tol_rad))
    kept = {scheme: [p for g, _, _, p in grasps if g.scheme == scheme] for scheme in {g.scheme for g, *_ in grasps}}
    stacks = {scheme: np.stack(poses) for scheme, poses in kept.items()}
    for k in range(1, len(transforms)):
        for g, source, gid, pose in grasps:
            image = transforms[k] @ pose
            if _same_grasp(image, stacks[g.scheme], g.scheme == "suction", pos_tol_m, cos_tol):
                continue
            out.append((g, source, f"{gid}@s{k}", image))
            stacks[g.scheme] = np.concatenate([stacks[g.scheme], image[None]])
    return out


def object_grasps(
    template: Template, kinds: tuple[str, ...], options: CandidateOptions
) -> list[tuple[GraspAnnotation, str, str, FloatArray]]:
    """(annotation, source, id, object_from_tcp) for every grasp of `template` usable by tool kinds `kinds`,
    carried through the template's symmetries when `options.symmetric`."""
    annotated = [g for g in template.grasps if g.scheme in kinds]
    out = [(g, "annotated", gid, pose) for g in annotated for gid, pose in expand_annotation(g, options)]
    sym = template.symmetry if options.symmetric else Symmetry()
    if out and sym.is_symmetric:
        out = symmetric_grasps(out, symmetry_group(sym, options.symmetry_steps))
    if options.synthesize == "always" or (options.synthesize == "missing" and not annotated):
        synthesized = [
            (g, "synthesized", g.id, np.asarray(g.object_from_tcp, dtype=np.float64))
            for g in _synthesize_cached(template, kinds, options.synthesis)
        ]
        if synthesized and sym.discrete:  # samples of a continuum: an image near a sample adds nothing
            synthesized = symmetric_grasps(synthesized, symmetry_group(sym, 1), *SYNTHESIZED_TOLERANCE)
        out.extend(synthesized)
    return out


@lru_cache(maxsize=256)
def _object_grasps_cached(
    template: Template, kinds: tuple[str, ...], options: CandidateOptions
) -> tuple[tuple[tuple[str, str, str, float, float, float, float, float], ...], FloatArray]:
    """`object_grasps` as the candidate fields that do not depend on the pose (id, source, scheme, opening_m,
    approach_m, retreat_m, quality, priority) and their object_from_tcp stacked (G, 4, 4), once per template (by
    identity), tool kinds and options (read-only: callers must not modify them)."""
    grasps = object_grasps(template, kinds, options)
    poses = np.stack([pose for *_, pose in grasps]) if grasps else np.zeros((0, 4, 4))
    poses.setflags(write=False)
    fields = []
    for g, source, gid, _ in grasps:
        synthesized = source == "synthesized"
        quality = min(max(float(g.priority), 0.0), 1.0) if synthesized else 1.0
        priority = 0.0 if synthesized else float(g.priority)
        opening, approach, retreat = float(g.opening_m), float(g.approach_m), float(g.retreat_m)
        fields.append((gid, source, g.scheme, opening, approach, retreat, quality, priority))
    return tuple(fields), poses


def _symmetry_axes(template: Template) -> list[tuple[FloatArray, FloatArray]]:
    """(axis (3,), point (3,)) of the template's continuous symmetry axes, object frame; for a 'cylinder' or
    'ring' or 'sphere' without declared symmetry the axis is inferred from the mesh."""
    axes = [
        (np.asarray(a, dtype=np.float64) / np.linalg.norm(a), np.asarray(p, dtype=np.float64))
        for a, p in template.symmetry.continuous
    ]
    if axes:
        return axes
    if template.shape in ("cylinder", "ring"):
        axis, centre, _, _ = _cylinder_axis(template)
        return [(axis, centre)]
    if template.shape == "sphere":
        centre = np.asarray(template.mesh.bounds, dtype=np.float64).mean(axis=0)
        return [(np.eye(3)[i], centre) for i in range(3)]
    return []


def symmetry_axes_world(template: Template, world_from_object: FloatArray) -> list[tuple[FloatArray, FloatArray]]:
    """(unit axis (3,), point (3,)) of the template's continuous symmetry axes (`_symmetry_axes`) in the world, for
    the part posed at `world_from_object` (4, 4)."""
    rot, t = world_from_object[:3, :3], world_from_object[:3, 3]
    return [(rot @ a, rot @ p + t) for a, p in _symmetry_axes(template)]


def _about(axis: FloatArray, point: FloatArray, angle: float) -> FloatArray:
    """(4, 4) rotation by `angle` about the line through `point` along unit `axis` (Rodrigues, no input checks:
    this runs once per candidate)."""
    x, y, z = axis
    k = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    pose = np.eye(4)
    pose[:3, :3] = np.eye(3) + np.sin(angle) * k + (1.0 - np.cos(angle)) * (k @ k)
    pose[:3, 3] = point - pose[:3, :3] @ point
    return pose


def snap_down(world_from_tcp: FloatArray, axes_world: list[tuple[FloatArray, FloatArray]]) -> FloatArray | None:
    """The grasp rotated about the object's symmetry axes (world frame) so that its approach points as far down
    as the symmetry allows; None when it already does (within 3 degrees) or no rotation helps."""
    pose = world_from_tcp.copy()
    down = np.array([0.0, 0.0, -1.0])
    if len(axes_world) >= 2:  # sphere-like: any rotation about the centre
        a = pose[:3, 2]
        angle = float(np.arccos(np.clip(a @ down, -1.0, 1.0)))
        if angle < np.deg2rad(3):
            return None
        axis = np.cross(a, down)
        if np.linalg.norm(axis) < 1e-9:
            axis = np.array([1.0, 0.0, 0.0])
        return _about(axis / np.linalg.norm(axis), axes_world[0][1], angle) @ pose
    axis, point = axes_world[0]
    a = pose[:3, 2]
    a_perp = a - axis * (a @ axis)
    t = down - axis * (down @ axis)
    if np.linalg.norm(a_perp) < 1e-6 or np.linalg.norm(t) < 1e-6:
        return None
    u, t = a_perp / np.linalg.norm(a_perp), t / np.linalg.norm(t)
    angle = float(np.arctan2(np.cross(u, t) @ axis, u @ t))
    if abs(angle) < np.deg2rad(3):
        return None
    return _about(axis, point, angle) @ pose


def snap_down_batch(
    world_from_tcp: FloatArray, axes_world: list[tuple[FloatArray, FloatArray]]
) -> tuple[FloatArray, FloatArray]:
    """`snap_down` for poses (N, 4, 4) at once: (snapped poses (N, 4, 4), (N,) bool where a snapped pose exists)."""
    poses = np.asarray(world_from_tcp, dtype=np.float64)
    n = len(poses)
    out = poses.copy()
    if n == 0 or not axes_world:
        return out, np.zeros(n, dtype=bool)
    down = np.array([0.0, 0.0, -1.0])
    a = poses[:, :3, 2]
    if len(axes_world) >= 2:  # sphere-like: rotate about a @ down through the centre
        point = axes_world[0][1]
        angle = np.arccos(np.clip(a @ down, -1.0, 1.0))
        axis = np.cross(a, down)
        norm = np.linalg.norm(axis, axis=1)
        axis = np.where(norm[:, None] < 1e-9, np.array([1.0, 0.0, 0.0]), axis / np.maximum(norm, 1e-12)[:, None])
        ok = angle >= np.deg2rad(3)
    else:
        axis1, point = axes_world[0]
        a_perp = a - axis1[None] * (a @ axis1)[:, None]
        t = down - axis1 * (down @ axis1)
        na, nt = np.linalg.norm(a_perp, axis=1), float(np.linalg.norm(t))
        if nt < 1e-6:
            return out, np.zeros(n, dtype=bool)
        u = a_perp / np.maximum(na, 1e-12)[:, None]
        t = t / nt
        angle = np.arctan2(np.cross(u, t) @ axis1, u @ t)
        ok = (na >= 1e-6) & (np.abs(angle) >= np.deg2rad(3))
        axis = np.broadcast_to(axis1, (n, 3))
    x, y, z = axis[:, 0], axis[:, 1], axis[:, 2]
    zero = np.zeros(n)
    k = np.stack([np.stack([zero, -z, y], -1), np.stack([z, zero, -x], -1), np.stack([-y, x, zero], -1)], 1)
    rot = np.eye(3)[None] + np.sin(angle)[:, None, None] * k + (1.0 - np.cos(angle))[:, None, None] * (k @ k)
    out[:, :3, :3] = rot @ poses[:, :3, :3]
    out[:, :3, 3] = np.einsum("nij,nj->ni", rot, poses[:, :3, 3] - point) + point
    return out, ok


def _align_closing(
    world_poses: FloatArray, axis_world: tuple[FloatArray, FloatArray], dirs: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """The poses (N, 4, 4) turned about the symmetry axis (unit axis, point) so that their closing axis x points
    along each direction (K, 3) (up to sign): (turned (N, K, 4, 4), valid (N, K) bool). Not valid where the
    approach is not along the axis (within 25 degrees), the direction is along the axis, or the pose already
    closes along it (within 5 degrees)."""
    axis, point = axis_world
    n, k = len(world_poses), len(dirs)
    out = np.repeat(np.asarray(world_poses, dtype=np.float64)[:, None], k, axis=1)
    along = np.abs(world_poses[:, :3, 2] @ axis) > np.cos(np.deg2rad(25))
    t = dirs - np.outer(dirs @ axis, axis)  # (K, 3)
    x = world_poses[:, :3, 0] - np.outer(world_poses[:, :3, 0] @ axis, axis)  # (N, 3)
    nt, nx = np.linalg.norm(t, axis=1), np.linalg.norm(x, axis=1)
    valid = along[:, None] & (nt[None] > 1e-6) & (nx[:, None] > 1e-6)
    if not valid.any():
        return out, valid
    t = t / np.maximum(nt, 1e-12)[:, None]
    x = x / np.maximum(nx, 1e-12)[:, None]
    angle = np.arctan2(np.cross(x[:, None], t[None]) @ axis, x @ t.T)  # (N, K)
    angle = np.where(angle > np.pi / 2, angle - np.pi, np.where(angle < -np.pi / 2, angle + np.pi, angle))
    valid &= np.abs(angle) >= np.deg2rad(5)
    kx = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    rot = (
        np.eye(3) + np.sin(angle)[..., None, None] * kx + (1.0 - np.cos(angle))[..., None, None] * (kx @ kx)
    )  # (N, K, 3, 3)
    out[..., :3, :3] = rot @ out[..., :3, :3]
    out[..., :3, 3] = np.einsum("nkij,nkj->nki", rot, out[..., :3, 3] - point) + point
    del n
    return out, valid


def _long_axis(template: Template) -> tuple[FloatArray, FloatArray, float] | None:
    """(unit long axis (3,), centre (3,), length m) of a prism-like template in its object frame, or None when the
    part has no clear long axis (a cube, a disc, a sphere, an irregular part)."""
    if template.shape == "cylinder":
        axis, centre, r, length = _cylinder_axis(template)
        return (axis, centre, length) if length >= 1.2 * 2 * r else None
    if template.shape not in ("box", "bar"):
        return None
    frame, ext = _obb(template)
    order = np.argsort(ext)[::-1]
    if ext[order[0]] < 1.3 * ext[order[1]]:
        return None
    return frame[:3, order[0]], frame[:3, 3], float(ext[order[0]])


def vertical_prism_grasps(
    template: Template, world_from_object: FloatArray, options: SynthesisOptions, min_tilt_rad: float = np.deg2rad(5)
) -> list[tuple[str, FloatArray, float, float]]:
    """Straight-down parallel pinches for a prism-like part lying tilted: (id, world_from_tcp (4, 4), opening m,
    quality) each.

    The jaws close horizontally, perpendicular to the long axis projected on the horizontal plane; at the centre
    and a quarter of the length off centre on both sides, the part is cut by the vertical plane across that
    projection: the opening is the cut's width along the closing direction plus `clearance_m` on each side, the
    TCP sits mid-width, `options.depth` below the cut's top (never below its mid-height) and, for jaw tips that
    would reach a neighbour or the floor, also 30 % and 20 % of the cut's height below its top. Both jaw orientations
    (half a turn about the approach) are offered. Empty when the part has no clear long axis, the axis is within
    30 degrees of vertical, a box face axis is within `min_tilt_rad` of vertical or a cylinder lies within it of
    flat (the synthesized face grasps then approach straight down already)."""
    found = _long_axis(template)
    if found is None:
        return []
    axis_o, centre_o, length = found
    rot = np.asarray(world_from_object, dtype=np.float64)[:3, :3]
    axis = rot @ axis_o
    centre = rot @ centre_o + world_from_object[:3, 3]
    up = np.array([0.0, 0.0, 1.0])
    horiz = axis - up * axis[2]
    if np.linalg.norm(horiz) < 0.5:  # within 30 degrees of vertical: standing, no horizontal projection
        return []
    if template.shape == "cylinder":
        aligned = abs(axis[2]) < np.sin(min_tilt_rad)  # lying flat: side grasps already come from above
    else:
        frame_rot = rot @ _obb(template)[0][:3, :3]
        aligned = bool(np.any(np.abs(frame_rot[2]) > np.cos(min_tilt_rad)))
    if aligned:
        return []
    horiz /= np.linalg.norm(horiz)
    closing = np.cross(up, horiz)
    verts = transform_points(world_from_object, np.asarray(template.mesh.vertices, dtype=np.float64))
    faces = np.asarray(template.mesh.faces)
    out: list[tuple[str, FloatArray, float, float]] = []
    for k, frac in enumerate((0.0, -0.25, 0.25)):
        origin = centre + axis * frac * length
        pts = _plane_cut(verts, faces, origin, horiz)
        if len(pts) < 3:
            continue
        cut = np.column_stack([(pts - origin) @ closing, pts[:, 2]])
        top, bottom = float(pts[:, 2].max()), float(pts[:, 2].min())
        height = top - bottom
        if height < 1e-3:
            continue
        depths = {round(min(options.depth(height), height / 2.0), 6), round(0.3 * height, 6), round(0.2 * height, 6)}
        outline = _cut_outline(cut)
        for d_idx, depth in enumerate(sorted(depths, reverse=True)):
            z_tcp = top - depth
            # everything of the cut above the jaw tips must fit between the open jaws
            lo, hi = _extent_above(cut, z_tcp - options.finger_tip_m, outline)
            width = hi - lo
            if width < 1e-3:
                continue
            pos = origin + closing * (hi + lo) / 2.0
            pos[2] = z_tcp
            opening = width + 2 * options.clearance_m
            quality = 0.95 - 0.1 * abs(frac) - 0.05 * d_idx
            for sign in (1.0, -1.0):
                pose = tcp_frame(-up, sign * closing, pos)
                out.append((f"vert_prism_{k}_d{d_idx}{'+' if sign > 0 else '-'}", pose, opening, quality))
    return out


def _cut_outline(cut: FloatArray) -> tuple[FloatArray, FloatArray | None]:
    """The distinct points of a 2D cut (M, 2) (rounded to 1e-9) and its convex hull's ring (None under 3 points)."""
    pts = np.unique(np.round(cut, 9), axis=0)
    if len(pts) < 3:
        return pts, None
    try:
        return pts, pts[ConvexHull(pts).vertices]
    except QhullError:  # collinear cut: its points are its own outline
        return pts, pts


def _extent_above(
    cut: FloatArray, z_min: float, outline: tuple[FloatArray, FloatArray | None] | None = None
) -> tuple[float, float]:
    """(low, high) along the first column of the convex hull of 2D points `cut` (M, 2) (across, height), keeping
    only the part of the hull at height >= `z_min` (its edges cut at that height); the whole hull when none is.
    outline: `_cut_outline(cut)` when already computed (one hull for several heights)."""
    pts, ring = _cut_outline(cut) if outline is None else outline
    keep = [pts[pts[:, 1] >= z_min, 0]]
    if ring is not None:
        a, b = ring, np.roll(ring, -1, axis=0)
        crosses = (a[:, 1] - z_min) * (b[:, 1] - z_min) < 0
        t = (z_min - a[crosses, 1]) / (b[crosses, 1] - a[crosses, 1])
        keep.append(a[crosses, 0] + t * (b[crosses, 0] - a[crosses, 0]))
    xs = np.concatenate(keep)
    if len(xs) == 0:
        xs = pts[:, 0]
    return float(xs.min()), float(xs.max())


def _plane_cut(verts: FloatArray, faces: np.ndarray, origin: FloatArray, normal: FloatArray) -> FloatArray:
    """(M, 3) points where the mesh's edges (vertices (V, 3), faces (F, 3)) cross the plane through `origin` with
    unit `normal`, plus the vertices lying on it (within 1e-9 m)."""
    d = (verts - origin) @ normal
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    da, db = d[edges[:, 0]], d[edges[:, 1]]
    cross = (da * db) < 0
    t = da[cross] / (da[cross] - db[cross])
    a, b = verts[edges[cross, 0]], verts[edges[cross, 1]]
    pts = a + t[:, None] * (b - a)
    on = verts[np.abs(d) < 1e-9]
    return np.concatenate([pts, on]) if len(on) else pts


def candidates_for_object(
    target: int,
    template: Template,
    world_from_object: FloatArray,
    tool_kind: str,
    options: CandidateOptions | None = None,
    closing_dirs: FloatArray | None = None,
) -> list[GraspCandidate]:
    """World grasp candidates for one object posed at `world_from_object` (4, 4), for a tool of `tool_kind`.

    closing_dirs (K, 3): world directions (the bin's walls) along which a part with one continuous symmetry axis
    is also offered its grasps approached along that axis, turned about it so the jaws close along each direction
    (`@align<k>` in the id): the palm then lies parallel to the wall."""
    opts = options or CandidateOptions()
    out: list[GraspCandidate] = []
    axes_world = symmetry_axes_world(template, world_from_object)
    grasps, object_poses = _object_grasps_cached(template, (tool_kind,), opts)
    if not grasps:
        return out
    world_poses = world_from_object @ object_poses
    if axes_world and opts.snap_to_vertical:
        snapped, has_snap = snap_down_batch(world_poses, axes_world)
    else:
        snapped, has_snap = world_poses, np.zeros(len(world_poses), dtype=bool)
    aligned = None
    if closing_dirs is not None and len(axes_world) == 1 and tool_kind == "parallel":
        aligned = _align_closing(world_poses, axes_world[0], np.asarray(closing_dirs, dtype=np.float64))
    name = template.name
    turned: dict[int, list[int]] = {}  # grasp index -> the wall directions it is turned to close along
    turned_poses = np.zeros((0, 0, 4, 4))
    if aligned is not None:
        turned_poses = aligned[0]
        for k, m in zip(*np.nonzero(aligned[1]), strict=True):
            turned.setdefault(int(k), []).append(int(m))
    snap = has_snap.tolist()
    for k, (gid, source, scheme, *rest) in enumerate(grasps):
        out.append(GraspCandidate(target, name, gid, source, scheme, world_poses[k], *rest))
        if snap[k]:
            out.append(GraspCandidate(target, name, f"{gid}@down", source, scheme, snapped[k], *rest))
        for m in turned.get(k, ()):
            out.append(GraspCandidate(target, name, f"{gid}@align{m}", source, scheme, turned_poses[k, m], *rest))
    if opts.level_within_rad > 0:
        out.extend(level_candidates(out, opts.level_within_rad))
    if opts.vertical_prism and tool_kind == "parallel" and opts.synthesize != "never":
        syn = opts.synthesis
        for gid, pose, opening, quality in vertical_prism_grasps(template, world_from_object, syn):
            out.append(
                GraspCandidate(
                    target, name, gid, "synthesized", "parallel", pose, opening, syn.approach_m, syn.retreat_m, quality
                )
            )
    return out


def level_candidates(candidates: list[GraspCandidate], within_rad: float) -> list[GraspCandidate]:
    """Copies (`@level` in the id) of the candidates approaching within `within_rad` of straight down, but more
    than 0.5 degrees off it, turned about their TCP so that they approach straight down: the closing axis stays
    perpendicular to the approach, in the plane it shared with it. A part fitted a few degrees off flat (fit noise on a
    plate lying on the floor) then meets level fingertips, which clear the floor at the same depth everywhere; the
    grip mechanics judge the pads against the slightly tilted faces."""
    out: list[GraspCandidate] = []
    if not candidates:
        return out
    poses = np.stack([c.world_from_tcp for c in candidates])
    cos_a = -poses[:, 2, 2]  # the approach's component along straight down
    rows = np.flatnonzero((cos_a >= np.cos(within_rad)) & (cos_a < np.cos(np.deg2rad(0.5))))
    if len(rows) == 0:
        return out
    sel = poses[rows]
    # turn about approach x down (unit), through the TCP, by the angle between them (Rodrigues, all at once)
    axis = np.stack([-sel[:, 1, 2], sel[:, 0, 2], np.zeros(len(rows))], axis=1)
    axis /= np.linalg.norm(axis, axis=1)[:, None]
    angle = np.arccos(np.clip(cos_a[rows], -1.0, 1.0))
    x, y, z = axis[:, 0], axis[:, 1], axis[:, 2]
    zero = np.zeros(len(rows))
    k = np.stack([np.stack([zero, -z, y], -1), np.stack([z, zero, -x], -1), np.stack([-y, x, zero], -1)], 1)
    turn = np.repeat(np.eye(4)[None], len(rows), axis=0)
    turn[:, :3, :3] = np.eye(3) + np.sin(angle)[:, None, None] * k + (1.0 - np.cos(angle))[:, None, None] * (k @ k)
    turn[:, :3, 3] = sel[:, :3, 3] - np.einsum("nij,nj->ni", turn[:, :3, :3], sel[:, :3, 3])
    level = turn @ sel
    for j, pose in zip(rows, level, strict=True):
        c = candidates[int(j)]
        out.append(
            GraspCandidate(
                c.target,
                c.template,
                f"{c.grasp_id}@level",
                c.source,
                c.scheme,
                pose,
                c.opening_m,
                c.approach_m,
                c.retreat_m,
                c.quality,
                c.priority,
            )
        )
    return out


def primitive_template(normpos: NormPosition, name: str = "") -> tuple[Template, FloatArray]:
    """A box (or plate, when one side is under a quarter of the next) template from a norm-position's oriented box
    and its world_from_object; for objects no template matched."""
    import trimesh

    ext = np.maximum(np.asarray(normpos.obb.extents, dtype=np.float64), 2e-3)
    pose = np.asarray(normpos.obb.frame_from_box, dtype=np.float64).copy()
    if np.linalg.det(pose[:3, :3]) < 0:
        pose[:3, 2] *= -1
    srt = np.sort(ext)
    shape = "plate" if srt[0] < 0.25 * srt[1] else "box"
    mesh = trimesh.creation.box(extents=ext)
    label = normpos.label or "unknown"
    return Template(name=name or f"primitive_{label}_{normpos.instance_id}", label=label, mesh=mesh, shape=shape), pose
