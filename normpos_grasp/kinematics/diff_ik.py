"""Differential IK through mink: pose targets and Cartesian straight-line moves for any tool.

Tasks: FrameTask on the `flange` site (targets given for the TCP are mapped through `flange_from_tcp`) and a
light PostureTask towards the start configuration. Limits (each optional): ConfigurationLimit, VelocityLimit,
CollisionAvoidanceLimit between named bodies. Pitfalls handled here: mink's `solve_ik(limits=None)` silently
adds a ConfigurationLimit, so limits are always passed as an explicit list. A ConfigurationLimit (gain 0.95)
lets each step cover at most 95 % of the distance to a limit, so with UR's +-2 pi ranges a solve whose nearest
solution lies across a limit stalls (benchmark: 45 % success from the home pose with it, far more without);
`solve` without the limit wraps the result back into the limits by multiples of 2 pi, which is exact for a
point target. `cartesian_path` keeps it on by default: a continuous path cannot be wrapped. `dt` only
matters for VelocityLimit (|dq| <= v dt per iteration).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import mink
import numpy as np

from normpos_grasp.errors import NoIKSolution
from normpos_grasp.geometry import rotation_angle, rotation_from_rotvec, rotation_to_rotvec
from normpos_grasp.typing import ArrayLike, FloatArray
from normpos_grasp.validation import as_float_array, check_pose

if TYPE_CHECKING:
    import mujoco

    from normpos_grasp.kinematics.robot import Robot

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class DiffIKOptions:
    """Settings of the differential IK.

    position_tol_m / orientation_tol_rad: convergence (default 0.1 mm / 0.1 deg). max_iterations: QP steps per
    target (per waypoint in a Cartesian path). dt: integration step, s (velocity limits act as |dq| <= v dt).
    damping: Levenberg-Marquardt damping of the QP. position_cost / orientation_cost: FrameTask weights (1/m,
    1/rad); posture_cost: PostureTask weight towards q_start (1/rad). use_configuration_limit,
    use_velocity_limit: enable those limits. collision_pairs: ((bodies...), (bodies...)) name groups for
    CollisionAvoidanceLimit (empty: none); min_collision_distance_m: the clearance it keeps.
    max_joint_step_rad: largest joint change allowed between consecutive path waypoints (catches flips).
    solver: qpsolvers backend.
    """

    position_tol_m: float = 1e-4
    orientation_tol_rad: float = math.radians(0.1)
    max_iterations: int = 300
    dt: float = 0.05
    damping: float = 1e-6
    position_cost: float = 1.0
    orientation_cost: float = 1.0
    posture_cost: float = 1e-4
    use_configuration_limit: bool = True
    use_velocity_limit: bool = True
    collision_pairs: tuple[tuple[tuple[str, ...], tuple[str, ...]], ...] = ()
    min_collision_distance_m: float = 0.005
    max_joint_step_rad: float = 0.5
    solver: str = "daqp"


@dataclass(frozen=True)
class DiffIKResult:
    """Outcome of one solve: q (6,), iterations used, remaining position (m) and orientation (rad) errors."""

    q: FloatArray
    iterations: int
    position_error_m: float
    orientation_error_rad: float
    converged: bool


@dataclass(frozen=True)
class DiffIKProblem:
    """What was asked: robot name, start configuration (6,), base_from_flange target (4, 4), options and,
    for a path, the index of the failing waypoint (-1 for a single solve)."""

    robot: str
    q_start: FloatArray
    base_from_flange_goal: FloatArray
    options: DiffIKOptions
    waypoint: int = -1


class DiffIKNotConverged(NoIKSolution):
    """Differential IK did not reach the target; `problem` and `result` hold what was asked and reached."""

    def __init__(self, message: str, problem: DiffIKProblem, result: DiffIKResult) -> None:
        super().__init__(message, "not_converged", problem.base_from_flange_goal)
        self.problem = problem
        self.result = result


def _pose_error(current: FloatArray, goal: FloatArray) -> tuple[float, float]:
    return float(np.linalg.norm(goal[:3, 3] - current[:3, 3])), rotation_angle(current[:3, :3].T @ goal[:3, :3])


@dataclass
class DiffIK:
    """A reusable mink setup for one robot (and optional MuJoCo model holding the arm as its first 6 dofs,
    e.g. a scene with obstacles for CollisionAvoidanceLimit)."""

    robot: Robot
    options: DiffIKOptions = field(default_factory=DiffIKOptions)
    model: mujoco.MjModel | None = None
    flange_from_tcp: FloatArray = field(default_factory=lambda: np.eye(4))

    def __post_init__(self) -> None:
        model = self.model if self.model is not None else self.robot.mujoco_model()
        self.model = self._mj = model
        self.flange_from_tcp = check_pose(self.flange_from_tcp, "flange_from_tcp")
        self._tcp_from_flange = np.linalg.inv(self.flange_from_tcp)
        opts = self.options
        self.configuration = mink.Configuration(model)
        self.frame_task = mink.FrameTask("flange", "site", opts.position_cost, opts.orientation_cost, lm_damping=1e-6)
        self.posture_task = mink.PostureTask(self.model, cost=opts.posture_cost)
        limits: list[Any] = []
        if opts.use_configuration_limit:
            limits.append(mink.ConfigurationLimit(self.model))
        if opts.use_velocity_limit:
            vel = dict(zip(_joint_names(self.model), self.robot.velocity_limits, strict=False))
            limits.append(mink.VelocityLimit(self.model, vel))
        if opts.collision_pairs:
            pairs = [(self._geoms(a), self._geoms(b)) for a, b in opts.collision_pairs]
            limits.append(
                mink.CollisionAvoidanceLimit(
                    self.model, pairs, minimum_distance_from_collisions=opts.min_collision_distance_m
                )
            )
        self.limits = limits  # an explicit list: never None (mink would add a ConfigurationLimit)

    def _geoms(self, bodies: tuple[str, ...]) -> list[int]:
        ids: list[int] = []
        for name in bodies:
            body = self._mj.body(name)
            ids += list(range(body.geomadr[0], body.geomadr[0] + body.geomnum[0]))
        return ids

    def _iterate(self, q: FloatArray, flange_goal: FloatArray) -> DiffIKResult:
        opts = self.options
        cfg = self.configuration
        full = cfg.q.copy()
        full[:6] = q
        cfg.update(full)
        self.frame_task.set_target(mink.SE3.from_matrix(flange_goal))
        tasks = [self.frame_task, self.posture_task]
        pos_err = rot_err = math.inf
        for it in range(opts.max_iterations + 1):
            current = cfg.get_transform_frame_to_world("flange", "site").as_matrix()
            pos_err, rot_err = _pose_error(current, flange_goal)
            if pos_err <= opts.position_tol_m and rot_err <= opts.orientation_tol_rad:
                return DiffIKResult(cfg.q[:6].copy(), it, pos_err, rot_err, True)
            if it == opts.max_iterations:
                break
            vel = mink.solve_ik(cfg, tasks, opts.dt, opts.solver, damping=opts.damping, limits=self.limits)
            cfg.integrate_inplace(vel, opts.dt)
        return DiffIKResult(cfg.q[:6].copy(), opts.max_iterations, pos_err, rot_err, False)

    def solve(self, q_start: ArrayLike, base_from_tcp_goal: ArrayLike) -> DiffIKResult:
        """Iterate from q_start (6,) to the goal pose of the TCP (4, 4) (the flange when flange_from_tcp is
        identity). Raises DiffIKNotConverged (reason not_converged) when the budget runs out."""
        q0 = as_float_array(q_start, "q_start", (6,))
        goal = check_pose(base_from_tcp_goal, "base_from_tcp_goal") @ self._tcp_from_flange
        self._set_posture(q0)
        result = self._iterate(q0, goal)
        if result.converged:
            lower, upper = self.robot.joint_limits
            wrapped = _wrap_into(result.q, lower, upper)
            if wrapped is None:
                result = dataclasses.replace(result, converged=False)
            else:
                result = dataclasses.replace(result, q=wrapped)
        if not result.converged:
            raise DiffIKNotConverged(
                f"{self.robot.name}: differential IK stopped {result.position_error_m * 1e3:.2f} mm / "
                f"{math.degrees(result.orientation_error_rad):.2f} deg from the target after {result.iterations} "
                "iterations; try the analytic IK, another start configuration or more iterations",
                DiffIKProblem(self.robot.name, q0, goal, self.options),
                result,
            )
        return result

    def _set_posture(self, q0: FloatArray) -> None:
        full = self.configuration.q.copy()
        full[:6] = q0
        self.posture_task.set_target(full)

    def cartesian_path(
        self,
        q_start: ArrayLike,
        base_from_tcp_goal: ArrayLike,
        step_m: float = 0.005,
        step_rad: float = math.radians(2.0),
    ) -> FloatArray:
        """Joint waypoints (N, 6), first = q_start, moving the TCP along the straight line (orientation by
        constant angular rate) to the goal, waypoints at most step_m / step_rad apart. Raises DiffIKNotConverged
        with the failing waypoint, or when consecutive waypoints jump by more than options.max_joint_step_rad."""
        q0 = as_float_array(q_start, "q_start", (6,))
        goal_tcp = check_pose(base_from_tcp_goal, "base_from_tcp_goal")
        start_tcp = self.robot.fk(q0) @ self.flange_from_tcp
        dist = float(np.linalg.norm(goal_tcp[:3, 3] - start_tcp[:3, 3]))
        rotvec = rotation_to_rotvec(start_tcp[:3, :3].T @ goal_tcp[:3, :3])
        n = max(1, math.ceil(max(dist / step_m, float(np.linalg.norm(rotvec)) / step_rad)))
        self._set_posture(q0)
        path = [q0]
        q = q0
        for k in range(1, n + 1):
            s = k / n
            tcp = np.eye(4)
            tcp[:3, :3] = start_tcp[:3, :3] @ rotation_from_rotvec(rotvec * s)
            tcp[:3, 3] = (1 - s) * start_tcp[:3, 3] + s * goal_tcp[:3, 3]
            goal = tcp @ self._tcp_from_flange
            result = self._iterate(q, goal)
            jump = float(np.abs(result.q - q).max())
            if not result.converged or jump > self.options.max_joint_step_rad:
                why = "did not converge" if not result.converged else f"jumped {jump:.2f} rad (configuration flip)"
                raise DiffIKNotConverged(
                    f"{self.robot.name}: Cartesian path waypoint {k}/{n} {why} "
                    f"({result.position_error_m * 1e3:.2f} mm, {math.degrees(result.orientation_error_rad):.2f} deg "
                    "left); the line may cross a singularity, a joint limit or an obstacle",
                    DiffIKProblem(self.robot.name, q0, goal, self.options, waypoint=k),
                    result,
                )
            q = result.q
            path.append(q)
        return np.array(path)


def _wrap_into(q: FloatArray, lower: FloatArray, upper: FloatArray) -> FloatArray | None:
    """q shifted by multiples of 2 pi per joint into [lower, upper], or None where no copy fits."""
    out = q.copy()
    outside = (q < lower) | (q > upper)
    for j in np.flatnonzero(outside):
        k = math.ceil((lower[j] - q[j]) / (2 * math.pi))
        candidate = q[j] + 2 * math.pi * k
        if candidate > upper[j]:
            return None
        out[j] = candidate
    return out


def _joint_names(model: mujoco.MjModel) -> list[str]:
    return [model.joint(i).name for i in range(model.njnt)]


def cartesian_path(
    robot: Robot,
    q_start: ArrayLike,
    base_from_flange_goal: ArrayLike,
    step_m: float = 0.005,
    options: DiffIKOptions | None = None,
    flange_from_tcp: ArrayLike | None = None,
) -> FloatArray:
    """Straight-line move of the flange (or of the TCP given `flange_from_tcp`, then the goal is base_from_tcp)
    from q_start (6,): joint waypoints (N, 6). See `DiffIK.cartesian_path`."""
    tcp = np.eye(4) if flange_from_tcp is None else np.asarray(flange_from_tcp, dtype=np.float64)
    return DiffIK(robot, options or DiffIKOptions(), flange_from_tcp=tcp).cartesian_path(
        q_start, base_from_flange_goal, step_m
    )


def solve_pose(
    robot: Robot, q_start: ArrayLike, base_from_flange_goal: ArrayLike, options: DiffIKOptions | None = None
) -> DiffIKResult:
    """Differential IK to one flange pose from q_start (6,); raises DiffIKNotConverged."""
    return DiffIK(robot, options or DiffIKOptions()).solve(q_start, base_from_flange_goal)
