"""`Robot`: one UR arm by name: FK, Jacobians and link poses (pinocchio), analytic IK with joint-limit branches,
calibrated models (factory DH corrections, IK refined by Newton steps), collision geometry.

Frames: base = UR's DH frame 0 (the controller's base frame); flange = DH frame 6, the pose actual_TCP_pose
reports with a zero TCP offset. Joint angles in radians, lengths in metres.
"""

from __future__ import annotations

import itertools
import logging
import math
from dataclasses import dataclass, field
from functools import cached_property
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING, Literal

import numpy as np
import pinocchio as pin

from normpos_grasp.errors import InputError, NoIKSolution, RobotModelError
from normpos_grasp.kinematics.analytic_ik import (
    ACOS_SLACK,
    FAST_OK,
    SINGULAR_NEAR,
    dh_lengths,
    ik_batch,
    ik_single,
    ik_solve_nominal,
)
from normpos_grasp.kinematics.dh import DHCalibration, DHChain
from normpos_grasp.kinematics.gripper import Gripper
from normpos_grasp.kinematics.mjcf import arm_mjcf
from normpos_grasp.kinematics.shapes import ARM_LINKS, CollisionShape, arm_collision_shapes
from normpos_grasp.kinematics.ur_params import JOINT_NAMES, URParams, ur_params
from normpos_grasp.typing import ArrayLike, BoolArray, FloatArray
from normpos_grasp.validation import as_float_array

if TYPE_CHECKING:
    import mujoco

logger = logging.getLogger(__name__)

ROBOT_NAMES = ("ur3e", "ur5e", "ur10e", "ur16e", "ur20", "ur30")
_TWO_PI = 2.0 * math.pi
_CALIBRATED_SLACK = 0.05  # acos clamp for seeds of a calibrated arm (targets just outside the nominal workspace)
_SINGULAR_NEAR = SINGULAR_NEAR
_ZEROS6 = np.zeros(6)
_ZEROS6.setflags(write=False)


@dataclass(frozen=True)
class IKOptions:
    """Settings of `Robot.ik` / `Robot.ik_or_raise`.

    wrist_singularity_tol: ik_or_raise rejects solutions with |sin q5| below this (dimensionless; 1e-3 is
    0.057 deg from the singularity). newton_iterations / newton_tol: refinement on a calibrated model
    (tolerance on the 6-D pose error, metres / radians). dedupe_tol: solutions closer than this (radians,
    max-abs) are merged. all_branches: also return the +-2 pi copies of joints allowed to turn past +-pi.
    """

    wrist_singularity_tol: float = 1e-3
    newton_iterations: int = 30
    newton_tol: float = 1e-12
    dedupe_tol: float = 1e-9
    all_branches: bool = True


_DEFAULT_IK = IKOptions()


@dataclass(frozen=True)
class IKLabel:
    """Configuration of a solution. shoulder 'left': wrist centre on the -x side of the shoulder link frame
    (branch q1 = psi + pi/2 + phi); elbow 'up': elbow above the shoulder-wrist line (towards base +z);
    wrist 'noflip': sin q5 < 0 (UR's usual tool-down pose), 'flip' otherwise."""

    shoulder: Literal["left", "right"]
    elbow: Literal["up", "down"]
    wrist: Literal["flip", "noflip"]

    def __str__(self) -> str:
        return f"shoulder-{self.shoulder}/elbow-{self.elbow}/wrist-{self.wrist}"


@dataclass(frozen=True)
class SingularityDistance:
    """How far q is from each UR singularity: shoulder (m, wrist centre distance from the plane of joints 1-2
    axes), elbow (|sin q3|), wrist (|sin q5|), and the smallest singular value of the Jacobian."""

    shoulder_m: float
    elbow: float
    wrist: float
    min_singular_value: float


@dataclass
class _PinState:
    model: pin.Model
    data: pin.Data = field(init=False)
    flange_id: int = field(init=False)

    def __post_init__(self) -> None:
        self.data = self.model.createData()
        self.flange_id = self.model.getFrameId("flange")


