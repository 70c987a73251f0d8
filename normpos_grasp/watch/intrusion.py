"""The per-frame intrusion test: depth nearer than expected, not explained by the arm, inside a zone.

For one streamed depth frame (native size): reduce it as the reference was; candidates are pixels with a valid
depth nearer than the reference's limit (`ExpectedScene.limit`) that the arm does not explain (`arm_explains`: the
back-projected point lies in no padded capsule of the arm along the commanded joints); a 3x3 opening drops
speckle, with the sensor's holes next to candidates counted as part of the shape (not of its size); the
candidates' zones come from per-pixel depth intervals of each zone box (no back-projection) and, for the rest,
their distance to the arm (the arm band); an 8-connected blob with at least `min_blob_px` candidate pixels inside
a watched zone is an intrusion, back-projected to the world to be named and located.

Approach band: a blob that has fewer than `min_blob_px` pixels inside but at least `min_blob_px` inside or within
`approach_m` of a zone box is an intrusion too when it is coming in: a blob of the previous frame lay near it (two
frames of evidence) and it is nearer to the zone than the nearest such blob was by more than `APPROACH_EPS_M`. The
camera sees only surfaces: a hand whose leading part is in the bin under the arm, or a person whose body is in the
operator strip above the camera's view, shows only the part outside. The band is ISO 13855's separation distance
S = K T for the watch's own reaction: K = 2.0 m/s (hand and arm approach speed) over T = two frame intervals at
30 fps, so an intruder that can be inside before the frame after next is stopped now. Something that rests or
recedes in the band does not stop the arm (nor keep a zone from clearing after a stop).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from normpos_grasp.cell.config import WatchSpec
from normpos_grasp.errors import InputError
from normpos_grasp.typing import BoolArray, FloatArray
from normpos_grasp.watch.expected import ExpectedScene, downsample_depth
from normpos_grasp.watch.person import PersonRule, blob_extent, classify
from normpos_grasp.watch.zones import WatchZones

# ISO 13855 approach speed of a hand or arm (2.0 m/s) over two frame intervals at 30 fps, m
APPROACH_M: float = WatchSpec.approach_m  # 0.13 m, the cell YAML's watch.approach_m default
# a blob in the approach band counts as coming in when it is nearer to its zone than in the previous frame by more
# than this (depth noise and a blob's changing outline move its nearest point by a few millimetres), m
APPROACH_EPS_M = 0.01


@dataclass(frozen=True, eq=False)
class Intrusion:
    """One blob inside a zone: zone name, label ('person', 'hand', 'object'), pixels of the blob and inside the
    zone (watch pixels), centroid (3,) and extents (major, minor, height) in the world, m; points (<= 400, 3) world
    samples of the blob for the live view; approaching: caught in the approach band (fewer than `min_blob_px` pixels
    inside), distance_m: then its nearest point's distance to the zone (0: touching it), m."""

    zone: str
    label: str
    n_px: int
    n_in_zone: int
    centroid: FloatArray
    extent_m: tuple[float, float, float]
    points: FloatArray
    distance_m: float = 0.0
    approaching: bool = False

    def to_dict(self) -> dict[str, object]:
        return {
            "zone": self.zone,
            "label": self.label,
            "pixels": self.n_px,
            "pixels_in_zone": self.n_in_zone,
            "approaching": self.approaching,
            "distance_m": round(self.distance_m, 3),
            "centroid_m": [round(float(v), 4) for v in self.centroid],
            "extent_m": [round(v, 3) for v in self.extent_m],
        }


@dataclass(frozen=True, eq=False)
class FrameCheck:
    """Result for one frame: intrusions (empty: clear), candidate pixel count, time spent (wall clock and this
    thread's CPU time), ms."""

    intrusions: tuple[Intrusion, ...] = ()
    n_candidates: int = 0
    elapsed_ms: float = 0.0
    cpu_ms: float = 0.0
    candidates: BoolArray | None = field(default=None, repr=False)

    @property
    def clear(self) -> bool:
        return not self.intrusions


