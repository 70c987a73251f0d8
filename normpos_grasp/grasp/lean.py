"""Grasps leaned away from the cell: copies of blocked parallel grasps turned so the hand clears a wall.

A part near a bin wall or in a corner has grasps whose palm or outer finger meets the wall although the jaws' contacts
are free. An integrator leans the hand away from the wall, towards the bin centre, keeping the contacts:
- lean (`@lean+<deg>` / `@lean-<deg>` in the id): the grasp turned about its closing axis through the TCP. Both
  contact points and the pads' normals stay where they were (the jaws close along the same line); only the pads'
  footprints turn on the faces, which the grip mechanics judge (`grasp.quality`: pad area, friction cones, torque);
- spin (`@spin+<deg>` / `@spin-<deg>`): for a part with one continuous symmetry axis (cylinders, rings, annotated
  free axes), the grasp turned about that axis: an equivalent grasp of the part whose approach leans by the angle;
- slide (`@slide+<mm>` / `@slide-<mm>`): the grasp moved along the pads' width (the TCP's y axis, across the closing
  and the approach): the jaws keep closing along the same direction on the same faces of a prism (a box's side, a
  cylinder along its axis), nearer the end away from the wall. The TCP stays over the part (within its extent
  along that axis less `LeanOptions.slide_inset_m`); the mechanics judge the pads' contact and the weight's torque
  about the squeeze line.

Only grasps approaching from above (`LeanOptions.max_from_down_rad`) whose tool meets a cell box at the grasp
(`blocked`, the planner's vectorised test of the tool's boxes against the cell's) get copies, the copies approach
from above too, and of each way (lean, spin or slide, each side) only the smallest angles or distances whose tool
clears the cell's boxes at the grasp are kept. The copies then go through every check of the evaluation like any
candidate (`planning.evaluate`): nothing here relaxes one.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np

from normpos_grasp.records.grasp import GraspCandidate
from normpos_grasp.typing import BoolArray, FloatArray


@dataclass(frozen=True)
class LeanOptions:
    """angles_rad: lean / spin angles tried on each side, smallest first, rad. slides_m: slide distances tried on
    each side, smallest first, m; none by default: a slid grasp moves the pads off the centre of mass, and the grip
    mechanics passed slides that slipped in MuJoCo (`make demo`'s default bin: a bar slid 20 mm turned in the
    jaws, where without slides it is pushed and then held; `simulate --scenes 40 --seed 0 --segmenter model`: 300 /
    319 held with slides, 302 / 320 without, the same 32 bins cleared). keep: clear angles kept per way and
    side (the smallest). max_from_down_rad: only grasps approaching within this angle of straight down get copies
    (side grasps that meet the floor are not a wall problem), rad. spin_off_axis_rad: the spin about a symmetry
    axis is offered only where the approach is at least this far off that axis (about the axis it only turns the
    jaws), rad."""

    angles_rad: tuple[float, ...] = (0.25, 0.45, 0.65, 0.85)
    slides_m: tuple[float, ...] = ()
    slide_inset_m: float = 0.005
    keep: int = 2
    max_from_down_rad: float = float(np.deg2rad(60.0))
    spin_off_axis_rad: float = float(np.deg2rad(25.0))


def _rotations(axes: FloatArray, angles: FloatArray) -> FloatArray:
    """(N, 3, 3) rotations by `angles` (N,) rad about unit `axes` (N, 3) (Rodrigues)."""
    x, y, z = axes[:, 0], axes[:, 1], axes[:, 2]
    zero = np.zeros(len(axes))
    k = np.stack([np.stack([zero, -z, y], -1), np.stack([z, zero, -x], -1), np.stack([-y, x, zero], -1)], 1)
    s, c = np.sin(angles)[:, None, None], np.cos(angles)[:, None, None]
    return np.eye(3)[None] + s * k + (1.0 - c) * (k @ k)


def turned_about(poses: FloatArray, axes: FloatArray, points: FloatArray, angles: FloatArray) -> FloatArray:
    """(N, 4, 4) poses (N, 4, 4) turned by `angles` (N,) rad about the world lines through `points` (N, 3) along unit
    `axes` (N, 3)."""
    rot = _rotations(axes, angles)
    out = np.array(poses, dtype=np.float64, copy=True)
    out[:, :3, :3] = rot @ out[:, :3, :3]
    out[:, :3, 3] = np.einsum("nij,nj->ni", rot, out[:, :3, 3] - points) + points
    return out


def wall_leans(
    candidates: Sequence[GraspCandidate],
    blocked: Callable[[FloatArray, FloatArray], FloatArray | BoolArray],
    symmetry_axes: dict[int, tuple[FloatArray, FloatArray]] | None = None,
    options: LeanOptions | None = None,
    part_points: dict[int, FloatArray] | None = None,
) -> list[GraspCandidate]:
    """Leaned and spun copies (module docstring) of the parallel `candidates` approaching from above that are
    `blocked` at their grasp.

    blocked(world_from_tcp (N, 4, 4), opening_m (N,)) -> (N,) bool: the tool meets the cell there.
    symmetry_axes: per target index, the part's one continuous symmetry axis in the world (unit axis (3,), point
    (3,)), for the spins. part_points: per target index, points of the part in the world (N, 3), m (its posed mesh
    vertices), which bound the slides; a target without them gets no slides. Each way and side keeps its
    `options.keep` smallest angles that `blocked` clears."""
    opts = options or LeanOptions()
    axes_of = symmetry_axes or {}
    rows = [
        i
        for i, c in enumerate(candidates)
        if c.scheme == "parallel" and -c.world_from_tcp[2, 2] >= np.cos(opts.max_from_down_rad)
    ]
    if not rows or opts.keep <= 0 or not (opts.angles_rad or opts.slides_m):
        return []
    poses = np.stack([candidates[i].world_from_tcp for i in rows])
    openings = np.array([candidates[i].opening_m for i in rows])
    hit = np.asarray(blocked(poses, openings), dtype=bool)
    rows = [i for i, h in zip(rows, hit, strict=True) if h]
    if not rows:
        return []
    # every (candidate, way, side, amount): its moved pose, then one vectorised test of them all
    src: list[tuple[int, str, float, float]] = []
    axes: list[FloatArray] = []
    points: list[FloatArray] = []
    for i in rows:
        c = candidates[i]
        ways = [("lean", c.world_from_tcp[:3, 0], c.world_from_tcp[:3, 3])]
        sym = axes_of.get(c.target)
        if sym is not None and abs(float(sym[0] @ c.world_from_tcp[:3, 2])) < np.cos(opts.spin_off_axis_rad):
            ways.append(("spin", sym[0], sym[1]))
        for way, axis, point in ways:
            for sign in (1.0, -1.0):
                for angle in opts.angles_rad:
                    src.append((i, way, sign, float(angle)))
                    axes.append(axis)
                    points.append(point)
    base = np.stack([candidates[i].world_from_tcp for i, *_ in src]) if src else np.zeros((0, 4, 4))
    moved = turned_about(
        base,
        np.asarray(axes).reshape(-1, 3),
        np.asarray(points).reshape(-1, 3),
        np.array([s * a for _, _, s, a in src], dtype=np.float64),
    )
    slid = []
    points_of = part_points or {}
    for i in rows:
        pose = candidates[i].world_from_tcp
        pts = points_of.get(candidates[i].target)
        if pts is None or len(pts) == 0:
            continue
        along = (np.asarray(pts, dtype=np.float64) - pose[:3, 3]) @ pose[:3, 1]  # the part along the slide
        room = {1.0: float(along.max()) - opts.slide_inset_m, -1.0: -float(along.min()) - opts.slide_inset_m}
        for sign in (1.0, -1.0):
            for dist in opts.slides_m:
                if dist > room[sign] + 1e-9:
                    continue
                src.append((i, "slide", sign, float(dist)))
                p = pose.copy()
                p[:3, 3] += pose[:3, 1] * sign * dist
                slid.append(p)
    if slid:
        moved = np.concatenate([moved, np.stack(slid)])
    clear = -moved[:, 2, 2] >= np.cos(opts.max_from_down_rad)  # still approaching from above
    if clear.any():
        rows_ok = np.flatnonzero(clear)
        clear[rows_ok] = ~np.asarray(
            blocked(moved[rows_ok], np.array([candidates[src[j][0]].opening_m for j in rows_ok])), dtype=bool
        )
    out: list[GraspCandidate] = []
    kept: dict[tuple[int, str, float], int] = {}
    for j, (i, way, sign, amount) in enumerate(src):
        key = (i, way, sign)
        if not clear[j] or kept.get(key, 0) >= opts.keep:
            continue
        kept[key] = kept.get(key, 0) + 1
        c = candidates[i]
        size = f"{amount * 1e3:.0f}" if way == "slide" else f"{np.rad2deg(amount):.0f}"
        gid = f"{c.grasp_id}@{way}{'+' if sign > 0 else '-'}{size}"
        out.append(replace(c, grasp_id=gid, world_from_tcp=moved[j]))
    return out
