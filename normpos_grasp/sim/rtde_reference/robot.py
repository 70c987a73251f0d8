"""Motion of the reference controller's arm: an online setpoint generator advanced once per 2 ms cycle.

Every motion keeps a scalar path coordinate driven by a bounded-acceleration ramp computed online (speed =
min(cruise, speed + a dt, sqrt(2 a remaining))), so stopping is the same ramp with the goal moved to the stopping
point. Joint moves interpolate joints; linear moves interpolate the TCP (position straight, rotation about one axis)
and map it to joints by damped least squares on the DH forward kinematics. Stops: stopJ decelerates every joint
proportionally at a rad/s^2; stopL decelerates along the running line at a m/s^2; protective and emergency stops
bring the arm to rest within `SAFETY_STOP_TIME_S` (UR's e-Series stopping time, 50 ms).
"""

from __future__ import annotations

import math

import numpy as np

from normpos_grasp.kinematics.ur_params import URParams
from normpos_grasp.typing import FloatArray

SAFETY_STOP_TIME_S = 0.05
UR_DH_ALPHA = (math.pi / 2, 0.0, 0.0, math.pi / 2, -math.pi / 2, 0.0)  # UR's DH table: link twists, rad


def frames(params: URParams, q: FloatArray) -> list[FloatArray]:
    """base_from_joint_frame_i (4, 4) for i = 0..6 at joints q (6,): the base, then after each link."""
    out = [np.eye(4)]
    for i in range(6):
        ct, st = math.cos(q[i]), math.sin(q[i])
        ca, sa = math.cos(UR_DH_ALPHA[i]), math.sin(UR_DH_ALPHA[i])
        a, d = params.a[i], params.d[i]
        link = np.array(
            [[ct, -st * ca, st * sa, a * ct], [st, ct * ca, -ct * sa, a * st], [0.0, sa, ca, d], [0.0, 0.0, 0.0, 1.0]]
        )
        out.append(out[-1] @ link)
    return out


def log_rotation(r: FloatArray) -> FloatArray:
    """Rotation vector (3,) rad of a rotation matrix (3, 3) (angle below pi)."""
    cos = min(1.0, max(-1.0, (float(np.trace(r)) - 1.0) / 2.0))
    angle = math.acos(cos)
    w = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]]) / 2.0
    if angle < 1e-9:
        return w
    return w * (angle / math.sin(angle)) if angle < math.pi - 1e-6 else _log_near_pi(r, angle)


def _log_near_pi(r: FloatArray, angle: float) -> FloatArray:
    axis = np.sqrt(np.clip((np.diag(r) + 1.0) / 2.0, 0.0, None))
    k = int(np.argmax(axis))
    axis = (r[:, k] + np.eye(3)[k]) / (2.0 * axis[k])
    return axis / np.linalg.norm(axis) * angle


def exp_rotation(w: FloatArray) -> FloatArray:
    """Rotation matrix (3, 3) of a rotation vector (3,) rad (Rodrigues)."""
    angle = float(np.linalg.norm(w))
    if angle < 1e-12:
        return np.eye(3)
    k = w / angle
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(angle) * kx + (1.0 - math.cos(angle)) * (kx @ kx)


class Ramp:
    """Scalar coordinate 0 -> length with speed cap `v` and acceleration `a` (units of the coordinate)."""

    def __init__(self, length: float, v: float, a: float) -> None:
        self.length, self.v, self.a = max(length, 0.0), max(v, 1e-9), max(a, 1e-9)
        self.s = 0.0
        self.speed = 0.0

    def step(self, dt: float) -> bool:
        """Advance `dt`; True when at the end and at rest."""
        left = self.length - self.s
        if left <= 1e-12:
            self.s, self.speed = self.length, 0.0
            return True
        brake = math.sqrt(2.0 * self.a * left)
        self.speed = min(self.v, self.speed + self.a * dt, brake)
        self.s = min(self.length, self.s + self.speed * dt)
        if self.length - self.s <= 1e-12:
            self.s, self.speed = self.length, 0.0
            return True
        return False

    def brake(self, a: float) -> None:
        """Stop as soon as deceleration `a` allows: the end moves to the stopping point."""
        self.a = max(a, 1e-9)
        self.length = min(self.length, self.s + self.speed * self.speed / (2.0 * self.a))


