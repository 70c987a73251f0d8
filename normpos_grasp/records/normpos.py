"""`NormPosition`: the world positions of an object's surface points with its class (the paper's core notion)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from normpos_grasp.records.kinds import Frame
from normpos_grasp.typing import BoolArray, FloatArray, IntArray


@dataclass(frozen=True, eq=False)
class OrientedBox:
    """Oriented box: `center` (3,), `axes` (3, 3) columns = box axes, `extents` (3,) full sizes; metres."""

    center: FloatArray
    axes: FloatArray
    extents: FloatArray

    @property
    def frame_from_box(self) -> FloatArray:
        """(4, 4) pose of the box in the points' frame."""
        pose = np.eye(4)
        pose[:3, :3] = self.axes
        pose[:3, 3] = self.center
        return pose

    def corners(self) -> FloatArray:
        """(8, 3) corners."""
        signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64)
        return self.center + (signs * self.extents / 2.0) @ self.axes.T


@dataclass(frozen=True, eq=False)
class NormPosition:
    """An object's measured surface points and class.

    Attributes:
        label: class name ('' when unknown until template fitting assigns one).
        score: segmentation confidence in [0, 1].
        mask: (H, W) bool visible-pixel mask the points came from.
        points: (N, 3) surface points in `frame`, metres.
        normals: (N, 3) unit normals pointing towards the camera.
        pixels: (N, 2) integer (u, v) pixel of each point.
        frame: 'world' or 'camera'.
        viewpoint: (3,) camera centre in `frame` (for visibility reasoning).
        instance_id: 1-based id within the frame.
        centroid, aabb_min, aabb_max: (3,) summaries of `points`, metres.
        obb: oriented bounding box of `points`.
    """

    label: str
    score: float
    mask: BoolArray
    points: FloatArray
    normals: FloatArray
    pixels: IntArray
    frame: Frame
    viewpoint: FloatArray
    instance_id: int
    centroid: FloatArray
    aabb_min: FloatArray
    aabb_max: FloatArray
    obb: OrientedBox

    @property
    def n_points(self) -> int:
        return int(self.points.shape[0])
