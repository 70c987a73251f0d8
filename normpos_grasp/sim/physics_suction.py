"""Suction-cup seal check: can a cup of a given diameter seal on the target's surface at a TCP pose?

Rays are cast along the approach axis (TCP +z) from the cup's rim and from rings inside it onto the target
mesh in its true pose. The cup seals when every ray hits the target (no edge under the rim, no hole under the
cup), the hit surface varies in height by no more than the lip's compliance (flatness), and its normals face
the cup within an angle. The vacuum force is then pressure difference x cup area.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from normpos_grasp.geometry.transforms import transform_points
from normpos_grasp.typing import FloatArray

if TYPE_CHECKING:
    import trimesh


@dataclass(frozen=True)
class SealOptions:
    """Seal criteria. flatness_m: allowed spread of surface heights under the cup (lip / bellows compliance),
    metres. max_normal_angle_rad: allowed tilt of surface normals against the approach axis, radians.
    rim_points: rays on the rim; rings: inner rings of rays (each with rim_points rays) plus the centre ray.
    search_m: rays start this far behind the TCP and reach as far beyond it, metres.
    """

    flatness_m: float = 0.004
    max_normal_angle_rad: float = 0.45
    rim_points: int = 24
    rings: int = 3
    search_m: float = 0.03


@dataclass(frozen=True, eq=False)
class SealCheck:
    """Result of a seal check. sealed: the cup seals; reason: '' or why not ('hole', 'edge', 'not_flat',
    'tilted', 'no_surface'); hit_fraction: share of rays hitting the target; height_spread_m: spread of hit
    depths along the approach axis; max_normal_angle_rad: largest normal tilt; contact_depth_m: mean depth of
    the hits along +z from the TCP (negative: surface in front of the TCP)."""

    sealed: bool
    reason: str
    hit_fraction: float
    height_spread_m: float
    max_normal_angle_rad: float
    contact_depth_m: float


def check_seal(
    mesh_world: trimesh.Trimesh, world_from_tcp: FloatArray, cup_diameter_m: float, options: SealOptions | None = None
) -> SealCheck:
    """Seal check of a cup of `cup_diameter_m` at `world_from_tcp` (4, 4) on `mesh_world` (target in world)."""
    opts = options or SealOptions()
    r = cup_diameter_m / 2.0
    angles = 2.0 * np.pi * np.arange(opts.rim_points) / opts.rim_points
    circle = np.column_stack([np.cos(angles), np.sin(angles), np.zeros_like(angles)])
    radii = [r * (k + 1) / (opts.rings + 1) for k in range(opts.rings)] + [r]
    disk = np.concatenate([np.zeros((1, 3))] + [circle * rad for rad in radii])
    is_rim = np.zeros(len(disk), dtype=bool)
    is_rim[-opts.rim_points :] = True
    start_tcp = disk + np.array([0.0, 0.0, -opts.search_m])
    origins = transform_points(world_from_tcp, start_tcp)
    direction = np.asarray(world_from_tcp, dtype=np.float64)[:3, 2]
    dirs = np.broadcast_to(direction, origins.shape).copy()
    locations, index_ray, index_tri = mesh_world.ray.intersects_location(origins, dirs, multiple_hits=False)
    depth = np.full(len(disk), np.inf)
    normal_angle = np.full(len(disk), np.pi)
    if len(index_ray):
        d = (locations - origins[index_ray]) @ direction - opts.search_m
        normals = np.asarray(mesh_world.face_normals, dtype=np.float64)[index_tri]
        ang = np.arccos(np.clip(-(normals @ direction), -1.0, 1.0))
        keep = d <= opts.search_m
        depth[index_ray[keep]] = d[keep]
        normal_angle[index_ray[keep]] = ang[keep]
    hit = np.isfinite(depth)
    frac = float(hit.mean())
    if not hit.any():
        return SealCheck(False, "no_surface", 0.0, float("inf"), float(np.pi), float("nan"))
    spread = float(depth[hit].max() - depth[hit].min())
    max_ang = float(normal_angle[hit].max())
    mean_depth = float(depth[hit].mean())
    if not hit[0]:  # nothing under the cup's centre
        return SealCheck(False, "hole", frac, spread, max_ang, mean_depth)
    if not hit[is_rim].all():
        return SealCheck(False, "edge", frac, spread, max_ang, mean_depth)
    if not hit.all():
        return SealCheck(False, "hole", frac, spread, max_ang, mean_depth)
    if spread > opts.flatness_m:
        return SealCheck(False, "not_flat", frac, spread, max_ang, mean_depth)
    if max_ang > opts.max_normal_angle_rad:
        return SealCheck(False, "tilted", frac, spread, max_ang, mean_depth)
    return SealCheck(True, "", frac, spread, max_ang, mean_depth)


def vacuum_force_n(cup_diameter_m: float, vacuum_kpa: float, efficiency: float) -> float:
    """Holding force of a sealed cup: pressure difference (kPa) x cup area x efficiency, newtons."""
    return float(vacuum_kpa * 1e3 * np.pi * (cup_diameter_m / 2.0) ** 2 * efficiency)
