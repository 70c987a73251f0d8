"""The per-frame intrusion test: depth nearer than expected, not explained by the arm, inside a zone.

For one streamed depth frame (native size): reduce it as the reference was; candidates are pixels with a valid
depth nearer than the reference's limit (`ExpectedScene.limit`) that the arm does not explain (outside the
predicted silhouette along the commanded joints, or inside it but nearer or farther than the arm can be there);
a 3x3 opening drops isolated speckle; 8-connected blobs of at least `min_blob_px` pixels are back-projected to the
world, and a blob with at least `min_blob_px` pixels inside a watched zone (or within the arm band) is an
intrusion. Everything is vectorised; only candidate pixels are back-projected.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from normpos_grasp.cell.config import WatchSpec
from normpos_grasp.typing import BoolArray, FloatArray
from normpos_grasp.watch.expected import ExpectedScene, downsample_depth
from normpos_grasp.watch.person import PersonRule, blob_extent, classify
from normpos_grasp.watch.zones import WatchZones


@dataclass(frozen=True, eq=False)
class Intrusion:
    """One blob inside a zone: zone name, label ('person', 'hand', 'object'), pixels of the blob and inside the
    zone (watch pixels), centroid (3,) and extents (major, minor, height) in the world, m; points (<= 400, 3) world
    samples of the blob for the live view."""

    zone: str
    label: str
    n_px: int
    n_in_zone: int
    centroid: FloatArray
    extent_m: tuple[float, float, float]
    points: FloatArray

    def to_dict(self) -> dict[str, object]:
        return {
            "zone": self.zone,
            "label": self.label,
            "pixels": self.n_px,
            "pixels_in_zone": self.n_in_zone,
            "centroid_m": [round(float(v), 4) for v in self.centroid],
            "extent_m": [round(v, 3) for v in self.extent_m],
        }


@dataclass(frozen=True, eq=False)
class FrameCheck:
    """Result for one frame: intrusions (empty: clear), candidate pixel count, time spent, ms."""

    intrusions: tuple[Intrusion, ...] = ()
    n_candidates: int = 0
    elapsed_ms: float = 0.0
    candidates: BoolArray | None = field(default=None, repr=False)

    @property
    def clear(self) -> bool:
        return not self.intrusions


class IntrusionDetector:
    """Compares frames with an `ExpectedScene`; zones from the cell's `watch:` spec."""

    def __init__(
        self, expected: ExpectedScene, zones: WatchZones, min_blob_px: int = 12, rule: PersonRule | None = None
    ) -> None:
        self.expected = expected
        self.zones = zones
        self.min_blob_px = int(min_blob_px)
        self.rule = rule or PersonRule()

    @classmethod
    def from_spec(cls, expected: ExpectedScene, spec: WatchSpec) -> IntrusionDetector:
        return cls(expected, WatchZones.from_spec(spec), spec.min_blob_px)

    def check(
        self, depth_m: FloatArray, q: FloatArray, held_radius_m: float = 0.0, keep_mask: bool = False
    ) -> FrameCheck:
        """Test one native-size depth frame (H, W), metres (0 = no measurement), at commanded joints q (6,) rad."""
        import cv2

        t0 = time.perf_counter()
        ex = self.expected
        d = downsample_depth(depth_m, ex.factor)
        cand = (d > 0) & (d < ex.limit)
        if cand.any() or ex.unknown.any():
            explained = ex.arm_explains(d, q, held_radius_m)
            cand &= ~explained
            cand &= ~ex.learn(d, explained)
        if cand.any():
            cand = cv2.morphologyEx(cand.astype(np.uint8), cv2.MORPH_OPEN, np.ones((3, 3), np.uint8)).astype(bool)
        n_cand = int(np.count_nonzero(cand))
        found: list[Intrusion] = []
        if n_cand >= self.min_blob_px:
            n, labels, stats, _ = cv2.connectedComponentsWithStats(cand.astype(np.uint8), connectivity=8)
            big = [i for i in range(1, n) if stats[i, cv2.CC_STAT_AREA] >= self.min_blob_px]
            if big:
                segments = ex.segments(q, held_radius_m) if self.zones.arm_margin_m > 0 else None
                v, u = np.nonzero(np.isin(labels, big))
                lab = labels[v, u]
                z = d[v, u].astype(np.float64)
                xy = ex.rays[v, u].astype(np.float64)
                cam = np.column_stack([xy * z[:, None], z])
                wfc = ex.camera.require_world_from_camera()
                world = cam @ wfc[:3, :3].T + wfc[:3, 3]
                zone = self.zones.zone_of(world, segments)
                for i in big:
                    sel = lab == i
                    zi = zone[sel]
                    inside = zi >= 0
                    if int(inside.sum()) < self.min_blob_px:
                        continue
                    pts = world[sel]
                    counts = np.bincount(zi[inside])
                    step = max(1, len(pts) // 400)
                    found.append(
                        Intrusion(
                            self.zones.label(int(np.argmax(counts))),
                            classify(pts, self.rule),
                            int(sel.sum()),
                            int(inside.sum()),
                            pts.mean(axis=0),
                            blob_extent(pts),
                            pts[::step][:400],
                        )
                    )
        return FrameCheck(tuple(found), n_cand, (time.perf_counter() - t0) * 1e3, cand if keep_mask else None)
