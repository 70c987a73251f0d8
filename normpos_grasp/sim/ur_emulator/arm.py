"""Kinematic simulation of a UR arm stepped at a fixed period: joint moves, linear moves, speed/servo control, stops.

No network and no threads: `SimulatedArm.step()` advances one period. The loopback controller and the SimDriver
both drive this class, so they share timing behaviour. Moves follow UR's conventions: `movej` is a synchronised
trapezoidal profile limited by the leading joint's speed and acceleration; `movel` is a straight TCP line
(position lerp + rotation slerp) with a trapezoidal profile on its length, solved to joints by IK every period.
"""

from __future__ import annotations

import abc
import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from normpos_grasp.errors import NoIKSolution, SimulationError
from normpos_grasp.geometry.transforms import pose_from_ur, pose_to_ur, rotation_from_rotvec, rotation_to_rotvec
from normpos_grasp.kinematics.ur_params import URParams, dh_forward_kinematics
from normpos_grasp.typing import FloatArray

log = logging.getLogger(__name__)

IKSolver = Callable[[FloatArray, FloatArray], FloatArray]
"""ik(base_from_flange (4, 4), q_near (6,)) -> (k, 6) solutions sorted by distance to q_near."""

PROTECTIVE_STOP_DECEL = 10.0  # rad/s^2, deceleration of a protective (category 2) stop


def trapezoid(distance: float, v: float, a: float) -> tuple[float, float]:
    """(total time s, cruise speed) of a rest-to-rest trapezoidal profile over `distance` with caps v, a."""
    if distance <= 0.0:
        return 0.0, 0.0
    v = max(v, 1e-9)
    a = max(a, 1e-9)
    if distance * a < v * v:  # triangle: never reaches v
        v_peak = math.sqrt(distance * a)
        return 2.0 * v_peak / a, v_peak
    return distance / v + v / a, v


def trapezoid_s(t: float, distance: float, v_cruise: float, a: float, total: float) -> float:
    """Distance travelled at time t along the profile from `trapezoid` (clamped to [0, distance])."""
    if t <= 0.0 or distance <= 0.0:
        return 0.0
    if t >= total:
        return distance
    t_acc = v_cruise / a
    if t < t_acc:
        return 0.5 * a * t * t
    if t > total - t_acc:
        tr = total - t
        return distance - 0.5 * a * tr * tr
    return 0.5 * a * t_acc * t_acc + v_cruise * (t - t_acc)


class Motion(abc.ABC):
    """One motion primitive; `advance(arm, dt)` sets the arm's next joint target, returns True when finished."""

    progress: int = 0

    @abc.abstractmethod
    def advance(self, arm: SimulatedArm, dt: float) -> bool:
        """Advance by `dt` seconds."""


class JointMove(Motion):
    """movej: synchronised trapezoid in joint space from the current joints to `q_goal`."""

    def __init__(self, q_start: FloatArray, q_goal: FloatArray, speed: float, accel: float) -> None:
        self.q0 = np.array(q_start, dtype=np.float64)
        self.dq = np.array(q_goal, dtype=np.float64) - self.q0
        self.distance = float(np.max(np.abs(self.dq)))
        self.accel = accel
        self.total, self.v = trapezoid(self.distance, speed, accel)
        self.t = 0.0

    def advance(self, arm: SimulatedArm, dt: float) -> bool:
        self.t += dt
        if self.distance == 0.0:
            arm.set_joint_target(self.q0 + self.dq, dt)
            return True
        s = trapezoid_s(self.t, self.distance, self.v, self.accel, self.total)
        arm.set_joint_target(self.q0 + self.dq * (s / self.distance), dt)
        return self.t >= self.total


class LinearMove(Motion):
    """movel: straight TCP line; profile on translation length (m) or, for pure rotations, on the angle (rad)."""

    def __init__(self, arm: SimulatedArm, tcp_goal: FloatArray, speed: float, accel: float) -> None:
        if arm.ik is None:
            raise SimulationError(
                "movel needs an IK solver: normpos_grasp.kinematics.Robot.load(model).ik was not importable; "
                "use movej or install the kinematics module"
            )
        arm.solve_tcp(tcp_goal)  # the goal must be reachable (analytic IK) before the move starts
        start = arm.base_from_tcp()
        self.p0 = start[:3, 3].copy()
        self.dp = tcp_goal[:3, 3] - self.p0
        self.r0 = start[:3, :3].copy()
        self.drot = rotation_to_rotvec(self.r0.T @ tcp_goal[:3, :3])
        self.distance = float(np.linalg.norm(self.dp))
        angle = float(np.linalg.norm(self.drot))
        if self.distance < 1e-6:
            self.distance = angle
        self.accel = accel
        self.total, self.v = trapezoid(self.distance, speed, accel)
        self.t = 0.0

    def pose_at(self, fraction: float) -> FloatArray:
        pose = np.eye(4)
        pose[:3, :3] = self.r0 @ rotation_from_rotvec(self.drot * fraction)
        pose[:3, 3] = self.p0 + self.dp * fraction
        return pose

    def advance(self, arm: SimulatedArm, dt: float) -> bool:
        self.t += dt
        frac = 1.0 if self.distance == 0.0 else trapezoid_s(self.t, self.distance, self.v, self.accel, self.total)
        frac = frac / self.distance if self.distance > 0.0 else 1.0
        target = self.pose_at(frac)
        q = arm.track_tcp(target)
        reached = arm.base_from_tcp(q)
        if np.linalg.norm(reached[:3, 3] - target[:3, 3]) > 1e-4:
            raise NoIKSolution(
                "linear move cannot follow its line here (singularity or workspace edge)", reason="wrist_singularity"
            )
        arm.set_joint_target(q, dt)
        return self.t >= self.total