def build_pinocchio_model(params: URParams, chain: DHChain) -> pin.Model:
    """Pinocchio model of the chain: revolute-z joints named per JOINT_NAMES, a BODY frame per link of
    ARM_LINKS ('base' on the universe) and the OP_FRAME 'flange'; limits and link masses from `params`."""
    model = pin.Model()
    model.name = params.name
    model.addFrame(pin.Frame("base", 0, 0, pin.SE3.Identity(), pin.FrameType.BODY))
    parent, placement = 0, np.eye(4)
    for i in range(6):
        se3 = pin.SE3(placement[:3, :3].copy(), placement[:3, 3].copy())
        limit = params.position_limit[i]
        lim = limit if math.isfinite(limit) else 1e10
        joint_id = model.addJoint(
            parent,
            pin.JointModelRZ(),
            se3,
            JOINT_NAMES[i],
            np.array([params.effort_limit[i]]),
            np.array([params.velocity_limit[i]]),
            np.array([-lim]),
            np.array([lim]),
        )
        mass = params.masses[i + 1]
        model.appendBodyToJoint(joint_id, pin.Inertia(mass, np.zeros(3), np.eye(3) * mass * 1e-3), pin.SE3.Identity())
        model.addFrame(
            pin.Frame(
                ARM_LINKS[i + 1],
                joint_id,
                model.getFrameId(JOINT_NAMES[i]) if i else 0,
                pin.SE3.Identity(),
                pin.FrameType.BODY,
            )
        )
        parent, placement = joint_id, chain.link_transform(i)
    flange = pin.SE3(placement[:3, :3].copy(), placement[:3, 3].copy())
    model.addFrame(pin.Frame("flange", parent, model.nframes - 1, flange, pin.FrameType.OP_FRAME))
    return model


