"""Template records: `Template` (mesh, control points, symmetry, grasps) and `TemplateFit`."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from normpos_grasp.errors import FrameError, InputError
from normpos_grasp.geometry.transforms import make_pose, rotation_from_rotvec
from normpos_grasp.records.kinds import FRAMES, Frame
from normpos_grasp.typing import FloatArray

if TYPE_CHECKING:
    import trimesh

SHAPE_CLASSES = ("box", "cylinder", "sphere", "plate", "bracket", "ring", "irregular")


@dataclass(frozen=True, eq=False)
class Symmetry:
    """Object symmetries in the object frame.

    continuous: tuples (axis (3,), point (3,)) of axes about which any rotation maps the object onto itself.
    discrete: (K, 4, 4) object_from_object transforms (identity excluded) that map it onto itself.
    """

    continuous: tuple[tuple[FloatArray, FloatArray], ...] = ()
    discrete: tuple[FloatArray, ...] = ()

    def transforms(self, continuous_steps: int = 36) -> FloatArray:
        """(M, 4, 4) symmetry transforms including the identity; continuous axes sampled in `continuous_steps`.

        With one continuous axis the discrete set is combined with each sampled rotation (for example a
        cylinder's flip); with two or more (a sphere) rotations about the first two axes are combined.
        """
        base = [np.eye(4)] + [np.asarray(t, dtype=np.float64) for t in self.discrete]
        rotations = [np.eye(4)]
        for axis, point in self.continuous[:2]:
            a = np.asarray(axis, dtype=np.float64)
            a = a / np.linalg.norm(a)
            p = np.asarray(point, dtype=np.float64)
            step = []
            for k in range(continuous_steps):
                rot = rotation_from_rotvec(a * (2 * np.pi * k / continuous_steps))
                step.append(make_pose(rot, p - rot @ p))
            rotations = [r @ s for r in rotations for s in step]
        return np.stack([r @ b for r in rotations for b in base])

    @property
    def is_symmetric(self) -> bool:
        return bool(self.continuous or self.discrete)


@dataclass(frozen=True, eq=False)
class GraspAnnotation:
    """A pick frame annotated on a template.

    object_from_tcp: (4, 4) TCP pose in the object frame; the TCP z axis is the approach direction
        (pointing from the gripper into the object), x the jaw closing direction for parallel grippers.
    scheme: 'parallel' or 'suction'. opening_m: jaw opening before closing (parallel), metres.
    priority: higher is preferred. approach_m / retreat_m: straight-line distances along -z before and
    after the grasp. free_axis: axis (object frame) about which the grasp may rotate freely (symmetry), or None.
    tilt_cone_rad: allowed tilt of the approach axis around its nominal direction.
    """

    id: str
    scheme: str
    object_from_tcp: FloatArray
    opening_m: float = 0.0
    priority: float = 0.0
    approach_m: float = 0.08
    retreat_m: float = 0.1
    free_axis: FloatArray | None = None
    tilt_cone_rad: float = 0.0


@dataclass(frozen=True, eq=False)
class Template:
    """A known-structure CAD template, in metres in its own object frame.

    name: unique id. label: class name that segmenters report. mesh: watertight trimesh.Trimesh (metres).
    control_points: name -> (3,) position (metres, object frame). shape: one of SHAPE_CLASSES (drives
    automatic grasp synthesis). mass_kg / material: for physics and payload checks.
    source: where it was loaded from. obj_id: BOP object id (-1 when none). units: the units the file
    declared ('mm' or 'm'; the mesh here is always metres). report: the `MeshReport` of its mesh check, if any.
    """

    name: str
    label: str
    mesh: trimesh.Trimesh
    control_points: dict[str, FloatArray] = field(default_factory=dict)
    symmetry: Symmetry = field(default_factory=Symmetry)
    grasps: tuple[GraspAnnotation, ...] = ()
    shape: str = "irregular"
    mass_kg: float = 0.1
    material: str = ""
    source: str = ""
    obj_id: int = -1
    units: str = "m"
    report: Any = None

    @property
    def diameter_m(self) -> float:
        """Largest distance between two mesh vertices (the BOP 'diameter'), metres."""
        v = np.asarray(self.mesh.convex_hull.vertices)
        d = np.linalg.norm(v[:, None, :] - v[None, :, :], axis=-1)
        return float(d.max())

    @property
    def extents_m(self) -> FloatArray:
        """(3,) axis-aligned extents of the mesh in the object frame, metres."""
        return np.asarray(self.mesh.extents, dtype=np.float64)


@dataclass(frozen=True, eq=False)
class TemplateFit:
    """Result of fitting a template to one norm-position.

    frame_from_object: (4, 4) pose in `frame`, the norm-position's frame: 'world' when the camera had extrinsics,
    else 'camera'. `world_from_object` returns it only for a world-frame fit and raises FrameError otherwise, so
    a camera-frame pose can never be taken for a world pose.
    score in [0, 1]; rmse_m: inlier point-to-surface RMS, metres; inlier_ratio: share of measured points
    within the inlier distance; coverage: share of the template's camera-visible surface that was measured;
    free_space_violation: share of the template's visible surface lying in front of measured depth;
    scale: size factor fitted (1.0 = CAD size; parts up to 5 % off are tolerated and reported).
    accepted: whether the fit passed acceptance; reason: why it was rejected ('' when accepted).
    """

    template: Template
    frame_from_object: FloatArray
    score: float
    rmse_m: float
    inlier_ratio: float
    coverage: float
    free_space_violation: float
    accepted: bool
    reason: str = ""
    scale: float = 1.0
    frame: Frame = "world"
    instance_id: int = 0
    time_s: float = 0.0
    extra: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.frame not in FRAMES:
            raise InputError(f"a fit's frame is 'world' or 'camera', got {self.frame!r}")

    @property
    def world_from_object(self) -> FloatArray:
        """(4, 4) pose in the world frame; FrameError for a fit made in the camera frame (no extrinsics)."""
        if self.frame != "world":
            raise FrameError(
                f"the fit of {self.template.name!r} is in the {self.frame} frame (the camera had no "
                "world_from_camera): calibrate extrinsics, or use frame_from_object"
            )
        return self.frame_from_object
