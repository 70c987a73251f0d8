"""Drags planned on the perceived scene: a part against a wall or in a corner is slid out by a fingertip on its top.

A push (`planning.push`) needs room for the closed fingers beside the part's far side; against a wall or in a corner
that room is the wall. A drag instead presses the closed fingertips a millimetre or two into the top of the part and
slides it horizontally towards the bin centre (the pads' friction, 0.9 in the physics, beats the part's on the
floor, 0.5, once the press is more than about its weight). Like a push it is planned from the fits and the measured
points only, executed by `push.push_motion` (checked against the perceived world, the cell's caps judged by
`push.judged_push_motion`) and replayed by `sim.physics_push.simulate_push` on the true scene.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterator, Sequence

import numpy as np

from normpos_grasp.cell.config import CellConfig
from normpos_grasp.errors import InputError
from normpos_grasp.planning.push import Push, perceived_world
from normpos_grasp.records.normpos import NormPosition
from normpos_grasp.records.plan import PickPlan
from normpos_grasp.records.template import TemplateFit
from normpos_grasp.typing import FloatArray

#: the top under the fingertip must face up at least this much (cos of its tilt) to be pressed on
MIN_TOP_NORMAL_Z = 0.7
#: tilts of the hand (rad) away from the wall, leaning in the drag's direction: the palm, wider than the gap between a
#: part and the wall, clears the wall while the fingertip reaches the part's top
TILTS_RAD = (0.0, 0.9, 0.7, 0.45)
#: turns of the closed jaws about the approach (rad): the fingers across the drag or along it (the tip faces press
#: level across the drag: MuJoCo slides the part best so), then half-way turns (other arm configurations when the
#: wrist meets a wall)
YAWS_RAD = tuple(np.array([0, 2, 4, 6, 1, 3, 5, 7]) * (np.pi / 4.0))


def _tip_points(cell: CellConfig) -> FloatArray:
    """(N, 3) corners of the closed fingers' tip faces (the tool's moving shapes, else all of its box shapes; the
    face farthest along the approach) in the TCP frame: the points a drag presses with."""
    shapes = cell.tool.posed_shapes(0.0)
    moving = [(s, p) for s, p in shapes if s.moves and s.kind == "box"] or [
        (s, p) for s, p in shapes if s.kind == "box"
    ]
    corners = []
    for s, pose in moving:
        half = np.asarray(s.size, dtype=np.float64) / 2.0
        local = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64) * half
        corners.append(local @ pose[:3, :3].T + pose[:3, 3])
    if not corners:
        return np.zeros((1, 3))
    points = np.vstack(corners)
    return points[points[:, 2] >= points[:, 2].max() - 1e-9]


def wall_gap(verts: FloatArray, world_from_bin: FloatArray, inner_size: FloatArray) -> float:
    """The smallest horizontal gap between a part's points (N, 3) and the bin's inner walls, m."""
    local = (verts - world_from_bin[:3, 3]) @ world_from_bin[:3, :3]
    half = np.asarray(inner_size, dtype=np.float64)[:2] / 2.0
    return float(np.min(half - np.abs(local[:, :2]).max(axis=0)))


def _tops(mesh: object, xy: FloatArray, above_z: float) -> tuple[FloatArray, FloatArray]:
    """Heights (K,) and normal z (K,) of the highest surface of `mesh` (posed, trimesh) under each of `xy` (K, 2);
    NaN and 0 where a point is off the part."""
    n = len(xy)
    origins = np.column_stack([xy, np.full(n, above_z)])
    rays = np.tile([0.0, 0.0, -1.0], (n, 1))
    locs, index, tri = mesh.ray.intersects_location(origins, rays)  # type: ignore[attr-defined]
    heights = np.full(n, np.nan)
    normal_z = np.zeros(n)
    normals = np.asarray(mesh.face_normals, dtype=np.float64)  # type: ignore[attr-defined]
    for loc, i, t in zip(locs, index, tri, strict=True):
        if not loc[2] <= heights[i]:  # NaN or higher
            heights[i] = loc[2]
            normal_z[i] = abs(normals[t, 2])
    return heights, normal_z


def drag_candidates(
    plan: PickPlan,
    fits: Sequence[TemplateFit],
    normpositions: Sequence[NormPosition],
    cell: CellConfig,
    floor_z: float,
    drag_m: float,
    press_m: float = 0.004,
    max_gap_m: float = 0.04,
) -> Iterator[Push]:
    """Drags from the perceived scene only, best first: the perceived objects within `max_gap_m` of a bin wall
    (nearest first); horizontal directions towards the bin centre and away from the nearest neighbours; the hand
    upright or leaning towards the drag (`TILTS_RAD`, so that the palm clears the wall), the closed fingers'
    lowest point on the object's top at its centre (else 1 or 2 cm towards the drag), where the top faces up
    (normal z >= MIN_TOP_NORMAL_Z) at least 4 mm above the floor. The descent from 8 cm above down to
    5 mm over the top must be clear of everything; the press (`press_m` into the top) and the slide (`drag_m`, else
    half of it) clear of everything but the object itself (the cell, the other objects, unexplained points)."""
    targets = list(plan.targets)
    if not targets or cell.bin is None:
        if cell.bin is None and targets:
            raise InputError("planning a drag needs a cell with a bin")
        return
    world, _ = perceived_world(cell, fits, normpositions)
    tips = _tip_points(cell)
    world_from_bin = np.asarray(cell.bin.world_from_bin, dtype=np.float64)
    inner = np.asarray(cell.bin.inner_size, dtype=np.float64)
    posed = []
    for t in targets:
        mesh = t.mesh.copy()  # type: ignore[attr-defined]
        mesh.apply_transform(np.asarray(t.world_from_object, dtype=np.float64))
        verts = np.asarray(mesh.vertices, dtype=np.float64)
        posed.append((mesh, verts, verts.mean(axis=0), wall_gap(verts, world_from_bin, inner)))
    order = sorted((k for k in range(len(targets)) if posed[k][3] < max_gap_m), key=lambda k: posed[k][3])
    angles = np.arange(8) * (np.pi / 4.0)
    dirs = np.column_stack([np.cos(angles), np.sin(angles), np.zeros(8)])
    for k in order:
        mesh, verts, c, _ = posed[k]
        pref = world_from_bin[:2, 3] - c[:2]
        pref = pref / max(float(np.linalg.norm(pref)), 1e-9)
        for j, (_, _, cj, _) in enumerate(posed):
            d = c[:2] - cj[:2]
            dist = float(np.linalg.norm(d))
            if j != k and 1e-6 < dist < 0.12:
                pref = pref + 0.5 * d / dist
        pref = pref / max(float(np.linalg.norm(pref)), 1e-9)
        ranked = [m for m in sorted(range(8), key=lambda m: -float(dirs[m, :2] @ pref)) if dirs[m, :2] @ pref > 0.3]
        high = float(verts[:, 2].max())
        name, own_clutter = targets[k].name, f"clutter/{targets[k].instance_id}"
        for m, tilt, shift, yaw in itertools.product(ranked, TILTS_RAD, (0.0, 0.01, 0.02), YAWS_RAD):
            d = dirs[m]
            side = np.array([-d[1], d[0], 0.0])  # horizontal, across the drag
            z = -np.cos(tilt) * np.array([0.0, 0.0, 1.0]) - np.sin(tilt) * d  # the hand leans towards the drag
            x = np.cos(yaw) * side + np.sin(yaw) * np.cross(side, z)  # the jaws turned about the approach
            rot = np.column_stack([x, np.cross(z, x), z])
            low = tips @ rot.T  # the tip faces' corners from the TCP, world axes
            tcp_xy = c[:2] + d[:2] * shift - low[:, :2].mean(axis=0)  # the tips centred over the contact point
            heights, normal_z = _tops(mesh, tcp_xy + low[:, :2], high + 0.05)
            over = np.isfinite(heights)
            if not over.any() or normal_z[over].min() < MIN_TOP_NORMAL_Z or np.nanmax(heights) - floor_z < 0.004:
                continue
            start = np.eye(4)
            start[:3, :3] = rot
            # the deepest corner `press_m` into the top, none deeper
            start[:3, 3] = [tcp_xy[0], tcp_xy[1], float(np.max(heights[over] - low[over, 2])) - press_m]
            descent = []
            for lift in (press_m + 0.005, 0.02, 0.05, 0.08):
                p = start.copy()
                p[2, 3] += lift
                descent.append(p)
            if any(world.check_tool(p, 0.0) is not None for p in descent):
                continue
            found = None
            with world.without(name, own_clutter):  # the object's own unexplained points ride along with it
                for dist in (drag_m, drag_m / 2.0):
                    along = []
                    for s in np.linspace(0.0, dist, 6):
                        p = start.copy()
                        p[:3, 3] += d * s
                        along.append(p)
                    if all(world.check_tool(p, 0.0) is None for p in along):
                        found = Push(start, d * dist, kind="drag", press_m=press_m)
                        break
            if found is not None:
                yield found
