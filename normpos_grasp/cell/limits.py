"""The cell's judge of motion: safety limits checked on every plan and target before anything is sent to an arm.

`SafetyLimits` holds joint position limits, joint speed and acceleration caps and a workspace box for the TCP in
the robot base frame. Every check raises `SafetyViolation` (with the offending values in `detail`, and `check` in
it naming the limit: 'input', 'joint_limits', 'workspace', 'time', 'joint_speed', 'joint_accel') and never sends or
clips: a target outside the limits is refused as a whole. Execution (`execution.plan.check_plan`) and the planner
(`planning.plan`, before it returns a plan) judge a plan's waypoints, segments and trajectory with the same
`SafetyLimits.check_path`.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from normpos_grasp.errors import SafetyViolation
from normpos_grasp.kinematics.ur_params import dh_forward_kinematics, ur_params
from normpos_grasp.typing import ArrayLike, FloatArray
from normpos_grasp.validation import as_float_array, check_pose

JOINT_TOL = 1e-9  # rad, numerical slack on joint limits

# Ceilings on caps. UR publishes no joint acceleration limits (the ROS description: has_acceleration_limits: false),
# so the acceleration and tool ceilings are the bounds ur_rtde 1.6.5 itself enforces on moveJ/moveL arguments
# (rtde_control_interface.h: UR_JOINT_ACCELERATION_MAX 40.0 rad/s^2, UR_TOOL_VELOCITY_MAX 3.0 m/s,
# UR_TOOL_ACCELERATION_MAX 150.0 m/s^2). Joint speed caps are bounded by the rated joint speeds (ur_params).
MAX_JOINT_ACCEL_CEILING = 40.0  # rad/s^2
MAX_TOOL_SPEED_CEILING = 3.0  # m/s
MAX_TOOL_ACCEL_CEILING = 150.0  # m/s^2


@dataclass(frozen=True)
class SafetyLimits:
    """Limits for one arm in one cell.

    model: UR model name (its DH table gives the TCP for the workspace check).
    q_lower, q_upper: (6,) joint limits, rad. max_joint_speed: (6,) rad/s. max_joint_accel: (6,) rad/s^2.
    workspace_min, workspace_max: (3,) corners of the allowed TCP box, m, in the base frame, or in the frame given
    by box_from_base (4, 4) (world_from_base for a cell's world-frame box).
    flange_from_tcp: (4, 4) tool transform used for the workspace check (identity: the flange).
    max_tool_speed: m/s cap for Cartesian moves. max_tool_accel: m/s^2.
    cell: the cell's name when the limits come from a cell (`from_cell`): its tool is the mounted one and its
    world_from_base the arm's mount, so a plan may replace neither ('' for limits of a bare arm).
    """

    model: str
    q_lower: FloatArray
    q_upper: FloatArray
    max_joint_speed: FloatArray
    max_joint_accel: FloatArray
    workspace_min: FloatArray
    workspace_max: FloatArray
    flange_from_tcp: FloatArray = field(default_factory=lambda: np.eye(4))
    max_tool_speed: float = 1.0
    max_tool_accel: float = 2.0
    box_from_base: FloatArray = field(default_factory=lambda: np.eye(4))
    cell: str = ""

    def __post_init__(self) -> None:
        """Caps must be positive, finite and within the robot's rated joint speeds and the acceleration ceilings."""
        rated = np.asarray(ur_params(self.model).velocity_limit, dtype=np.float64)
        for name, value, ceiling, unit in (
            ("max_joint_speed", self.max_joint_speed, rated, "rad/s (the rated joint speeds)"),
            ("max_joint_accel", self.max_joint_accel, np.full(6, MAX_JOINT_ACCEL_CEILING), "rad/s^2"),
        ):
            v = np.asarray(value, dtype=np.float64)
            if v.shape != (6,) or not np.all(np.isfinite(v)) or np.any(v <= 0.0):
                raise SafetyViolation(f"{name} must be 6 positive finite values, got {np.asarray(value).tolist()}")
            over = v > ceiling * (1 + 1e-9)
            if np.any(over):
                j = int(np.argmax(over))
                raise SafetyViolation(
                    f"{name} joint {j} = {v[j]:g} exceeds the {self.model} ceiling {ceiling[j]:g} {unit}",
                    detail={"joint": j, "value": float(v[j]), "ceiling": float(ceiling[j])},
                )
        for tname, x, top, tunit in (
            ("max_tool_speed", self.max_tool_speed, MAX_TOOL_SPEED_CEILING, "m/s"),
            ("max_tool_accel", self.max_tool_accel, MAX_TOOL_ACCEL_CEILING, "m/s^2"),
        ):
            if not (np.isfinite(x) and 0.0 < x <= top):
                raise SafetyViolation(f"{tname} = {x:g} {tunit} must be in (0, {top:g}] {tunit}")

    @classmethod
    def from_cell(cls, cell: Any, max_tool_accel: float = 2.0) -> SafetyLimits:
        """Limits of a cell (normpos_grasp.cell.CellConfig): its robot's joint limits, the cell's joint speed and
        acceleration caps, its TCP workspace box (world frame, checked through world_from_base) and its tool."""
        motion = cell.motion
        base = cls.for_model(cell.robot_model)
        return replace(
            base,
            max_joint_speed=np.minimum(base.max_joint_speed, as_float_array(motion.joint_velocity, "v", (6,))),
            max_joint_accel=as_float_array(motion.joint_acceleration, "joint_acceleration", (6,)),
            workspace_min=as_float_array(motion.workspace_min, "workspace_min", (3,)),
            workspace_max=as_float_array(motion.workspace_max, "workspace_max", (3,)),
            flange_from_tcp=check_pose(cell.tool.flange_from_tcp, "cell.tool.flange_from_tcp"),
            max_tool_speed=float(motion.tcp_speed_m_s),
            max_tool_accel=max_tool_accel,
            box_from_base=check_pose(cell.world_from_base, "cell.world_from_base"),
            cell=str(cell.name) or "cell",
        )

    @classmethod
    def for_model(
        cls,
        model: str,
        workspace_min: ArrayLike | None = None,
        workspace_max: ArrayLike | None = None,
        speed_fraction: float = 1.0,
        max_joint_accel: float = 4.0,
        flange_from_tcp: ArrayLike | None = None,
        max_tool_speed: float = 1.0,
        max_tool_accel: float = 2.0,
    ) -> SafetyLimits:
        """Limits from the UR parameter table: joint limits, `speed_fraction` of the rated joint speeds, a
        joint acceleration cap (rad/s^2), and a workspace box (default: a cube of twice the reach)."""
        p = ur_params(model)
        if not (np.isfinite(max_joint_accel) and 0.0 < max_joint_accel <= MAX_JOINT_ACCEL_CEILING):
            raise SafetyViolation(
                f"joint acceleration cap {max_joint_accel:g} rad/s^2 must be in (0, {MAX_JOINT_ACCEL_CEILING:g}] "
                "(ur_rtde's UR_JOINT_ACCELERATION_MAX; UR publishes no higher rated value)"
            )
        if not 0.0 < speed_fraction <= 1.0:
            raise SafetyViolation(f"speed_fraction must be in (0, 1], got {speed_fraction}")
        upper = np.array([min(v, 2 * np.pi) if np.isfinite(v) else 2 * np.pi for v in p.position_limit])
        reach = p.reach_m + 0.3
        wmin = as_float_array(workspace_min if workspace_min is not None else (-reach, -reach, -reach), "wmin", (3,))
        wmax = as_float_array(workspace_max if workspace_max is not None else (reach, reach, reach), "wmax", (3,))
        if np.any(wmin >= wmax):
            raise SafetyViolation(f"workspace_min {wmin} must be below workspace_max {wmax} on every axis")
        return cls(
            model=p.name,
            q_lower=-upper,
            q_upper=upper,
            max_joint_speed=np.array(p.velocity_limit) * speed_fraction,
            max_joint_accel=np.full(6, float(max_joint_accel)),
            workspace_min=wmin,
            workspace_max=wmax,
            flange_from_tcp=check_pose(
                flange_from_tcp if flange_from_tcp is not None else np.eye(4), "flange_from_tcp"
            ),
            max_tool_speed=max_tool_speed,
            max_tool_accel=max_tool_accel,
        )

    def with_workspace(self, workspace_min: ArrayLike, workspace_max: ArrayLike) -> SafetyLimits:
        """A copy with another workspace box (base frame, m)."""
        return replace(
            self,
            workspace_min=as_float_array(workspace_min, "workspace_min", (3,)),
            workspace_max=as_float_array(workspace_max, "workspace_max", (3,)),
        )

    # ------------------------------------------------------------------ checks
    def base_from_tcp(self, q: ArrayLike) -> FloatArray:
        """TCP pose(s) (..., 4, 4) in the base frame for joints (..., 6)."""
        return dh_forward_kinematics(ur_params(self.model), q) @ self.flange_from_tcp

    def check_joints(self, q: ArrayLike, what: str = "target") -> FloatArray:
        """Check joint targets (6,) or (N, 6) against joint limits and the workspace box; returns them as float64."""
        qs = np.asarray(q, dtype=np.float64)
        if qs.ndim == 1:
            qs = qs[None]
        if qs.ndim != 2 or qs.shape[1] != 6:
            raise SafetyViolation(
                f"{what}: expected joints of shape (6,) or (N, 6), got {np.shape(q)}", detail={"check": "input"}
            )
        if not np.all(np.isfinite(qs)):
            raise SafetyViolation(
                f"{what}: joint values must be finite, got NaN/inf", detail={"check": "input", "q": qs}
            )
        low = qs < self.q_lower - JOINT_TOL
        high = qs > self.q_upper + JOINT_TOL
        if np.any(low | high):
            i, j = np.argwhere(low | high)[0]
            raise SafetyViolation(
                f"{what} #{i}: joint {j} = {qs[i, j]:.4f} rad is outside [{self.q_lower[j]:.4f}, "
                f"{self.q_upper[j]:.4f}]; nothing was sent",
                detail={"check": "joint_limits", "index": int(i), "joint": int(j), "q": qs[i]},
            )
        self.check_tcp_positions(self.base_from_tcp(qs)[:, :3, 3], what)
        return qs if np.ndim(q) == 2 else qs[0]

    def check_tcp_positions(self, points: ArrayLike, what: str = "target") -> None:
        """Check TCP positions (N, 3) (base frame, m) against the workspace box (in its frame)."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        pts = pts @ self.box_from_base[:3, :3].T + self.box_from_base[:3, 3]
        outside = np.any((pts < self.workspace_min) | (pts > self.workspace_max), axis=1)
        if np.any(outside):
            i = int(np.argmax(outside))
            raise SafetyViolation(
                f"{what} #{i}: TCP at {np.round(pts[i], 4).tolist()} m is outside the workspace box "
                f"{self.workspace_min.tolist()} .. {self.workspace_max.tolist()} (base frame); nothing was sent",
                detail={"check": "workspace", "index": i, "tcp": pts[i]},
            )

    def check_tcp_pose(self, base_from_tcp: ArrayLike, what: str = "target") -> FloatArray:
        pose = check_pose(base_from_tcp, what)
        self.check_tcp_positions(pose[:3, 3][None], what)
        return pose

    def check_joint_speed(self, speed: float, accel: float) -> None:
        """A movej speed (rad/s) and acceleration (rad/s^2) for the leading joint: within the smallest caps."""
        vmax, amax = float(np.min(self.max_joint_speed)), float(np.min(self.max_joint_accel))
        if not (0.0 < speed <= vmax + 1e-12) or not (0.0 < accel <= amax + 1e-12):
            raise SafetyViolation(
                f"joint move speed {speed} rad/s / acceleration {accel} rad/s^2 must be in (0, {vmax:.3f}] / "
                f"(0, {amax:.3f}]; nothing was sent",
                detail={"speed": speed, "accel": accel},
            )

    def check_tool_speed(self, speed: float, accel: float) -> None:
        if not (0.0 < speed <= self.max_tool_speed) or not (0.0 < accel <= self.max_tool_accel):
            raise SafetyViolation(
                f"linear move speed {speed} m/s / acceleration {accel} m/s^2 must be in (0, {self.max_tool_speed}] "
                f"/ (0, {self.max_tool_accel}]; nothing was sent",
                detail={"speed": speed, "accel": accel},
            )

    def check_segment(self, q_from: ArrayLike, q_to: ArrayLike, what: str = "segment", samples: int = 16) -> None:
        """Check the straight joint-space segment between two configurations (TCP box at `samples` points)."""
        a = np.asarray(q_from, dtype=np.float64)
        b = np.asarray(q_to, dtype=np.float64)
        s = np.linspace(0.0, 1.0, samples)[:, None]
        self.check_joints(a + (b - a) * s, what)

    def check_trajectory(self, times: ArrayLike, q: ArrayLike, what: str = "trajectory") -> None:
        """Check time-stamped joint samples: limits, workspace, and finite-difference speed/acceleration caps."""
        t = np.asarray(times, dtype=np.float64).reshape(-1)
        qs = self.check_joints(np.asarray(q, dtype=np.float64).reshape(-1, 6), what)
        if t.shape[0] != qs.shape[0]:
            raise SafetyViolation(
                f"{what}: {t.shape[0]} time stamps for {qs.shape[0]} joint samples", detail={"check": "input"}
            )
        if t.shape[0] < 2:
            return
        dt = np.diff(t)
        if np.any(dt <= 0):
            i = int(np.argmax(dt <= 0))
            raise SafetyViolation(
                f"{what}: time stamps must increase; sample {i + 1} at {t[i + 1]} s after {t[i]} s",
                detail={"check": "time", "index": i + 1},
            )
        qd = np.diff(qs, axis=0) / dt[:, None]
        over = np.abs(qd) > self.max_joint_speed * (1 + 1e-6) + 1e-9
        if np.any(over):
            i, j = np.argwhere(over)[0]
            raise SafetyViolation(
                f"{what}: joint {j} speed {abs(qd[i, j]):.3f} rad/s between samples {i} and {i + 1} exceeds the cap "
                f"{self.max_joint_speed[j]:.3f} rad/s; nothing was sent",
                detail={"check": "joint_speed", "index": int(i), "joint": int(j), "speed": float(qd[i, j])},
            )
        if qd.shape[0] >= 2:
            dtm = 0.5 * (dt[1:] + dt[:-1])
            qdd = np.diff(qd, axis=0) / dtm[:, None]
            over = np.abs(qdd) > self.max_joint_accel * (1 + 1e-6) + 1e-9
            if np.any(over):
                i, j = np.argwhere(over)[0]
                raise SafetyViolation(
                    f"{what}: joint {j} acceleration {abs(qdd[i, j]):.3f} rad/s^2 at sample {i + 1} exceeds the cap "
                    f"{self.max_joint_accel[j]:.3f} rad/s^2; nothing was sent",
                    detail={"check": "joint_accel", "index": int(i + 1), "joint": int(j), "accel": float(qdd[i, j])},
                )

    def check_path(
        self,
        names: tuple[str, ...] | list[str],
        q: ArrayLike,
        times: ArrayLike | None = None,
        samples: ArrayLike | None = None,
    ) -> None:
        """Judge a plan's motion: waypoints `q` (N, 6) rad named `names`, the straight joint-space segment between
        each two consecutive waypoints, and the time-stamped trajectory (`times` (M,) s, `samples` (M, 6) rad) when
        given: joint limits, workspace box, joint speed and acceleration caps."""
        qs = np.asarray(q, dtype=np.float64)
        self.check_joints(qs, "waypoint")
        for i in range(len(qs) - 1):
            self.check_segment(qs[i], qs[i + 1], f"segment {names[i]}->{names[i + 1]}")
        if times is not None and samples is not None:
            self.check_trajectory(times, samples)

    def to_dict(self) -> dict[str, Any]:
        return {
            "model": self.model,
            "q_lower": self.q_lower.tolist(),
            "q_upper": self.q_upper.tolist(),
            "max_joint_speed": self.max_joint_speed.tolist(),
            "max_joint_accel": self.max_joint_accel.tolist(),
            "workspace_min": self.workspace_min.tolist(),
            "workspace_max": self.workspace_max.tolist(),
        }
