"""Collision primitives attached to robot links and grippers, and the UR arm's capsule layout.

Size conventions follow python-fcl: capsule (radius, length) with `length` the distance between the two
hemisphere centres; cylinder (radius, length) full height; box (sx, sy, sz) full edge lengths; sphere
(radius,). The shape's axis (capsule, cylinder) is the z axis of `link_from_shape`. Metres.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from normpos_grasp.errors import InputError
from normpos_grasp.kinematics.ur_params import URParams
from normpos_grasp.typing import FloatArray

ShapeKind = Literal["capsule", "cylinder", "box", "sphere"]
_SIZE_LEN = {"capsule": 2, "cylinder": 2, "box": 3, "sphere": 1}

# Link names of a UR arm, base to tool; the body frame of link i rotates with joint i about its z axis.
ARM_LINKS = ("base", "shoulder", "upper_arm", "forearm", "wrist_1", "wrist_2", "wrist_3")


@dataclass(frozen=True)
class CollisionShape:
    """One primitive on a link: place it at base_from_link @ link_from_shape (4, 4). Sizes in metres."""

    link: str
    kind: ShapeKind
    size: tuple[float, ...]
    link_from_shape: FloatArray

    def __post_init__(self) -> None:
        if self.kind not in _SIZE_LEN:
            raise InputError(f"shape kind must be one of {sorted(_SIZE_LEN)}, got {self.kind!r}")
        if len(self.size) != _SIZE_LEN[self.kind] or any(not (s > 0 and math.isfinite(s)) for s in self.size):
            raise InputError(
                f"{self.kind} on link {self.link!r}: size needs {_SIZE_LEN[self.kind]} positive values, got {self.size}"
            )
        pose = np.array(self.link_from_shape, dtype=np.float64)
        if pose.shape != (4, 4):
            raise InputError(f"link_from_shape of {self.link!r}: expected (4, 4), got {pose.shape}")
        pose.setflags(write=False)
        object.__setattr__(self, "link_from_shape", pose)

    def transformed(self, a_from_link: FloatArray, link: str | None = None) -> CollisionShape:
        """The same shape expressed in another frame: a_from_shape = a_from_link @ link_from_shape."""
        return CollisionShape(link or self.link, self.kind, self.size, np.asarray(a_from_link) @ self.link_from_shape)


def _pose(axis: str, centre: tuple[float, float, float]) -> FloatArray:
    """Pose whose z axis points along the link's `axis` ('x', 'y' or 'z'), origin at `centre`."""
    pose = np.eye(4)
    if axis == "x":
        pose[:3, :3] = [[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]]
    elif axis == "y":
        pose[:3, :3] = [[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]]
    pose[:3, 3] = centre
    return pose


def _segment(
    link: str, kind: ShapeKind, radius: float, axis: str, start: float, end: float, at: tuple[float, float]
) -> CollisionShape:
    """Capsule/cylinder along `axis` from coordinate `start` to `end`; `at` gives the other two coordinates."""
    lo, hi = min(start, end), max(start, end)
    mid = 0.5 * (lo + hi)
    centre = {"x": (mid, at[0], at[1]), "y": (at[0], mid, at[1]), "z": (at[0], at[1], mid)}[axis]
    return CollisionShape(link, kind, (radius, max(hi - lo, 1e-4)), _pose(axis, centre))


def arm_collision_shapes(params: URParams) -> list[CollisionShape]:
    """Capsules/cylinders covering a UR arm, each in its link frame (see `ARM_LINKS`).

    Link frames: base = DH frame 0; link i (1..6) = DH frame i-1 rotated by q_i about its z axis, so link i's
    z axis is joint i's axis. Sizes come from `params.link_geometry` (UR5e measured, others scaled).
    """
    g = params.link_geometry
    d1, d4, d5, d6 = params.d[0], params.d[3], params.d[4], params.d[5]
    a2, a3 = params.a[1], params.a[2]
    sh, fa = g.shoulder_offset, g.shoulder_offset - g.elbow_offset
    return [
        _segment("base", "cylinder", g.footprint_radius, "z", 0.0, g.base_height, (0.0, 0.0)),
        _segment("shoulder", "capsule", g.shoulder_radius, "z", g.base_height, d1, (0.0, 0.0)),
        _segment("upper_arm", "capsule", g.shoulder_radius, "z", 0.0, sh, (0.0, 0.0)),
        _segment("upper_arm", "capsule", g.upper_arm_radius, "x", 0.0, a2, (0.0, sh)),
        _segment("forearm", "capsule", g.elbow_radius, "z", fa, sh, (0.0, 0.0)),
        _segment("forearm", "capsule", g.forearm_radius, "x", 0.0, a3, (0.0, fa)),
        _segment("wrist_1", "capsule", g.wrist_radius, "z", fa, d4, (0.0, 0.0)),
        _segment("wrist_2", "capsule", g.wrist_radius, "z", 0.0, d5, (0.0, 0.0)),
        _segment("wrist_3", "cylinder", g.wrist_radius, "z", 0.0, d6, (0.0, 0.0)),
    ]