class Arm:
    """Joints (6,) rad and speeds rad/s of one UR arm; `cycle(dt)` runs the current motion one period."""

    def __init__(self, params: URParams, q: FloatArray) -> None:
        self.params = params
        self.q = np.array(q, dtype=np.float64)
        self.qd = np.zeros(6)
        self.vmax = np.array(params.velocity_limit, dtype=np.float64)
        self.flange_from_tcp = np.eye(4)
        self.motion: object | None = None
        self.queue: list[tuple[str, FloatArray, float, float]] = []
        self.fault = ""
        # joint motion state
        self._q0 = self.q.copy()
        self._dq = np.zeros(6)
        self._ramp: Ramp | None = None
        # linear motion state
        self._p0 = np.zeros(3)
        self._dp = np.zeros(3)
        self._r0 = np.eye(3)
        self._axis_angle = np.zeros(3)
        # stop / servo state
        self._stop_qd = np.zeros(6)
        self._stop_a = 0.0
        self._servo_goal = self.q.copy()
        self._servo_time = 0.008

    # ------------------------------------------------------------------ kinematics
    def tcp(self, q: FloatArray | None = None) -> FloatArray:
        """base_from_tcp (4, 4) at joints q (default: now)."""
        return frames(self.params, np.asarray(self.q if q is None else q, dtype=np.float64))[-1] @ self.flange_from_tcp

    def _joints_for(self, pose: FloatArray, iterations: int = 1) -> FloatArray:
        """Joints near the current ones reaching `pose`: damped least squares on the geometric Jacobian (revolute
        joint i moves the TCP by z_i x (p_tcp - p_i), turns it about z_i)."""
        q = self.q.copy()
        for _ in range(iterations):
            chain = frames(self.params, q)
            cur = chain[-1] @ self.flange_from_tcp
            err = np.concatenate([pose[:3, 3] - cur[:3, 3], log_rotation(pose[:3, :3] @ cur[:3, :3].T)])
            if float(np.max(np.abs(err))) < 1e-12:
                break
            z = np.array([f[:3, 2] for f in chain[:6]])
            o = np.array([f[:3, 3] for f in chain[:6]])
            jac = np.vstack([np.cross(z, cur[:3, 3] - o).T, z.T])
            q = q + jac.T @ np.linalg.solve(jac @ jac.T + 1e-8 * np.eye(6), err)
        return q

    # ------------------------------------------------------------------ commands
    @property
    def moving(self) -> bool:
        return self.motion is not None

    def move_joints(self, q_goal: FloatArray, v: float, a: float) -> None:
        self._q0 = self.q.copy()
        self._dq = np.asarray(q_goal, dtype=np.float64) - self._q0
        self._ramp = Ramp(float(np.max(np.abs(self._dq))), v, a)
        self.motion = "joint"

    def move_line(self, pose_goal: FloatArray, v: float, a: float) -> None:
        start = self.tcp()
        self._p0 = start[:3, 3].copy()
        self._dp = pose_goal[:3, 3] - self._p0
        self._r0 = start[:3, :3].copy()
        self._axis_angle = log_rotation(start[:3, :3].T @ pose_goal[:3, :3])
        length = float(np.linalg.norm(self._dp))
        self._line_by_angle = length < 1e-7
        self._ramp = Ramp(float(np.linalg.norm(self._axis_angle)) if self._line_by_angle else length, v, a)
        self.motion = "line"

    def run_path(self, entries: list[tuple[str, FloatArray, float, float]]) -> None:
        """Path entries (kind 'movej' joints / 'movel' pose, v, a) run one after another to exact stops."""
        self.queue = list(entries)
        self._next_in_queue()

    def _next_in_queue(self) -> None:
        if not self.queue:
            self.motion = None
            return
        kind, target, v, a = self.queue.pop(0)
        if kind == "movej":
            self.move_joints(target, v, a)
        else:
            self.move_line(target, v, a)

    def servo(self, q_goal: FloatArray, time_s: float) -> None:
        self._servo_goal = np.asarray(q_goal, dtype=np.float64).copy()
        self._servo_time = max(time_s, 0.002)
        if self.motion != "servo":
            self.queue = []
            self.motion = "servo"

    def stop_joints(self, a: float) -> None:
        """stopJ: every joint's speed to zero at `a` rad/s^2 (the leading joint), joints in proportion."""
        self.queue = []
        if self.motion is None:
            return
        self._stop_qd = self.qd.copy()
        self._stop_a = max(a, 1e-6)
        self.motion = "stop"

    def stop_line(self, a: float) -> None:
        """stopL: along the running line at `a` m/s^2 (a joint stop when no line runs)."""
        self.queue = []
        if self.motion == "line" and self._ramp is not None and not self._line_by_angle:
            self._ramp.brake(a)
        else:
            self.stop_joints(a)

    def safety_stop(self) -> None:
        """Protective / emergency stop: at rest within SAFETY_STOP_TIME_S."""
        peak = float(np.max(np.abs(self.qd)))
        self.stop_joints(max(peak / SAFETY_STOP_TIME_S, 1.0))
        if self.motion is None:
            self.qd = np.zeros(6)

    # ------------------------------------------------------------------ the cycle
    def cycle(self, dt: float) -> None:
        q_prev = self.q.copy()
        kind = self.motion
        if kind == "joint" and self._ramp is not None:
            done = self._ramp.step(dt)
            frac = self._ramp.s / self._ramp.length if self._ramp.length > 0 else 1.0
            self.q = self._q0 + self._dq * frac
            if done:
                self._next_in_queue()
        elif kind == "line" and self._ramp is not None:
            done = self._ramp.step(dt)
            full = float(np.linalg.norm(self._axis_angle)) if self._line_by_angle else float(np.linalg.norm(self._dp))
            frac = self._ramp.s / full if full > 0 else 1.0
            pose = np.eye(4)
            pose[:3, 3] = self._p0 + self._dp * frac
            pose[:3, :3] = self._r0 @ exp_rotation(self._axis_angle * frac)
            q = self._joints_for(pose)
            if float(np.linalg.norm(self.tcp(q)[:3, 3] - pose[:3, 3])) > 1e-4:
                self.fault = "linear move cannot follow its line (singular or out of reach)"
                self.q = q_prev
                self.qd = np.zeros(6)
                self.motion = None
                return
            self.q = q
            if done:
                self._next_in_queue()
        elif kind == "servo":
            want = (self._servo_goal - self.q) / max(self._servo_time, dt)
            self.q = self.q + np.clip(want, -self.vmax, self.vmax) * dt
        elif kind == "stop":
            peak = float(np.max(np.abs(self._stop_qd)))
            new_peak = max(0.0, peak - self._stop_a * dt)
            self._stop_qd = self._stop_qd * (new_peak / peak) if peak > 0 else self._stop_qd * 0.0
            self.q = self.q + self._stop_qd * dt
            if new_peak == 0.0:
                self.motion = None
        qd = (self.q - q_prev) / dt
        over = np.abs(qd) > self.vmax * 1.05
        if np.any(over):
            j = int(np.argmax(np.abs(qd) / self.vmax))
            self.fault = f"joint {j} at {abs(qd[j]):.2f} rad/s above its rated {self.vmax[j]:.2f} rad/s"
            qd = np.clip(qd, -self.vmax, self.vmax)
            self.q = q_prev + qd * dt
        self.qd = qd if kind is not None else np.zeros(6)