class Robot:
    """A UR arm: load with `Robot.load('ur5e')` (optionally with factory calibration)."""

    def __init__(self, params: URParams, calibration: DHCalibration | None = None) -> None:
        self.params = params
        self.name = params.name
        self.calibration = calibration
        self.chain = DHChain.nominal(params, calibration)
        self._lengths = dh_lengths(params)
        self._lengths_arr = np.array(self._lengths, dtype=np.float64)
        self._pin = _PinState(build_pinocchio_model(params, self.chain))
        limits = np.array(params.position_limit)
        self._lower, self._upper = -limits, limits
        self._lower.setflags(write=False)
        self._upper.setflags(write=False)
        self._upper_list: list[float] = [float(v) for v in limits]
        # +-2 pi copies: with limits in (pi, 3 pi) each joint has at most one extra copy of a principal angle
        # (v - 2 pi sign v), so the branches are the 2^m on/off patterns of those m joints; wider limits take the
        # general path over every multiple of 2 pi.
        finite = np.isfinite(limits)
        self._branch_joints = np.flatnonzero(finite & (limits > math.pi))
        self._binary = bool(np.all(limits[finite] < 3 * math.pi))
        m = len(self._branch_joints)
        self._branch_bits = np.array(list(itertools.product((False, True), repeat=m)), dtype=bool).reshape(-1, m)
        per_joint = []
        for lim in limits:
            k = int(math.ceil(lim / _TWO_PI)) if math.isfinite(lim) else 0
            per_joint.append([i * _TWO_PI for i in range(-k, k + 1) if abs(i) * _TWO_PI < lim + math.pi])
        self._branch_offsets = np.array(list(itertools.product(*per_joint)))  # (C, 6), general path
        self._fast_ik = calibration is None and self._binary  # the compiled one-pose path applies

    @staticmethod
    def load(name: str, calibration: DHCalibration | str | Path | None = None) -> Robot:
        """The arm called `name` (ur3e, ur5e, ur10e, ur16e, ur20, ur30); `calibration`: DH corrections or the
        path of a calibration.conf-style file. Raises RobotModelError for unknown names."""
        cal = DHCalibration.from_conf(calibration) if isinstance(calibration, str | Path) else calibration
        return Robot(ur_params(name), cal)

    def __repr__(self) -> str:
        return f"Robot({self.name!r}{', calibrated' if self.calibration else ''})"

    # ----------------------------------------------------------------------------------------------- models
    @property
    def calibrated(self) -> bool:
        """True when factory DH corrections are applied."""
        return self.calibration is not None

    @property
    def pinocchio_model(self) -> pin.Model:
        """The pinocchio model (frames: ARM_LINKS and 'flange')."""
        return self._pin.model

    @property
    def mjcf_path(self) -> Path:
        """Path of the committed nominal MJCF file of this model (robots/<name>/<name>.xml)."""
        return Path(str(resources.files("normpos_grasp.robot_models") / self.name / f"{self.name}.xml"))

    @property
    def scene_path(self) -> Path:
        """Path of the committed scene file (robots/<name>/scene.xml)."""
        return Path(str(resources.files("normpos_grasp.robot_models") / self.name / "scene.xml"))

    def mjcf_xml(self, gripper: Gripper | None = None, opening_m: float | None = None) -> str:
        """MJCF text of this arm (the calibrated chain when calibrated), with `gripper` at the flange if given
        (body 'gripper', site 'tcp')."""
        return arm_mjcf(self.params, self.chain, gripper=gripper, opening_m=opening_m)

    def mujoco_model(self, gripper: Gripper | None = None, opening_m: float | None = None) -> mujoco.MjModel:
        """A fresh MuJoCo model of this arm (the committed file, or built from the calibrated chain or with a
        gripper attached: body 'gripper', site 'tcp')."""
        import mujoco

        if self.calibrated or gripper is not None:
            return mujoco.MjModel.from_xml_string(self.mjcf_xml(gripper, opening_m))
        if not self.mjcf_path.is_file():
            raise RobotModelError(
                f"{self.mjcf_path} is missing; regenerate with `python -m normpos_grasp.robot_models.generate`"
            )
        return mujoco.MjModel.from_xml_path(str(self.mjcf_path))

    # --------------------------------------------------------------------------------------------- limits
    @property
    def joint_limits(self) -> tuple[FloatArray, FloatArray]:
        """(lower (6,), upper (6,)) joint position limits, radians (inf where unlimited)."""
        return self._lower, self._upper

    @property
    def velocity_limits(self) -> FloatArray:
        """(6,) joint speed limits, rad/s."""
        return np.array(self.params.velocity_limit)

    def within_limits(self, q: ArrayLike, tol: float = 0.0) -> BoolArray:
        """Whether each configuration of q (..., 6) lies within the position limits (+- tol radians)."""
        qs = np.asarray(q, dtype=np.float64)
        return np.all((qs >= self._lower - tol) & (qs <= self._upper + tol), axis=-1)

    @cached_property
    def collision_geometry(self) -> list[CollisionShape]:
        """Capsules/cylinders per link; place each at link_poses(q)[shape.link] @ shape.link_from_shape."""
        return arm_collision_shapes(self.params)

    # --------------------------------------------------------------------------------------------- FK
    def _q(self, q: ArrayLike) -> FloatArray:
        arr = np.asarray(q, dtype=np.float64)
        if arr.shape != (6,) or not np.isfinite(arr).all():
            return as_float_array(q, "q", (6,))  # raises the detailed InputError
        return arr

    def fk(self, q: ArrayLike) -> FloatArray:
        """base_from_flange (4, 4) at joint angles q (6,), radians (pinocchio)."""
        st = self._pin
        pin.framesForwardKinematics(st.model, st.data, self._q(q))
        return np.array(st.data.oMf[st.flange_id].homogeneous)

    def fk_batch(self, qs: ArrayLike) -> FloatArray:
        """base_from_flange (N, 4, 4) for qs (N, 6) (vectorised DH chain, same model as `fk`)."""
        return self.chain.forward_kinematics(as_float_array(qs, "qs", (None, 6)))

    def link_poses(self, q: ArrayLike) -> dict[str, FloatArray]:
        """base_from_link (4, 4) of every link in ARM_LINKS plus 'flange', at q (6,)."""
        st = self._pin
        pin.framesForwardKinematics(st.model, st.data, self._q(q))
        names = (*ARM_LINKS, "flange")
        return {n: np.array(st.data.oMf[st.model.getFrameId(n)].homogeneous) for n in names}

    def jacobian(self, q: ArrayLike) -> FloatArray:
        """(6, 6) Jacobian of the flange at q: rows [v; w], v the linear velocity of the flange origin and w
        the angular velocity, both expressed in the base frame (pinocchio LOCAL_WORLD_ALIGNED)."""
        st = self._pin
        qq = self._q(q)
        pin.computeJointJacobians(st.model, st.data, qq)
        pin.framesForwardKinematics(st.model, st.data, qq)
        return np.array(pin.getFrameJacobian(st.model, st.data, st.flange_id, pin.LOCAL_WORLD_ALIGNED))

    def manipulability(self, q: ArrayLike) -> float:
        """Yoshikawa's measure sqrt(det(J J^T)) of the flange Jacobian (0 at a singularity), m^3.

        Computed as the product of J's singular values: the determinant of J J^T squares the rounding of a singular
        direction (1e-18 and more at an exact singularity, BLAS-dependent), the singular values do not.
        """
        return float(np.prod(np.linalg.svd(self.jacobian(q), compute_uv=False)))

    def singularity_distance(self, q: ArrayLike) -> SingularityDistance:
        """Distance of q (6,) from the shoulder, elbow and wrist singularities (see SingularityDistance)."""
        qq = self._q(q)
        poses = self.link_poses(qq)
        wrist_centre = poses["wrist_2"][:3, 3]
        shoulder = poses["shoulder"]
        x_local = float(shoulder[:3, 0] @ (wrist_centre - shoulder[:3, 3]))
        sv = np.linalg.svd(self.jacobian(qq), compute_uv=False)
        return SingularityDistance(abs(x_local), abs(math.sin(qq[2])), abs(math.sin(qq[4])), float(sv[-1]))

    def ik_labels(self, q: ArrayLike) -> IKLabel:
        """Shoulder/elbow/wrist configuration label of q (6,) (see IKLabel)."""
        qq = self._q(q)
        poses = self.link_poses(qq)
        sh = poses["shoulder"]
        wrist_centre = poses["wrist_2"][:3, 3]
        x_local = float(sh[:3, 0] @ (wrist_centre - sh[:3, 3]))
        s_origin = poses["upper_arm"][:3, 3]
        elbow = poses["forearm"][:3, 3]
        line = wrist_centre - s_origin
        normal = poses["upper_arm"][:3, 2]
        up = np.cross(normal, line)  # in the arm plane, perpendicular to the shoulder-wrist line
        if up[2] < 0 or (abs(up[2]) < 1e-12 and float(up @ sh[:3, 0]) < 0):
            up = -up
        return IKLabel(
            "left" if x_local < 0 else "right",
            "up" if float(up @ (elbow - s_origin)) >= 0 else "down",
            "noflip" if math.sin(qq[4]) < 0 else "flip",
        )

    # --------------------------------------------------------------------------------------------- IK
    def _check_target(self, base_from_flange: ArrayLike) -> FloatArray:
        pose = np.asarray(base_from_flange, dtype=np.float64)
        if pose.shape != (4, 4) or not np.isfinite(pose).all():
            raise InputError(f"base_from_flange: expected a finite (4, 4) pose, got shape {pose.shape}")
        (r00, r01, r02, _), (r10, r11, r12, _), (r20, r21, r22, _), last = pose.tolist()
        # columns orthonormal and z = x cross y (a proper rotation), in scalar math (numpy calls cost ~us each)
        err = max(
            abs(r00 * r00 + r10 * r10 + r20 * r20 - 1.0),
            abs(r01 * r01 + r11 * r11 + r21 * r21 - 1.0),
            abs(r00 * r01 + r10 * r11 + r20 * r21),
            abs(r10 * r21 - r20 * r11 - r02),
            abs(r20 * r01 - r00 * r21 - r12),
            abs(r00 * r11 - r10 * r01 - r22),
        )
        if err > 1e-6 or last != [0.0, 0.0, 0.0, 1.0]:
            raise InputError(
                f"base_from_flange: rotation block is not a proper rotation (error {err:.2e}) or the last row "
                f"{last} is not [0, 0, 0, 1]"
            )
        return pose

    def _principal(
        self, pose: FloatArray, q6_default: float, options: IKOptions, near: FloatArray | None = None
    ) -> tuple[FloatArray, str]:
        """Distinct principal solutions (k, 6) in (-pi, pi]. Refined by Newton steps on the calibrated chain,
        or on the nominal one near a singularity, where acos/atan2 lose digits (errors up to ~1e-8)."""
        slack = _CALIBRATED_SLACK if self.calibrated else ACOS_SLACK
        sols, reason = ik_single(self._lengths, pose.tolist(), q6_default, slack)
        found = [s for s in sols if s is not None]
        if self.calibrated and near is not None:
            found.append(tuple(near))  # near the nominal workspace boundary two branches share one clamped seed
        if not found:
            return np.empty((0, 6)), reason
        q = np.array(found)
        if self.calibrated:
            q, ok = self._refine(q, pose, options)
            q = q[ok]
            if q.shape[0] == 0:
                nominal = ik_single(self._lengths, pose.tolist(), q6_default)[1]
                return q, nominal or "not_converged"  # outside even the nominal workspace: out_of_reach
            q = q - _TWO_PI * np.round(q / _TWO_PI)
        else:
            d4, d6 = self._lengths[3], self._lengths[5]
            r = math.hypot(pose[0, 3] - d6 * pose[0, 2], pose[1, 3] - d6 * pose[1, 2])
            shoulder = math.acos(min(1.0, d4 / r)) < _SINGULAR_NEAR
            polish = [
                shoulder or abs(math.sin(s[2])) < _SINGULAR_NEAR or abs(math.sin(s[4])) < _SINGULAR_NEAR for s in found
            ]
            if not any(polish):
                return q, ""  # regular pose: the 8 branches are distinct, no polishing or dedupe needed
            flags = np.array(polish)
            refined, ok = self._refine(q[flags], pose, options)
            q[flags] = refined
            keep = np.ones(len(q), dtype=bool)
            keep[np.flatnonzero(flags)[~ok]] = False  # clamped acos seeds of a pose just out of reach
            q = q[keep]
            q = q - _TWO_PI * np.round(q / _TWO_PI)
            if len(q) == 0:
                return q, "out_of_reach"
        if len(q) > 1:
            close = np.abs(q[:, None, :] - q[None, :, :]).max(axis=2) <= options.dedupe_tol
            close[np.tril_indices(len(q))] = False
            q = q[~close.any(axis=0)]  # drop copies of an earlier solution (at singular boundaries)
        return q, ""

    def _refine(self, seeds: FloatArray, target: FloatArray, options: IKOptions) -> tuple[FloatArray, BoolArray]:
        """Gauss-Newton steps (least squares: safe at singular Jacobians) from each seed (k, 6) on this robot's
        chain; returns the refined configurations and whether each converged to options.newton_tol."""
        st = self._pin
        goal = pin.SE3(target[:3, :3].copy(), target[:3, 3].copy())
        out = seeds.copy()
        ok = np.zeros(len(seeds), dtype=bool)
        for k, seed in enumerate(seeds):
            q = seed.copy()
            for _ in range(options.newton_iterations + 1):
                pin.framesForwardKinematics(st.model, st.data, q)
                err = pin.log6(st.data.oMf[st.flange_id].actInv(goal)).vector
                if np.abs(err).max() < options.newton_tol:
                    ok[k] = True
                    break
                jac = pin.computeFrameJacobian(st.model, st.data, q, st.flange_id, pin.LOCAL)
                q = q + np.linalg.lstsq(jac, err, rcond=1e-10)[0]
            else:
                ok[k] = bool(np.abs(err).max() < 1e3 * options.newton_tol)
            out[k] = q
        return out, ok

    def _branches(self, q: FloatArray, q_near: FloatArray | None, all_branches: bool) -> FloatArray:
        """Expand principal solutions (k, 6) into every +-2 pi copy inside the limits (or the copy nearest
        q_near when all_branches is False); unlimited joints take the copy nearest q_near."""
        if q.shape[0] == 0:
            return q
        ref = q_near if q_near is not None else np.zeros(6)
        unlimited = ~np.isfinite(self._upper)
        if unlimited.any():
            q = q.copy()
            q[:, unlimited] += _TWO_PI * np.round((ref[unlimited] - q[:, unlimited]) / _TWO_PI)
        if self._binary:  # limits are symmetric (+-position_limit)
            jj = self._branch_joints
            principal = q[:, jj]
            alternative = principal - np.copysign(_TWO_PI, principal)
            alt_ok = np.abs(alternative) <= self._upper[jj]
            base_ok = np.all(np.abs(q) <= self._upper, axis=1)
            if not all_branches:  # distance is separable per joint: pick each joint's nearest valid copy
                use_alt = alt_ok & (np.abs(alternative - ref[jj]) < np.abs(principal - ref[jj]))
                out = q.copy()
                out[:, jj] = np.where(use_alt, alternative, principal)
                return out[base_ok]
            bits = self._branch_bits
            valid = base_ok[:, None] & ~np.any(bits[None] & ~alt_ok[:, None, :], axis=2)  # (k, C)
            cand = np.repeat(q[:, None, :], len(bits), axis=1)  # (k, C, 6)
            cand[:, :, jj] = np.where(bits[None], alternative[:, None, :], principal[:, None, :])
            return cand[valid]
        cand = q[:, None, :] + self._branch_offsets[None, :, :]
        ok = np.all((cand >= self._lower - 1e-12) & (cand <= self._upper + 1e-12), axis=2)
        if not all_branches:
            dist = np.linalg.norm(cand - ref, axis=2)
            dist[~ok] = np.inf
            best = np.argmin(dist, axis=1)
            keep = np.isfinite(dist[np.arange(q.shape[0]), best])
            return np.clip(cand[np.arange(q.shape[0]), best][keep], self._lower, self._upper)
        return np.clip(cand[ok], self._lower, self._upper)  # removes the 1e-12 slack

    def _nearest_copies(self, q: FloatArray, near: FloatArray | None) -> FloatArray:
        """Scalar-math twin of `_branches(q, near, False)` for (pi, 3 pi) limits, sorted by distance to near
        (numpy calls cost microseconds each; this path runs per pose inside planners)."""
        ref = [0.0] * 6 if near is None else near.tolist()
        limits = self._upper_list
        rows: list[tuple[float, list[float]]] = []
        for sol in q.tolist():
            row = []
            for j in range(6):
                v, lim, r = sol[j], limits[j], ref[j]
                if lim == math.inf:
                    v += _TWO_PI * round((r - v) / _TWO_PI)
                elif lim > math.pi:
                    alt = v - math.copysign(_TWO_PI, v)
                    if abs(alt) <= lim and abs(alt - r) < abs(v - r):
                        v = alt
                if abs(v) > lim:
                    break
                row.append(v)
            else:
                rows.append((sum((a - b) * (a - b) for a, b in zip(row, ref, strict=True)), row))
        rows.sort(key=lambda item: item[0])
        return np.array([row for _, row in rows], dtype=np.float64).reshape(-1, 6)

    def ik(
        self, base_from_flange: ArrayLike, q_near: ArrayLike | None = None, options: IKOptions | None = None
    ) -> FloatArray:
        """All IK solutions (k, 6) of a base_from_flange pose inside the joint limits, sorted by Euclidean
        joint distance to q_near (6,) (to zeros when None). Up to 8 analytic solutions, each with its +-2 pi
        copies (options.all_branches). Empty (0, 6) when unreachable; `ik_or_raise` says why.

        The nominal model away from singularities takes a compiled path (`analytic_ik.ik_solve_nominal`, a few
        microseconds); a calibrated model, and poses within 1e-5 of a singularity (Newton-polished), take
        `_ik_python`. Both give the same solutions in the same order."""
        opts = options or _DEFAULT_IK
        if self._fast_ik:
            pose = np.asarray(base_from_flange, dtype=np.float64)
            if q_near is None:
                near = _ZEROS6
            else:
                near = np.asarray(q_near, dtype=np.float64)
                if near.shape != (6,):
                    near = self._q(q_near)  # raises the detailed InputError
            if pose.shape == (4, 4):
                sols, status = ik_solve_nominal(self._lengths_arr, pose, near, self._upper, opts.all_branches)
                if status == FAST_OK:
                    return sols
        return self._ik_python(base_from_flange, q_near, opts)

    def _ik_python(self, base_from_flange: ArrayLike, q_near: ArrayLike | None, opts: IKOptions) -> FloatArray:
        """`ik` in Python and numpy (every model and pose; Newton polish near singularities)."""
        pose = self._check_target(base_from_flange)
        near = None if q_near is None else self._q(q_near)
        q6 = 0.0 if near is None else float(near[5])
        principal, _ = self._principal(pose, q6, opts, near)
        if not opts.all_branches and self._binary:
            return self._nearest_copies(principal, near)
        sols = self._branches(principal, near, opts.all_branches)
        diff = sols - (near if near is not None else 0.0)
        return sols[np.argsort(np.einsum("ij,ij->i", diff, diff), kind="stable")]

    def ik_or_raise(
        self, base_from_flange: ArrayLike, q_near: ArrayLike | None = None, options: IKOptions | None = None
    ) -> FloatArray:
        """Like `ik`, without solutions within options.wrist_singularity_tol of the wrist singularity, and
        raising NoIKSolution(reason=out_of_reach | joint_limits | wrist_singularity | not_converged)."""
        opts = options or _DEFAULT_IK
        if self._fast_ik:
            sols = self.ik(base_from_flange, q_near, opts)
            good = np.abs(np.sin(sols[:, 4])) >= opts.wrist_singularity_tol
            if good.any():
                return sols[good]  # sorted by distance; the failure reasons come from the path below
        pose = self._check_target(base_from_flange)
        near = None if q_near is None else self._q(q_near)
        principal, reason = self._principal(pose, 0.0 if near is None else float(near[5]), opts, near)
        if principal.shape[0] == 0:
            if reason == "not_converged":
                raise NoIKSolution(
                    f"{self.name}: analytic seeds did not converge on the calibrated model within "
                    f"{opts.newton_iterations} Newton steps; check the calibration deltas",
                    "not_converged",
                    pose,
                )
            dist = float(np.linalg.norm(pose[:3, 3]))
            raise NoIKSolution(
                f"{self.name}: flange target at {np.round(pose[:3, 3], 4).tolist()} m ({dist:.3f} m from the base "
                f"origin) is out of reach (nominal reach {self.params.reach_m} m, and the wrist centre must stay "
                f"more than d4={self.params.d[3]} m from the base axis); move the target closer",
                "out_of_reach",
                pose,
            )
        sols = self._branches(principal, near, opts.all_branches)
        if sols.shape[0] == 0:
            raise NoIKSolution(
                f"{self.name}: {principal.shape[0]} geometric solutions exist but none within the joint limits "
                f"{self._upper.round(3).tolist()} rad; rotate the target about the flange axis or relax limits",
                "joint_limits",
                pose,
            )
        good = np.abs(np.sin(sols[:, 4])) >= opts.wrist_singularity_tol
        if not good.any():
            raise NoIKSolution(
                f"{self.name}: every solution has |sin q5| < {opts.wrist_singularity_tol} (wrist singularity: "
                "joints 4 and 6 aligned); tilt the tool or change the approach direction",
                "wrist_singularity",
                pose,
            )
        sols = sols[good]
        ref = near if near is not None else np.zeros(6)
        return sols[np.argsort(np.linalg.norm(sols - ref, axis=1), kind="stable")]

    def ik_batch(self, base_from_flange: ArrayLike, q6_default: float = 0.0) -> tuple[FloatArray, BoolArray]:
        """Vectorised principal solutions for poses (N, 4, 4): q (N, 8, 6) in (-pi, pi] (NaN where invalid)
        and valid (N, 8), solution index 4*shoulder + 2*wrist + elbow. Nominal model only (joint limits
        not applied); a calibrated robot raises RobotModelError (use `ik` per pose)."""
        if self.calibrated:
            raise RobotModelError("ik_batch solves the nominal model only; use ik() on a calibrated robot")
        poses = as_float_array(base_from_flange, "base_from_flange", (None, 4, 4))
        return ik_batch(self._lengths, poses, q6_default)