class IntrusionDetector:
    """Compares frames with an `ExpectedScene`; zones from the cell's `watch:` spec; approach_m: width of the
    approach band around each zone box (0: off), m. Keeps the previous frame's blobs in the band (`check` is meant
    for the frames of one stream, in order)."""

    def __init__(
        self,
        expected: ExpectedScene,
        zones: WatchZones,
        min_blob_px: int = 12,
        rule: PersonRule | None = None,
        approach_m: float = APPROACH_M,
    ) -> None:
        if not approach_m >= 0.0:
            raise InputError(f"approach_m must be >= 0 m, got {approach_m}")
        self.expected = expected
        self.zones = zones
        self.min_blob_px = int(min_blob_px)
        self.rule = rule or PersonRule()
        self.approach_m = float(approach_m)
        # the previous frame's blobs of at least min_blob_px: (row0, row1, col0, col1) bounding box, nearest distance
        # to a zone box (0: some pixels inside), m
        self._blobs: list[tuple[int, int, int, int, float]] = []
        # per pixel, the depth interval of each zone box along its ray (zone membership without back-projecting)
        self.enter, self.leave = zones.depth_intervals(expected.rays, expected.camera.require_world_from_camera())

    @classmethod
    def from_spec(cls, expected: ExpectedScene, spec: WatchSpec) -> IntrusionDetector:
        return cls(expected, WatchZones.from_spec(spec), spec.min_blob_px, approach_m=spec.approach_m)

    def check(
        self, depth_m: FloatArray, q: FloatArray, held_radius_m: float = 0.0, keep_mask: bool = False
    ) -> FrameCheck:
        """Test one native-size depth frame (H, W), metres (0 = no measurement), at commanded joints q (6,) rad, or
        along the joint path (M, 6) of the stream's latency (the newest pose last)."""
        import cv2

        t0, c0 = time.perf_counter(), time.thread_time()
        ex = self.expected
        d = downsample_depth(depth_m, ex.factor)
        cand = (d > 0) & (d < ex.limit)
        if cand.any() or ex.unknown.any():
            explained = ex.arm_explains(d, q, held_radius_m, among=cand)
            cand &= ~explained
            cand &= ~ex.learn(d, explained)
        shape = cand
        if cand.any():
            # the opening drops speckle; holes of the sensor next to candidates count as the intruder for its shape
            # (a hand under the arm or at an edge reaches the stream as a sparse scatter of valid pixels), never for
            # its size
            kernel = np.ones((3, 3), np.uint8)
            c8 = cand.astype(np.uint8)
            grown = c8 | (cv2.dilate(c8, kernel) & (d <= 0).astype(np.uint8))
            shape = cv2.morphologyEx(grown, cv2.MORPH_OPEN, kernel).astype(bool)
            cand &= shape
        n_cand = int(np.count_nonzero(cand))
        found: list[Intrusion] = []
        blobs: list[tuple[int, int, int, int, float]] = []
        if n_cand >= self.min_blob_px:
            v, u = np.nonzero(cand)
            z = d[v, u]
            zone = self._zone_of_pixels(v, u, z, q, held_radius_m)
            inside = zone >= 0
            # distance to the nearest zone box of each candidate outside every zone; within approach_m: the band
            track = self.approach_m > 0 and len(self.zones.names) > 0
            gap = np.zeros(len(v))
            near = inside.copy()
            if track and not inside.all():
                rest = np.nonzero(~inside)[0]
                dist = self.zones.distance(ex.world_points(v[rest], u[rest], z[rest]))
                k, gap[rest] = np.argmin(dist, axis=1), np.min(dist, axis=1)
                ok = gap[rest] <= self.approach_m
                near[rest[ok]] = True
                zone[rest[ok]] = k[ok]
            if track or int(inside.sum()) >= self.min_blob_px:
                _, labels = cv2.connectedComponents(shape.astype(np.uint8), connectivity=8)
                lab = labels[v, u]
                area = np.bincount(lab)
                in_zone = np.bincount(lab[inside], minlength=len(area))
                in_band = np.bincount(lab[near], minlength=len(area))
                for i in np.nonzero(area >= self.min_blob_px)[0]:
                    sel = lab == i
                    distance, coming = 0.0, False
                    if track:
                        vs, us = v[sel], u[sel]
                        box = (int(vs.min()), int(vs.max()), int(us.min()), int(us.max()))
                        distance = 0.0 if in_zone[i] else float(gap[sel].min())
                        blobs.append((*box, distance))
                        if in_zone[i] < self.min_blob_px:
                            if in_band[i] < self.min_blob_px:
                                continue
                            reach = int(np.ceil(ex.camera.fx * self.approach_m / float(np.median(z[sel])))) + 2
                            coming = self._coming_in(box, distance, reach)
                            if not coming:
                                continue
                    elif in_zone[i] < self.min_blob_px:
                        continue
                    pts = ex.world_points(v[sel], u[sel], z[sel])
                    zi = zone[sel & near]
                    counts = np.bincount(zi[zi >= 0])
                    step = max(1, len(pts) // 400)
                    found.append(
                        Intrusion(
                            self.zones.label(int(np.argmax(counts))),
                            classify(pts, self.rule),
                            int(area[i]),
                            int(in_zone[i]),
                            pts.mean(axis=0),
                            blob_extent(pts),
                            pts[::step][:400],
                            distance,
                            coming,
                        )
                    )
        self._blobs = blobs
        elapsed, cpu = (time.perf_counter() - t0) * 1e3, (time.thread_time() - c0) * 1e3
        return FrameCheck(tuple(found), n_cand, elapsed, cpu, cand if keep_mask else None)

    def _coming_in(self, box: tuple[int, int, int, int], distance: float, reach_px: int) -> bool:
        """Whether a blob short of `min_blob_px` pixels inside a zone (bounding box rows v0..v1, columns u0..u1;
        nearest distance to a zone, m) comes in: a blob of the previous frame lay within `reach_px` of its box and
        the nearest of those was farther from a zone by more than APPROACH_EPS_M."""
        v0, v1, u0, u1 = box
        before = [
            p[4]
            for p in self._blobs
            if p[0] <= v1 + reach_px and p[1] >= v0 - reach_px and p[2] <= u1 + reach_px and p[3] >= u0 - reach_px
        ]
        return bool(before) and distance < min(before) - APPROACH_EPS_M

    def _zone_of_pixels(
        self, v: np.ndarray, u: np.ndarray, z: np.ndarray, q: FloatArray, held_radius_m: float
    ) -> np.ndarray:
        """(N,) zone index of reduced-frame pixels at depths z (m): the first box holding the point, len(names) for
        the arm band (within `arm_margin_m` of the arm along the path q), -1 for none."""
        zone = np.full(len(v), -1, dtype=np.int64)
        for i in range(len(self.zones.names)):
            hit = (zone < 0) & (z >= self.enter[i, v, u]) & (z <= self.leave[i, v, u])
            zone[hit] = i
        if self.zones.arm_margin_m > 0:
            rest = np.nonzero(zone < 0)[0]
            if len(rest):
                ex = self.expected
                pts = ex.world_points(v[rest], u[rest], z[rest])
                near = ex.segments(q, held_radius_m).within(pts, self.zones.arm_margin_m)
                zone[rest[near]] = len(self.zones.names)
        return zone
