"""`ArmModel`: the arm as the planner sees it: UR DH kinematics, batched analytic IK over all 8 branches, link
frames and conservative link capsules for collision checks.

The planner evaluates hundreds of candidate poses at once, so IK here is vectorised over poses (numpy, no Python
loop per pose). When the kinematics stage's `Robot` supplies link collision geometry it is used instead of the
capsules derived from the DH table.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from normpos_grasp.errors import InputError
from normpos_grasp.geometry.transforms import invert_pose
from normpos_grasp.kinematics.analytic_ik import SINGULAR_SIN, dh_lengths, ik_batch
from normpos_grasp.kinematics.shapes import ARM_LINKS, arm_collision_shapes
from normpos_grasp.kinematics.ur_params import DH_ALPHA, URParams, dh_forward_kinematics, dh_link, ur_params
from normpos_grasp.typing import ArrayLike, BoolArray, FloatArray

_COS_ALPHA = tuple(math.cos(a) for a in DH_ALPHA)
_SIN_ALPHA = tuple(0.0 if abs(math.sin(a)) < 1e-15 else math.sin(a) for a in DH_ALPHA)
_COS_ALPHA = tuple(0.0 if abs(c) < 1e-15 else c for c in _COS_ALPHA)


@dataclass(frozen=True)
class LinkShape:
    """One collision shape of the arm: `kind` 'capsule' (size = radius, length along z), 'box' (size = full
    extents), 'sphere' (size = radius) or 'cylinder' (radius, length); `link_from_shape` (4, 4); `joint` is the
    index of the DH frame (0 = base, 6 = flange) the link rides on."""

    link: str
    kind: str
    size: tuple[float, ...]
    link_from_shape: FloatArray
    joint: int


@dataclass(frozen=True, eq=False)
class ArmModel:
    """A UR arm in the cell: DH parameters, `world_from_base` (4, 4), joint limits (rad), velocity limits (rad/s),
    and link collision shapes. Build with `ArmModel.from_name('ur5e', world_from_base)`."""

    params: URParams
    world_from_base: FloatArray
    lower: FloatArray
    upper: FloatArray
    velocity_limits: FloatArray
    shapes: tuple[LinkShape, ...]
    adjacent: frozenset[tuple[int, int]] = field(default_factory=frozenset)

    @property
    def name(self) -> str:
        return self.params.name

    @classmethod
    def from_name(cls, name: str, world_from_base: ArrayLike | None = None) -> ArmModel:
        """Arm for UR model `name` ('ur5e', ...) mounted at `world_from_base` (identity by default)."""
        params = ur_params(name)
        pose = np.eye(4) if world_from_base is None else np.asarray(world_from_base, dtype=np.float64)
        limit = np.minimum(np.asarray(params.position_limit, dtype=np.float64), 2 * np.pi)
        shapes = _kinematics_shapes(params)
        return cls(
            params=params,
            world_from_base=pose,
            lower=-limit,
            upper=limit,
            velocity_limits=np.asarray(params.velocity_limit, dtype=np.float64),
            shapes=shapes,
            adjacent=frozenset({(i, i + 1) for i in range(6)} | {(i, i + 2) for i in range(5)} | {(3, 6), (4, 6)}),
        )

    def fk(self, q: ArrayLike) -> FloatArray:
        """world_from_flange (..., 4, 4) for joint angles q (..., 6), radians."""
        return self.world_from_base @ dh_forward_kinematics(self.params, q)

    def frames(self, q: ArrayLike) -> FloatArray:
        """(..., 7, 4, 4) world_from_frame_i for DH frames 0 (base) .. 6 (flange)."""
        qs = np.asarray(q, dtype=np.float64)
        if qs.shape == (6,):
            return self._frames_single(qs)
        out = np.empty(qs.shape[:-1] + (7, 4, 4))
        pose = np.broadcast_to(self.world_from_base, qs.shape[:-1] + (4, 4)).copy()
        out[..., 0, :, :] = pose
        for i in range(6):
            pose = pose @ dh_link(self.params, i, qs[..., i])
            out[..., i + 1, :, :] = pose
        return out

    def _frames_single(self, q: FloatArray) -> FloatArray:
        """Fast path of `frames` for one configuration (scalar trig, one small matmul per joint)."""
        out = np.empty((7, 4, 4))
        pose = self.world_from_base
        out[0] = pose
        p = self.params
        for i in range(6):
            ct, st = math.cos(q[i]), math.sin(q[i])
            ca, sa = _COS_ALPHA[i], _SIN_ALPHA[i]
            link = np.array(
                [
                    [ct, -st * ca, st * sa, p.a[i] * ct],
                    [st, ct * ca, -ct * sa, p.a[i] * st],
                    [0.0, sa, ca, p.d[i]],
                    [0.0, 0.0, 0.0, 1.0],
                ]
            )
            pose = pose @ link
            out[i + 1] = pose
        return out

    def ik(self, world_from_flange: ArrayLike, q_ref: ArrayLike | None = None) -> tuple[FloatArray, BoolArray]:
        """All analytic IK branches for (N, 4, 4) flange poses in the world.

        Returns (q (N, 8, 6) radians, ok (N, 8) bool): each branch is wrapped by multiples of 2 pi to the
        solution inside the joint limits closest to `q_ref` (zeros by default); ok is False where the branch
        does not exist (out of reach, wrist singularity) or no wrap fits the limits (see `ik_reasons`).
        """
        poses = np.asarray(world_from_flange, dtype=np.float64).reshape(-1, 4, 4)
        base_from_flange = invert_pose(self.world_from_base) @ poses
        q, exists = _ur_ik(self.params, base_from_flange)
        ref = np.zeros(6) if q_ref is None else np.asarray(q_ref, dtype=np.float64)
        q, in_limits = self.wrap_to_limits(q, ref)
        return q, exists & in_limits

    def ik_reasons(self, world_from_flange: ArrayLike) -> tuple[FloatArray, BoolArray, BoolArray]:
        """Like `ik`, but returns (q (N, 8, 6), exists (N, 8), in_limits (N, 8)) to tell 'ik' from 'joint_limits'."""
        poses = np.asarray(world_from_flange, dtype=np.float64).reshape(-1, 4, 4)
        q, exists = _ur_ik(self.params, invert_pose(self.world_from_base) @ poses)
        q, in_limits = self.wrap_to_limits(q, np.zeros(6))
        return q, exists, in_limits & exists

    def wrap_to_limits(self, q: FloatArray, q_ref: FloatArray) -> tuple[FloatArray, BoolArray]:
        """Shift each angle by k 2 pi to the value closest to q_ref inside the limits; (q, all-joints-ok)."""
        two_pi = 2 * np.pi
        best = q + two_pi * np.round((q_ref - q) / two_pi)
        ok = (best >= self.lower - 1e-9) & (best <= self.upper + 1e-9)
        for shift in (-two_pi, two_pi):
            alt = best + shift
            alt_ok = (alt >= self.lower - 1e-9) & (alt <= self.upper + 1e-9)
            take = ~ok & alt_ok
            best = np.where(take, alt, best)
            ok = ok | alt_ok
        return best, np.all(ok, axis=-1)

    def within_limits(self, q: ArrayLike) -> bool:
        qs = np.asarray(q, dtype=np.float64)
        return bool(np.all(qs >= self.lower - 1e-9) and np.all(qs <= self.upper + 1e-9))

    def shape_poses(self, q: ArrayLike, frames: FloatArray | None = None) -> list[FloatArray]:
        """World poses (4, 4) of `shapes` at configuration q (6,) (pass `frames` from `frames(q)` to reuse)."""
        f = self.frames(q) if frames is None else frames
        return [f[s.joint] @ s.link_from_shape for s in self.shapes]


def _kinematics_shapes(params: URParams) -> tuple[LinkShape, ...]:
    """The kinematics stage's link primitives (`arm_collision_shapes`) re-expressed in DH frames.

    Link i (1..6) is DH frame i-1 rotated by q_i about z, i.e. DH frame i times inv(Tz(d_i) Tx(a_i) Rx(alpha_i));
    the base link is DH frame 0."""
    out = []
    for shape in arm_collision_shapes(params):
        i = ARM_LINKS.index(shape.link)
        if i == 0:
            pose = np.asarray(shape.link_from_shape, dtype=np.float64)
        else:
            fixed = dh_link(params, i - 1, np.zeros(()))  # Tz(d) Tx(a) Rx(alpha) at q = 0
            pose = invert_pose(fixed) @ np.asarray(shape.link_from_shape, dtype=np.float64)
        out.append(LinkShape(shape.link, shape.kind, tuple(float(v) for v in shape.size), pose, i))
    return tuple(out)


def _ur_ik(params: URParams, base_from_flange: FloatArray) -> tuple[FloatArray, BoolArray]:
    """All 8 analytic IK branches of (N, 4, 4) flange poses (kinematics.analytic_ik.ik_batch): (N, 8, 6) angles
    in (-pi, pi] and (N, 8) existence flags; wrist-singular branches count as not existing (q6 is arbitrary there).
    Branch k: shoulder bit 2, wrist bit 1, elbow bit 0."""
    q, ok = ik_batch(dh_lengths(params), base_from_flange)
    ok &= np.abs(np.sin(np.nan_to_num(q[..., 4]))) >= SINGULAR_SIN
    q = np.where(ok[..., None], q, 0.0)
    q = (q + np.pi) % (2 * np.pi) - np.pi
    # numerical guard: keep only branches whose FK reproduces the pose (drops near-singular garbage)
    fk = dh_forward_kinematics(params, q)
    ok &= np.abs(fk[..., :3, :] - base_from_flange[:, None, :3, :]).max(axis=(-2, -1)) < 1e-7
    return q, ok


def invert_batch(poses: FloatArray) -> FloatArray:
    """Inverse of rigid poses (..., 4, 4)."""
    rot_t = np.swapaxes(poses[..., :3, :3], -1, -2)
    out = np.zeros_like(poses)
    out[..., :3, :3] = rot_t
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", rot_t, poses[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def check_joint_vector(q: ArrayLike, name: str = "q") -> FloatArray:
    arr = np.asarray(q, dtype=np.float64)
    if arr.shape != (6,):
        raise InputError(f"{name}: expected 6 joint angles in radians, got shape {arr.shape}")
    return arr
