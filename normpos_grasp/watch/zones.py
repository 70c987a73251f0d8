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

    def distance(self, points_world: FloatArray) -> FloatArray:
        """(N, Z) Euclidean distance from each point (N, 3) to each zone box (grown by the margin), 0 inside, m."""
        pts = np.asarray(points_world, dtype=np.float64).reshape(-1, 1, 3)
        gap = np.maximum(np.maximum(self.lo[None] - pts, pts - self.hi[None]), 0.0)
        return np.asarray(np.sqrt(np.einsum("nzk,nzk->nz", gap, gap)))

    def depth_intervals(self, rays: np.ndarray, world_from_camera: FloatArray) -> tuple[np.ndarray, np.ndarray]:
        """(enter, leave), each (Z, H, W) float32: the z-depths (m) between which each pixel's ray (rays (H, W, 2):
        normalised pixel coordinates, so a point is z (x, y, 1)) lies inside each zone box; enter > leave where the
        ray misses it. A pixel at depth z is in zone i when enter[i] <= z <= leave[i] (the same test as `zone_of`
        on its back-projected point, without back-projecting)."""
        h, w = rays.shape[:2]
        dirs = np.concatenate([rays.reshape(-1, 2), np.ones((h * w, 1))], axis=1) @ world_from_camera[:3, :3].T
        o = world_from_camera[:3, 3]
        enter = np.full((len(self.names), h * w), np.inf, dtype=np.float32)
        leave = np.full((len(self.names), h * w), -np.inf, dtype=np.float32)
        with np.errstate(divide="ignore", invalid="ignore"):
            for i in range(len(self.names)):
                t1 = (self.lo[i] - o) / dirs
                t2 = (self.hi[i] - o) / dirs
                # a ray parallel to a slab: inside it for all t (nan -> ignored) or never (inf bounds)
                near, far = slab_interval(t1, t2)
                hit = far >= np.maximum(near, 0.0)
                enter[i, hit] = np.maximum(near[hit], 0.0)
                leave[i, hit] = far[hit]
        return enter.reshape(-1, h, w), leave.reshape(-1, h, w)

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

    def within(self, points: FloatArray, margin_m: FloatArray | float) -> BoolArray:
        """(N,) True where a point (N, 3) lies within `margin_m` (scalar or (N,), m) of some capsule's surface.

        Capsules are taken `CHUNK` at a time (`ArmCapsules.at` lists them link by link, so a chunk is one link along
        the path); only points inside a chunk's bounding box, and not yet found, are measured against it."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        n = len(p)
        out = np.zeros(n, dtype=bool)
        if len(self.radius) == 0 or n == 0:
            return out
        margin = np.broadcast_to(np.asarray(margin_m, dtype=np.float64).reshape(-1), (n,))
        reach_max = self.radius + float(margin.max())
        for lo in range(0, len(self.radius), CHUNK):
            a, b = self.start[lo : lo + CHUNK], self.end[lo : lo + CHUNK]
            grow = reach_max[lo : lo + CHUNK, None]
            box_lo = np.minimum(a, b) - grow
            box_hi = np.maximum(a, b) + grow
            inside = ~out & np.all((p >= box_lo.min(axis=0)) & (p <= box_hi.max(axis=0)), axis=1)
            idx = np.nonzero(inside)[0]
            if len(idx) == 0:
                continue
            out[idx] = _near_any(p[idx], a, b, self.radius[lo : lo + CHUNK], margin[idx])
        return out


CHUNK = 8  # capsules measured together in `ArmSegments.within`


def _near_any(p: FloatArray, a: FloatArray, b: FloatArray, radius: FloatArray, margin: FloatArray) -> BoolArray:
    """(n,) True where a point p (n, 3) lies within radius (c,) + margin (n,) of some segment a-b (c, 3); float32,
    coordinates taken relative to the first point (sub-millimetre rounding over a cell)."""
    o = p[0]
    p32 = (p - o).astype(np.float32)
    a32 = (a - o).astype(np.float32)
    ab = (b - a).astype(np.float32)
    inv = (1.0 / np.maximum(np.einsum("cj,cj->c", ab, ab), 1e-12)).astype(np.float32)
    q = [p32[:, k, None] - a32[None, :, k] for k in range(3)]  # (n, c) each
    t = q[0] * ab[:, 0] + q[1] * ab[:, 1] + q[2] * ab[:, 2]
    t *= inv
    np.clip(t, 0.0, 1.0, out=t)
    d2 = np.zeros_like(t)
    for k in range(3):
        g = q[k] - t * ab[:, k]
        d2 += g * g
    reach = np.maximum(radius.astype(np.float32)[None] + margin.astype(np.float32)[:, None], 0.0)
    return np.asarray(np.any(d2 <= reach * reach, axis=1))


def slab_interval(t1: np.ndarray, t2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(near, far) (N,) ray parameters of a box from the (N, 3) parameters at which each ray crosses its two faces
    on each axis (NaN ignored: a ray in a face's plane); column by column (a reduction over an axis of 3 costs
    several times more)."""
    lo, hi = np.minimum(t1, t2), np.maximum(t1, t2)
    near = np.fmax(np.fmax(lo[:, 0], lo[:, 1]), lo[:, 2])
    far = np.fmin(np.fmin(hi[:, 0], hi[:, 1]), hi[:, 2])
    return near, far