class PathMove(Motion):
    """A sequence of movej/movel entries run one after another (blend radii are run as exact stops)."""

    def __init__(self, entries: Sequence[tuple[str, FloatArray, float, float]]) -> None:
        self.entries = list(entries)
        self.index = 0
        self.current: Motion | None = None

    def advance(self, arm: SimulatedArm, dt: float) -> bool:
        while self.index < len(self.entries):
            if self.current is None:
                kind, target, v, a = self.entries[self.index]
                self.progress = self.index
                if kind == "movej":
                    self.current = JointMove(arm.q_cmd, target, v, a)
                else:
                    self.current = LinearMove(arm, pose_from_ur(target), v, a)
            if self.current.advance(arm, dt):
                self.current = None
                self.index += 1
                if self.index < len(self.entries):
                    continue
            return self.index >= len(self.entries)
        return True


class StopMove(Motion):
    """Decelerate every joint's current speed to zero with `decel` (rad/s^2), scaled so the joints stop together."""

    def __init__(self, qd: FloatArray, decel: float) -> None:
        self.qd = np.array(qd, dtype=np.float64)
        peak = float(np.max(np.abs(self.qd)))
        self.scale = self.qd / peak if peak > 0 else np.zeros(6)
        self.speed = peak
        self.decel = max(decel, 1e-6)

    def advance(self, arm: SimulatedArm, dt: float) -> bool:
        self.speed = max(0.0, self.speed - self.decel * dt)
        arm.set_joint_target(arm.q_cmd + self.scale * self.speed * dt, dt)
        return self.speed == 0.0


class SpeedControl(Motion):
    """speedj: ramp joint speeds to `qd_target` with `accel`; runs until replaced or `duration` (s, 0 = forever)."""

    def __init__(self, qd_now: FloatArray, qd_target: FloatArray, accel: float, duration: float = 0.0) -> None:
        self.qd = np.array(qd_now, dtype=np.float64)
        self.qd_target = np.array(qd_target, dtype=np.float64)
        self.accel = max(accel, 1e-6)
        self.duration = duration
        self.t = 0.0

    def advance(self, arm: SimulatedArm, dt: float) -> bool:
        self.t += dt
        step = np.clip(self.qd_target - self.qd, -self.accel * dt, self.accel * dt)
        self.qd = self.qd + step
        arm.set_joint_target(arm.q_cmd + self.qd * dt, dt)
        return self.duration > 0.0 and self.t >= self.duration


class ServoControl(Motion):
    """servoj: each streamed joint target is reached linearly over its `time` (s), starting from where the arm is
    when the target arrives; speeds saturate at the joint limits (as the controller's servo does) instead of
    faulting, since a late client sample only means a longer step."""

    def __init__(self, q_target: FloatArray, time: float) -> None:
        self.q_target = np.array(q_target, dtype=np.float64)
        self.time = time
        self.q_start: FloatArray | None = None
        self.elapsed = 0.0

    def retarget(self, q_target: FloatArray, time: float) -> None:
        q_target = np.asarray(q_target, dtype=np.float64)
        if not np.array_equal(q_target, self.q_target):
            self.q_target = q_target.copy()
            self.q_start = None
        self.time = time

    def advance(self, arm: SimulatedArm, dt: float) -> bool:
        if self.q_start is None:
            self.q_start, self.elapsed = arm.q_cmd.copy(), 0.0
        self.elapsed += dt
        frac = min(1.0, self.elapsed / max(self.time, dt))
        q_next = self.q_start + (self.q_target - self.q_start) * frac
        step = np.clip(q_next - arm.q_cmd, -arm.qd_limit * dt, arm.qd_limit * dt)
        arm.set_joint_target(arm.q_cmd + step, dt)
        return False


