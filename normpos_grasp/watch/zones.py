"""Watched volumes: the cell YAML's boxes (world frame, grown by a margin) and a band around the arm's links."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from normpos_grasp.cell.config import WatchSpec
from normpos_grasp.typing import BoolArray, FloatArray, IntArray


@dataclass(frozen=True, eq=False)
class WatchZones:
    """names (Z,); lo, hi (Z, 3) box corners in the world, m, already grown by the margin; arm_margin_m: points
    within this distance of the arm's link segments are watched too (0: off), m."""

    names: tuple[str, ...]
    lo: FloatArray
    hi: FloatArray
    arm_margin_m: float = 0.0

    @classmethod
    def from_spec(cls, spec: WatchSpec) -> WatchZones:
        m = spec.margin_m
        lo = np.array([z.lo for z in spec.zones], dtype=np.float64).reshape(-1, 3) - m
        hi = np.array([z.hi for z in spec.zones], dtype=np.float64).reshape(-1, 3) + m
        return cls(tuple(z.name for z in spec.zones), lo, hi, spec.arm_margin_m)

    def zone_of(self, points_world: FloatArray, segments: ArmSegments | None = None) -> IntArray:
        """(N,) index of the first zone holding each point (N, 3), len(names) for the arm band, -1 for none."""
        pts = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
        out = np.full(len(pts), -1, dtype=np.int64)
        if len(pts) == 0:
            return out
        if len(self.names):
            inside = np.all((pts[:, None, :] >= self.lo[None]) & (pts[:, None, :] <= self.hi[None]), axis=2)
            hit = inside.any(axis=1)
            out[hit] = np.argmax(inside[hit], axis=1)
        if self.arm_margin_m > 0 and segments is not None:
            near = (out < 0) & segments.within(pts, self.arm_margin_m)
            out[near] = len(self.names)
        return out

    def label(self, index: int) -> str:
        return self.names[index] if 0 <= index < len(self.names) else "arm_band"


@dataclass(frozen=True, eq=False)
class ArmSegments:
    """The arm (and tool) as capsules in the world: start, end (S, 3), m; radius (S,), m."""

    start: FloatArray
    end: FloatArray
    radius: FloatArray

    def distance(self, points: FloatArray) -> FloatArray:
        """(N, S) distance from each point to each capsule's surface (negative inside), m."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        a, b = self.start, self.end
        ab = b - a
        denom = np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-12)
        t = np.clip(np.einsum("nsj,sj->ns", p[:, None, :] - a[None], ab) / denom[None], 0.0, 1.0)
        closest = a[None] + t[..., None] * ab[None]
        return np.asarray(np.linalg.norm(p[:, None, :] - closest, axis=2) - self.radius[None])

    def within(self, points: FloatArray, margin_m: float) -> BoolArray:
        """(N,) True where a point lies within `margin_m` of some capsule."""
        if len(self.radius) == 0:
            return np.zeros(len(np.asarray(points).reshape(-1, 3)), dtype=bool)
        return np.asarray(self.distance(points).min(axis=1) <= margin_m)