@dataclass
class SimulatedArm:
    """Joint state of one UR arm; `step()` advances `dt` seconds (default 2 ms: 500 Hz).

    q_cmd, qd: (6,) commanded joints (rad) and speeds (rad/s); the simulation is kinematic, so actual = commanded.
    tcp_offset: flange_from_tcp (4, 4). ik: optional IK solver used by linear moves.
    """

    params: URParams
    q: FloatArray
    dt: float = 0.002
    ik: IKSolver | None = None
    tcp_offset: FloatArray = field(default_factory=lambda: np.eye(4))
    qd: FloatArray = field(default_factory=lambda: np.zeros(6))
    motion: Motion | None = None
    fault: str = ""

    def __post_init__(self) -> None:
        self.q = np.array(self.q, dtype=np.float64).reshape(6)
        self.q_cmd = self.q.copy()
        self.qd_limit = np.array(self.params.velocity_limit, dtype=np.float64)

    def base_from_flange(self, q: FloatArray | None = None) -> FloatArray:
        return dh_forward_kinematics(self.params, self.q if q is None else q)

    def base_from_tcp(self, q: FloatArray | None = None) -> FloatArray:
        return self.base_from_flange(q) @ self.tcp_offset

    def tcp_pose_vector(self) -> FloatArray:
        """actual_TCP_pose: [x, y, z, rx, ry, rz] (m, rotation vector rad)."""
        return pose_to_ur(self.base_from_tcp())

    def track_tcp(self, base_from_tcp: FloatArray, iterations: int = 3, damping: float = 1e-6) -> FloatArray:
        """Joints near `q_cmd` reaching a nearby TCP pose: damped Gauss-Newton on the DH kinematics with a
        finite-difference Jacobian (about 0.1 ms; used every period by linear moves, no branch switching)."""
        q = self.q_cmd.copy()
        eps = 1e-7
        for _ in range(iterations):
            batch = q[None] + np.vstack([np.zeros(6), np.eye(6) * eps])
            poses = dh_forward_kinematics(self.params, batch) @ self.tcp_offset
            err = np.concatenate(
                [base_from_tcp[:3, 3] - poses[0, :3, 3], rotation_to_rotvec(base_from_tcp[:3, :3] @ poses[0, :3, :3].T)]
            )
            if float(np.linalg.norm(err)) < 1e-10:
                break
            jac = np.empty((6, 6))
            for j in range(6):
                jac[:3, j] = (poses[j + 1, :3, 3] - poses[0, :3, 3]) / eps
                jac[3:, j] = rotation_to_rotvec(poses[j + 1, :3, :3] @ poses[0, :3, :3].T) / eps
            q = q + np.linalg.solve(jac.T @ jac + damping * np.eye(6), jac.T @ err)
        return q

    def solve_tcp(self, base_from_tcp: FloatArray) -> FloatArray:
        """Joints reaching a TCP pose, nearest to the current joints; raises NoIKSolution."""
        if self.ik is None:
            raise SimulationError("no IK solver configured for this arm")
        flange = base_from_tcp @ np.linalg.inv(self.tcp_offset)
        sols = np.asarray(self.ik(flange, self.q_cmd), dtype=np.float64).reshape(-1, 6)
        if sols.shape[0] == 0:
            raise NoIKSolution("linear move left the reachable workspace", reason="out_of_reach", target=flange)
        return np.asarray(sols[0], dtype=np.float64)

    def set_joint_target(self, q_next: FloatArray, dt: float) -> None:
        """Move to q_next in one period; a jump above the joint speed limits is a fault (protective stop)."""
        q_next = np.asarray(q_next, dtype=np.float64)
        speed = (q_next - self.q_cmd) / dt
        if np.any(np.abs(speed) > self.qd_limit * 1.05 + 1e-9):
            worst = int(np.argmax(np.abs(speed) / self.qd_limit))
            self.fault = (
                f"joint {worst} speed {abs(speed[worst]):.3f} rad/s exceeds its limit {self.qd_limit[worst]:.3f} rad/s"
            )
            speed = np.clip(speed, -self.qd_limit, self.qd_limit)
            q_next = self.q_cmd + speed * dt
        self.qd = speed
        self.q_cmd = q_next
        self.q = q_next.copy()

    def start(self, motion: Motion) -> None:
        self.motion = motion

    def stop(self, decel: float) -> None:
        """Replace the current motion with a deceleration to rest."""
        self.motion = StopMove(self.qd, decel)

    @property
    def moving(self) -> bool:
        return self.motion is not None

    def step(self) -> None:
        """Advance one period; records `fault` (and stops) when a motion cannot continue."""
        if self.motion is None:
            self.qd = np.zeros(6)
            return
        try:
            done = self.motion.advance(self, self.dt)
        except (NoIKSolution, SimulationError) as exc:
            self.fault = str(exc)
            log.warning("motion aborted: %s", exc)
            self.motion = StopMove(self.qd, PROTECTIVE_STOP_DECEL)
            return
        if done:
            self.motion = None
