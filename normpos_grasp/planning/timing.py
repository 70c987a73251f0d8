"""Time parameterisation of joint paths within velocity and acceleration caps.

Each segment (a list of joint configurations along one geometric curve: a Cartesian straight line sampled densely,
or a straight joint edge) is traversed with a trapezoidal profile of its path parameter, starting and ending at
rest; the parameter's speed and acceleration limits come from the largest joint derivative along the segment, so
every joint stays within its caps (checked again on the samples, with a safety factor for curvature).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from normpos_grasp.cell.stream import STREAM_PERIOD_S
from normpos_grasp.errors import PlanningError
from normpos_grasp.records.plan import Trajectory
from normpos_grasp.typing import ArrayLike, FloatArray


@dataclass(frozen=True)
class TimingOptions:
    """dt_s: sample period of the output trajectory, s. method: 'ruckig' (`time_path`: time-optimal, jerk-limited,
    blending through waypoints) or 'trapezoid' (`time_parameterise`: rest-to-rest trapezoids per segment).

    trapezoid: safety: share of the velocity cap (its square: of the acceleration cap) the profile plans for (the
    remainder absorbs the curvature of Cartesian segments in joint space).

    ruckig: jerk_rad_s3: jerk cap of every joint, rad/s^3 (UR publishes none; 20x the example cell's 5 rad/s^2
    reaches full acceleration in 0.05 s, 2.5 samples of 20 ms). It is bounded by the servo stream: execution sends a
    cubic spline through the 20 ms samples every 8 ms and checks those commands against the caps; the spline's
    accelerations exceed the profile's the more the sharper its corners: with 0.97 of the caps planned the streamed
    commands peak at 0.98 of the acceleration cap at 50 rad/s^3, 0.99 at 100, and above the cap (1.00-1.04, the
    driver refuses them) at 150-200 (`benchmarks/bench_cycle.py`). 0.99 leaves no margin an unseen path is sure to
    keep, so the planner checks every plan's stream as the driver will (`cell.stream.check_stream`, pieces at
    stream_period_s, s: the driver's default period) and re-times a plan whose stream exceeds with the jerk cap
    halved, down to stream_jerk_floor_rad_s3 (below it the plan is refused: 'path_stream_<check>'): a plan the
    driver would refuse at run time (nothing moves, but the pick is lost) is never emitted, and the faster cap is
    kept wherever its stream passes (`planning.plan._timed_for_stream`). cap_share: share of the velocity,
    acceleration and jerk caps the profiles plan for (the rest absorbs the rounding of plan.json and of the servo
    stream). blend: pass through waypoints without a gripper action at speed where the path allows it (False: rest
    at every waypoint). check_step_rad: largest joint step between collision checks of a blended joint motion, rad
    (the planner's edge resolution).
    """

    dt_s: float = 0.02
    safety: float = 0.9
    method: str = "ruckig"
    jerk_rad_s3: float = 100.0
    cap_share: float = 0.97
    blend: bool = True
    check_step_rad: float = 0.03
    stream_period_s: float = STREAM_PERIOD_S
    stream_jerk_floor_rad_s3: float = 25.0

    def __post_init__(self) -> None:
        if self.method not in ("ruckig", "trapezoid"):
            raise PlanningError(f"timing method {self.method!r}: choose 'ruckig' or 'trapezoid'")
        for name in ("jerk_rad_s3", "stream_period_s", "stream_jerk_floor_rad_s3"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0.0):
                raise PlanningError(f"timing {name} = {value!r}: must be positive and finite")


def _trapezoid(length: float, v: float, a: float) -> tuple[float, float, float]:
    """(accel time, cruise time, peak speed) of a rest-to-rest trapezoid over `length`."""
    if length <= 0:
        return 0.0, 0.0, 0.0
    t_acc = v / a
    if a * t_acc * t_acc >= length:  # triangle
        t_acc = float(np.sqrt(length / a))
        return t_acc, 0.0, a * t_acc
    return t_acc, (length - a * t_acc * t_acc) / v, v


def rest_to_rest_s(distance: ArrayLike, v: ArrayLike, a: ArrayLike, j: ArrayLike) -> FloatArray:
    """Shortest rest-to-rest time, s, over `distance` (rad or m, elementwise) within speed `v`, acceleration `a` and
    jerk `j` caps (the symmetric jerk-limited profile Ruckig finds for one degree of freedom)."""
    d = np.abs(np.asarray(distance, dtype=np.float64))
    v, a, j = (np.broadcast_to(np.asarray(x, dtype=np.float64), d.shape) for x in (v, a, j))

    def ramp(vp: FloatArray) -> FloatArray:  # time from rest to speed vp (and back): a is reached when vp > a^2/j
        return np.where(vp <= a * a / j, 2.0 * np.sqrt(vp / j), vp / a + a / j)

    t_full = ramp(v)
    cruise = d >= v * t_full  # ramps up and down cover vp * ramp(vp)
    vp_short = np.cbrt(d * d * j / 4.0)  # vp * 2 sqrt(vp / j) = d
    vp_long = 0.5 * a * (-a / j + np.sqrt(a * a / (j * j) + 4.0 * d / a))  # vp (vp / a + a / j) = d
    vp = np.where(vp_short <= a * a / j, vp_short, vp_long)
    with np.errstate(invalid="ignore", divide="ignore"):
        t = np.where(cruise, t_full + np.where(v > 0, d / v, 0.0), 2.0 * ramp(vp))
    return np.where(d > 0.0, t, 0.0)


def joint_caps(
    vmax: ArrayLike, amax: ArrayLike, options: TimingOptions | None = None
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """(velocity, acceleration, jerk) caps (6,) the Ruckig profiles plan for: the cell's caps (rad/s, rad/s^2) and
    options.jerk_rad_s3, each times options.cap_share."""
    opts = options or TimingOptions()
    share = opts.cap_share
    v = np.broadcast_to(np.asarray(vmax, dtype=np.float64), (6,)) * share
    a = np.broadcast_to(np.asarray(amax, dtype=np.float64), (6,)) * share
    return v, a, np.full(6, opts.jerk_rad_s3 * share)


def joint_motion_s(a: FloatArray, b: FloatArray, caps: tuple[FloatArray, FloatArray, FloatArray]) -> float:
    """Rest-to-rest time, s, of a joint motion a -> b (6,) rad within caps (velocity, acceleration, jerk) (6,):
    the slowest joint's `rest_to_rest_s` (a time-synchronised profile cannot be shorter)."""
    return float(np.max(rest_to_rest_s(np.asarray(b) - np.asarray(a), *caps)))


def time_segment(
    points: FloatArray,
    vmax: FloatArray,
    amax: FloatArray,
    tcp_points: FloatArray | None = None,
    tcp_speed: float = np.inf,
    options: TimingOptions | None = None,
) -> tuple[FloatArray, FloatArray]:
    """Rest-to-rest timing of one segment: `points` (K, 6) rad along the curve; returns (t (M,), q (M, 6)).

    The path parameter s runs over the cumulative largest-joint distance; joint velocity is dq/ds * ds/dt, so
    ds/dt <= min_j vmax_j / max|dq_j/ds| and similarly for acceleration (plus curvature margin from `safety`).
    `tcp_points` (K, 3) with `tcp_speed` (m/s) caps the Cartesian speed too."""
    opts = options or TimingOptions()
    pts = np.asarray(points, dtype=np.float64)
    if len(pts) < 2:
        return np.zeros(1), pts[:1].copy()
    steps = np.diff(pts, axis=0)
    ds = np.abs(steps).max(axis=1)
    s = np.concatenate([[0.0], np.cumsum(ds)])
    length = float(s[-1])
    if length < 1e-12:
        return np.zeros(1), pts[:1].copy()
    with np.errstate(invalid="ignore", divide="ignore"):
        deriv = np.where(ds[:, None] > 0, np.abs(steps) / ds[:, None], 0.0)  # |dq/ds| <= 1 by construction
    dmax = np.maximum(deriv.max(axis=0), 1e-9)
    v_s = float(np.min(vmax / dmax)) * opts.safety
    a_s = float(np.min(amax / dmax)) * opts.safety * opts.safety
    if tcp_points is not None and np.isfinite(tcp_speed):
        dp = np.linalg.norm(np.diff(np.asarray(tcp_points, dtype=np.float64), axis=0), axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            ratio = np.where(ds > 0, dp / ds, 0.0)
        if ratio.max() > 0:
            v_s = min(v_s, tcp_speed * opts.safety / float(ratio.max()))
    t_acc, t_cruise, v_peak = _trapezoid(length, v_s, a_s)
    duration = 2 * t_acc + t_cruise
    n = max(int(np.ceil(duration / opts.dt_s)), 1)
    t = np.linspace(0.0, duration, n + 1)
    a_used = v_peak / t_acc if t_acc > 0 else 0.0
    pos = np.where(
        t < t_acc,
        0.5 * a_used * t**2,
        np.where(
            t < t_acc + t_cruise,
            0.5 * a_used * t_acc**2 + v_peak * (t - t_acc),
            length - 0.5 * a_used * np.maximum(duration - t, 0.0) ** 2,
        ),
    )
    pos = np.clip(pos, 0.0, length)
    q = np.stack([np.interp(pos, s, pts[:, j]) for j in range(pts.shape[1])], axis=1)
    return t, q


def time_parameterise(
    segments: list[FloatArray],
    vmax: FloatArray,
    amax: FloatArray,
    tcp_segments: list[FloatArray | None] | None = None,
    tcp_speed: float = np.inf,
    options: TimingOptions | None = None,
) -> Trajectory:
    """Concatenate rest-to-rest timings of `segments` (each (K, 6) rad) into one trajectory and verify the caps
    on the samples (finite differences); raises PlanningError when a cap is exceeded beyond 2 %."""
    opts = options or TimingOptions()
    ts: list[FloatArray] = []
    qs: list[FloatArray] = []
    t0 = 0.0
    for k, seg in enumerate(segments):
        tcp = tcp_segments[k] if tcp_segments is not None else None
        t, q = time_segment(seg, vmax, amax, tcp, tcp_speed, opts)
        if ts:
            t, q = t[1:], q[1:]
        if len(t):
            ts.append(t + t0)
            qs.append(q)
            t0 = float(ts[-1][-1])
    t_all = np.concatenate(ts) if ts else np.zeros(1)
    q_all = np.concatenate(qs) if qs else np.zeros((1, 6))
    qd = np.zeros_like(q_all)
    if len(t_all) > 1:
        dt = np.diff(t_all)
        good = dt > 1e-12
        vel = np.zeros((len(dt), q_all.shape[1]))
        vel[good] = np.diff(q_all, axis=0)[good] / dt[good, None]
        qd[1:] = vel
        over = np.abs(vel) > vmax * 1.02
        if over.any():
            i, j = np.argwhere(over)[0]
            raise PlanningError(
                f"time parameterisation exceeded joint {j} velocity cap: {abs(vel[i, j]):.3f} > "
                f"{vmax[j]:.3f} rad/s at t={t_all[i]:.3f} s"
            )
    return Trajectory(t_all, q_all, qd)


# -- time-optimal, jerk-limited timing (Ruckig) through the waypoints, with blends where the path allows ------------


@dataclass(frozen=True, eq=False)
class PathPiece:
    """One geometric piece of a path, in order; consecutive pieces share their end configurations.

    points: (K, 6) rad. tcp: (K, 3) TCP positions, m, for a straight Cartesian line (followed exactly: its joint
    samples are splined over arc length and only the speed along it is chosen); None for a straight joint edge
    (K == 2). rest_after: the arm stops at the end (gripper action, end of the path). free: for a joint edge, a
    collision test of configurations off the edge ((M, 6) rad -> True when all are free); with it the motion may
    leave the edge to blend through its ends (checked with `free`, and resting at its ends where it is not free),
    without it the edge is followed exactly and its ends are stops.
    """

    points: FloatArray
    tcp: FloatArray | None = None
    rest_after: bool = False
    free: Callable[[FloatArray], bool] | None = None


class _Spline:
    """Not-a-knot C2 cubic spline y(x) through knots x (K,) increasing, values y (K, D) (a parabola for K = 3, a
    line for K = 2); scipy's CubicSpline costs ~1 ms per construction, this a few tens of microseconds."""

    def __init__(self, x: FloatArray, y: FloatArray) -> None:
        self.x, self.y = x, y
        k = len(x)
        h = np.diff(x)
        slope = np.diff(y, axis=0) / h[:, None]
        m = np.zeros_like(y)  # second derivatives at the knots
        if k == 3:
            m[:] = 2.0 * (slope[1] - slope[0]) / (h[0] + h[1])
        elif k >= 4:
            a = np.zeros((k, k))
            rhs = np.zeros_like(y)
            i = np.arange(1, k - 1)
            a[i, i - 1], a[i, i], a[i, i + 1] = h[:-1], 2.0 * (h[:-1] + h[1:]), h[1:]
            rhs[1:-1] = 6.0 * (slope[1:] - slope[:-1])
            a[0, :3] = h[1], -(h[0] + h[1]), h[0]  # not-a-knot: the third derivative is continuous at x[1]
            a[-1, -3:] = h[-1], -(h[-2] + h[-1]), h[-2]  # and at x[-2]
            m = np.asarray(np.linalg.solve(a, rhs), dtype=np.float64)
        self.m, self.h = m, h

    def __call__(self, xs: ArrayLike, order: int = 0) -> FloatArray:
        """Values (order 0) or derivatives (1, 2) at xs (M,) ((M, D)) or at a scalar ((D,))."""
        arr = np.atleast_1d(np.asarray(xs, dtype=np.float64))
        i = np.clip(np.searchsorted(self.x, arr, side="right") - 1, 0, len(self.h) - 1)
        h = self.h[i][:, None]
        u = (self.x[i + 1][:, None] - arr[:, None]) / h  # weights of the interval's left and right knots
        w = (arr[:, None] - self.x[i][:, None]) / h
        m0, m1, y0, y1 = self.m[i], self.m[i + 1], self.y[i], self.y[i + 1]
        if order == 0:
            out = (m0 * (u**3 - u) + m1 * (w**3 - w)) * h * h / 6.0 + y0 * u + y1 * w
        elif order == 1:
            out = (y1 - y0) / h + h * (m1 * (3.0 * w * w - 1.0) - m0 * (3.0 * u * u - 1.0)) / 6.0
        else:
            out = m0 * u + m1 * w
        return out if np.ndim(xs) else out[0]

    def bounds(self) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Largest first, second and third derivative magnitudes over the span, per column."""
        fine = np.linspace(0.0, 1.0, 9)
        xs = (self.x[:-1, None] + self.h[:, None] * fine[None]).ravel()
        p1 = np.abs(self(xs, 1)).max(axis=0)
        p2 = np.abs(self.m).max(axis=0)  # y'' is linear between knots
        p3 = (np.abs(np.diff(self.m, axis=0)) / self.h[:, None]).max(axis=0)
        return p1, p2, p3


class _Line:
    """A Cartesian line's joint path q(s), s in metres of TCP travel: a C2 cubic spline through the IK samples,
    with bounds of its first three derivatives and the speed, acceleration and jerk caps along it that keep every
    joint within its caps (q' s', q'' s'^2 + q' s'', q''' s'^3 + 3 q'' s' s'' + q' s''')."""

    def __init__(
        self,
        points: FloatArray,
        tcp: FloatArray,
        caps: tuple[FloatArray, FloatArray, FloatArray],
        tcp_speed: float,
        tcp_accel: float,
    ) -> None:
        s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(tcp, axis=0), axis=1))])
        keep = np.concatenate([[True], np.diff(s) > 1e-12])
        self.length = float(s[-1])
        self.spline = _Spline(s[keep], points[keep])
        self.first, self.last = points[0], points[-1]
        p1, p2, p3 = self.spline.bounds()
        p1 = np.maximum(p1, 1e-9)
        vmax, amax, jmax = caps
        v = min(tcp_speed, float(np.min(vmax / p1)))
        for _ in range(40):  # keep at least a fifth of each budget for the path's curvature terms
            a = min(tcp_accel, float(np.min((amax - p2 * v * v) / p1)))
            j = float(np.min((jmax - p3 * v**3 - 3.0 * p2 * v * a) / p1))
            if a >= 0.2 * min(tcp_accel, float(np.min(amax / p1))) and j >= 0.2 * float(np.min(jmax / p1)):
                break
            v *= 0.8
        else:
            raise PlanningError("a Cartesian line is too curved in joint space to be timed within the caps")
        self.v_max, self.a_max, self.j_max = v, a, j
        self.tangent0, self.tangent1 = self.spline(0.0, 1), self.spline(self.length, 1)

    def joint_state(self, at_end: bool, speed: float) -> tuple[FloatArray, FloatArray, FloatArray]:
        """(q, qd, qdd) at the start or end when passing at `speed` m/s with no acceleration along the line."""
        s = self.length if at_end else 0.0
        return self.spline(s), self.spline(s, 1) * speed, self.spline(s, 2) * speed * speed


_State = tuple[Any, Any, Any]  # (position, velocity, acceleration) or (velocity, acceleration, jerk) caps


def _ruckig(
    start: _State,
    goal: _State,
    caps: _State,
    phase: bool = False,
) -> Any:
    """Ruckig's time-optimal trajectory between two states (each (position, velocity, acceleration)) within
    caps (velocity, acceleration, jerk), all per degree of freedom."""
    from ruckig import InputParameter, Result, Ruckig, Synchronization, Trajectory

    n = len(start[0])
    inp = InputParameter(n)
    inp.current_position, inp.current_velocity, inp.current_acceleration = (list(map(float, x)) for x in start)
    inp.target_position, inp.target_velocity, inp.target_acceleration = (list(map(float, x)) for x in goal)
    inp.max_velocity, inp.max_acceleration, inp.max_jerk = (list(map(float, x)) for x in caps)
    if phase:
        inp.synchronization = Synchronization.Phase
    traj = Trajectory(n)
    result = Ruckig(n).calculate(inp, traj)
    if result not in (Result.Working, Result.Finished):
        raise PlanningError(f"Ruckig found no trajectory ({result})")
    return traj


def _sample_times(duration: float, dt: float) -> FloatArray:
    """0, dt, 2 dt, ... and `duration`, without a regular sample closer than dt / 2 to the end (short intervals
    would turn plan.json's rounding into large finite-difference accelerations)."""
    if duration <= 0.0:
        return np.zeros(1)
    t = np.arange(0.0, duration, dt)
    if len(t) > 1 and duration - t[-1] < 0.5 * dt:
        t = t[:-1]
    return np.append(t, duration)


def _profile_1d(length: float, v0: float, v1: float, v: float, a: float, j: float) -> Any | None:
    """1-DoF Ruckig profile over s in [0, length] from speed v0 to v1, or None when it would leave the interval
    or run backwards (passing speeds too high for the length)."""
    traj = _ruckig(([0.0], [v0], [0.0]), ([length], [v1], [0.0]), ([v], [a], [j]))
    ts = np.linspace(0.0, traj.duration, 64)
    pos = np.array([traj.at_time(float(t))[0][0] for t in ts])
    vel = np.array([traj.at_time(float(t))[1][0] for t in ts])
    if vel.min() < -1e-9 or pos.min() < -1e-9 or pos.max() > length + 1e-9:
        return None
    return traj


def time_path(
    pieces: list[PathPiece],
    vmax: FloatArray,
    amax: FloatArray,
    lower: FloatArray,
    upper: FloatArray,
    tcp_speed: float = np.inf,
    tcp_accel: float = np.inf,
    options: TimingOptions | None = None,
) -> Trajectory:
    """Time-optimal, jerk-limited trajectory through `pieces` (Ruckig), sampled every options.dt_s and at every
    piece end (each waypoint is a sample). Caps: vmax, amax (6,) rad/s, rad/s^2, options.jerk_rad_s3; lower,
    upper (6,) joint limits, rad; tcp_speed (m/s) and tcp_accel (m/s^2) along Cartesian lines.

    Cartesian lines keep their geometry (q(s) spline through the line's IK samples) with a 1-DoF profile of the
    travel s; straight joint edges resting at both ends are followed exactly (1-DoF profile of the edge
    parameter, the leading joint at its caps); a joint edge with a `free` test meets the neighbouring lines at
    their cruise speed and the neighbouring joint edges with a `free` test at `_via_velocity` instead of stopping
    (a 6-DoF time-synchronised profile through the exact waypoint, checked for collisions and joint limits, else
    resting at its ends). Two consecutive collinear lines pass their common end at speed. Every sample
    is then checked against the caps (finite differences, as execution.safety does) and the limits; raises
    PlanningError when a cap is exceeded.
    """
    opts = options or TimingOptions()
    share = opts.cap_share
    vmax = np.asarray(vmax, dtype=np.float64)
    amax = np.asarray(amax, dtype=np.float64)
    caps = (vmax * share, amax * share, np.full(6, opts.jerk_rad_s3 * share))
    kept: list[PathPiece] = []
    for p in pieces:  # pieces without motion drop out; a stop at the end of one moves to the piece before
        if np.abs(p.points[-1] - p.points[0]).max() > 1e-12:
            kept.append(p)
        elif p.rest_after and kept:
            kept[-1] = replace(kept[-1], rest_after=True)
    if not kept:
        raise PlanningError("time_path: no motion to time")
    pieces = kept
    lines: dict[int, _Line] = {}
    for k, p in enumerate(pieces):
        if p.tcp is not None and float(np.linalg.norm(p.tcp[-1] - p.tcp[0])) > 1e-9:
            lines[k] = _Line(p.points, p.tcp, caps, tcp_speed * share, tcp_accel * share)
    n = len(pieces)
    # speed (m/s along the neighbouring line) at the end of piece k; 0: rest
    speed = np.zeros(n)
    if opts.blend:
        for k in range(n - 1):
            a, b = pieces[k], pieces[k + 1]
            if a.rest_after:
                continue
            la, lb = lines.get(k), lines.get(k + 1)
            if la is not None and lb is not None:
                ua, ub = a.tcp[-1] - a.tcp[0], b.tcp[-1] - b.tcp[0]  # type: ignore[index]
                cos = float(ua @ ub) / (np.linalg.norm(ua) * np.linalg.norm(ub))
                scale = max(float(np.abs(la.tangent1).max()), 1e-9)
                if cos > 1.0 - 1e-9 and float(np.abs(la.tangent1 - lb.tangent0).max()) <= 1e-3 * scale:
                    speed[k] = min(la.v_max, lb.v_max)
            elif la is not None and b.tcp is None and b.free is not None:
                speed[k] = la.v_max
            elif lb is not None and a.tcp is None and a.free is not None:
                speed[k] = lb.v_max
            elif la is None and lb is None and a.free is not None and b.free is not None:
                speed[k] = 1.0  # two joint edges: through their common end at `_via_velocity`
    done: dict[tuple[int, float, float], tuple[str, Any, Any]] = {}  # profiles found, by piece and passing speeds
    for _ in range(4 * n + 8):
        profiles, retry = _profiles(pieces, lines, speed, caps, lower, upper, opts, done)
        if not retry:
            break
    else:
        raise PlanningError("time_path: no consistent passing speeds")
    ts: list[FloatArray] = []
    qs: list[FloatArray] = []
    qds: list[FloatArray] = []
    t0 = 0.0
    for kind, traj, extra in profiles:
        t_local = _sample_times(float(traj.duration), opts.dt_s)
        q, qd = _evaluate(kind, traj, extra, t_local)
        if ts:
            t_local, q, qd = t_local[1:], q[1:], qd[1:]
        ts.append(t_local + t0)
        qs.append(q)
        qds.append(qd)
        t0 += float(traj.duration)
    t_all, q_all, qd_all = np.concatenate(ts), np.concatenate(qs), np.concatenate(qds)
    _check_caps(t_all, q_all, vmax, amax, lower, upper)
    return Trajectory(t_all, q_all, qd_all)


def _profiles(
    pieces: list[PathPiece],
    lines: dict[int, _Line],
    speed: FloatArray,
    caps: tuple[FloatArray, FloatArray, FloatArray],
    lower: FloatArray,
    upper: FloatArray,
    opts: TimingOptions,
    done: dict[tuple[int, float, float], tuple[str, Any, Any]] | None = None,
) -> tuple[list[tuple[str, Any, Any]], bool]:
    """One profile per piece for the passing speeds `speed` (lowered in place where a piece cannot take them);
    returns (profiles, retry): retry is True when a speed was lowered and the profiles must be recomputed.

    `done` keeps the profiles found by piece index and passing speeds (in, out) across the retries of one path: a
    piece whose speeds a retry left as they were gets the same profile (and blend check) without computing it again.
    Only found profiles are kept; a piece that fails is recomputed, and fails the same way."""
    out: list[tuple[str, Any, Any]] = []
    n = len(pieces)
    done = {} if done is None else done
    for k, p in enumerate(pieces):
        v_in = float(speed[k - 1]) if k > 0 else 0.0
        v_out = float(speed[k])
        key = (k, v_in, v_out)
        found = done.get(key)
        if found is not None:
            out.append(found)
            continue
        line = lines.get(k)
        if line is not None:
            traj = _profile_1d(line.length, v_in, v_out, line.v_max, line.a_max, line.j_max)
            if traj is None:  # too short for these passing speeds: lower them
                if k > 0:
                    speed[k - 1] = 0.0 if v_in < 1e-3 else 0.6 * v_in
                speed[k] = 0.0 if v_out < 1e-3 else 0.6 * v_out
                return out, True
            done[key] = ("line", traj, line)
            out.append(done[key])
            continue
        a, b = p.points[0], p.points[-1]  # a joint edge (or a line without TCP travel)
        if v_in == 0.0 and v_out == 0.0:  # followed exactly: a profile of s in [0, 1], q = a + s (b - a)
            d = np.abs(b - a)
            moving = d > 1e-15
            lim = [[float(np.min(c[moving] / d[moving]))] for c in caps]
            traj = _ruckig(([0.0], [0.0], [0.0]), ([1.0], [0.0], [0.0]), (lim[0], lim[1], lim[2]))
            done[key] = ("edge", traj, (a, b))
            out.append(done[key])
            continue
        start, goal = (a, np.zeros(6), np.zeros(6)), (b, np.zeros(6), np.zeros(6))
        if v_in > 0.0:
            prev = lines.get(k - 1)
            start = (
                prev.joint_state(True, v_in) if prev is not None else (a, _via_velocity(pieces, k - 1, caps), start[2])
            )
        if v_out > 0.0:
            nxt = lines.get(k + 1)
            goal = nxt.joint_state(False, v_out) if nxt is not None else (b, _via_velocity(pieces, k, caps), goal[2])
        try:
            traj = _ruckig(start, goal, caps)
            ok = _blend_ok(traj, p, lower, upper, caps[0], opts.check_step_rad)
        except PlanningError:
            ok = False
        if not ok:  # rest at both ends of this joint motion
            if k > 0:
                speed[k - 1] = 0.0
            if k < n - 1:
                speed[k] = 0.0
            return out, True
        done[key] = ("joints", traj, (a, b))
        out.append(done[key])
    return out, False


def _via_velocity(pieces: list[PathPiece], k: int, caps: tuple[FloatArray, FloatArray, FloatArray]) -> FloatArray:
    """Joint velocity (6,) rad/s at the common end of joint edges k and k + 1: per joint, the smaller of the two
    edges' mean velocities over their rest-to-rest times (`joint_motion_s`) where both move it the same way, 0
    where they turn it back or leave it (a joint never runs past the via to come back)."""
    a, w, b = pieces[k].points[0], pieces[k].points[-1], pieces[k + 1].points[-1]
    v1 = (w - a) / max(joint_motion_s(a, w, caps), 1e-9)
    v2 = (b - w) / max(joint_motion_s(w, b, caps), 1e-9)
    same = np.sign(v1) * np.sign(v2) > 0
    return np.where(same, np.sign(v1) * np.minimum(np.abs(v1), np.abs(v2)), 0.0)  # within the caps: means


def _blend_ok(traj: Any, piece: PathPiece, lower: FloatArray, upper: FloatArray, vcap: FloatArray, step: float) -> bool:
    """Whether a blended joint motion stays within the joint limits and is collision-free (piece.free), checked
    at samples `step` rad apart (largest joint change, as the planner checks its edges) and at both ends."""
    if piece.free is None:
        return False
    lo, hi = _extrema(traj)
    if np.any(lo < lower) or np.any(hi > upper):
        return False
    dt = 0.25 * step / max(float(np.max(vcap)), 1e-9)
    times = np.append(np.arange(0.0, float(traj.duration), dt), float(traj.duration))
    fine = np.array([traj.at_time(float(t))[0] for t in times])
    # cumulative largest-joint travel bounds every joint's change between two samples: keep the last fine sample
    # before `step` of travel is used up (fine samples are at most step / 4 apart)
    travel = np.concatenate([[0.0], np.cumsum(np.abs(np.diff(fine, axis=0)).max(axis=1))])
    keep = [0]
    for i in range(1, len(fine)):
        if travel[i] - travel[keep[-1]] > step:
            keep.append(i - 1)
    if keep[-1] != len(fine) - 1:
        keep.append(len(fine) - 1)
    return bool(piece.free(fine[keep]))


def _extrema(traj: Any) -> tuple[FloatArray, FloatArray]:
    ext = traj.position_extrema
    return np.array([e.min for e in ext]), np.array([e.max for e in ext])


def _evaluate(kind: str, traj: Any, extra: Any, times: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Joint positions and velocities (M, 6) of one piece's profile at `times` (s from its start)."""
    states = [traj.at_time(float(t)) for t in times]
    if kind == "joints":
        q, qd = np.array([s[0] for s in states]), np.array([s[1] for s in states])
        q[0], q[-1] = extra  # exactly the waypoints (Ruckig's end state is within rounding of them)
        return q, qd
    s = np.array([st[0][0] for st in states])
    sd = np.array([st[1][0] for st in states])
    if kind == "line":
        line: _Line = extra
        s = np.clip(s, 0.0, line.length)
        q = line.spline(s)
        q[0], q[-1] = line.first, line.last  # exactly the waypoints (the spline meets them within rounding)
        return q, line.spline(s, 1) * sd[:, None]
    a, b = extra
    s = np.clip(s, 0.0, 1.0)
    q = a + s[:, None] * (b - a)
    q[-1] = b
    return q, sd[:, None] * (b - a)


def _check_caps(
    t: FloatArray, q: FloatArray, vmax: FloatArray, amax: FloatArray, lower: FloatArray, upper: FloatArray
) -> None:
    """The caps on the samples as execution.safety.SafetyLimits.check_trajectory computes them (finite
    differences), and the joint limits; PlanningError naming the first excess."""
    if np.any(q < lower - 1e-9) or np.any(q > upper + 1e-9):
        i, j = np.argwhere((q < lower - 1e-9) | (q > upper + 1e-9))[0]
        raise PlanningError(f"timed trajectory leaves joint {j}'s limits at t={t[i]:.3f} s")
    dt = np.diff(t)
    if np.any(dt <= 0):
        raise PlanningError("timed trajectory: time stamps must increase")
    qd = np.diff(q, axis=0) / dt[:, None]
    if np.any(np.abs(qd) > vmax):
        i, j = np.argwhere(np.abs(qd) > vmax)[0]
        raise PlanningError(
            f"timed trajectory: joint {j} speed {abs(qd[i, j]):.3f} > {vmax[j]:.3f} rad/s at t={t[i]:.3f} s"
        )
    if len(qd) >= 2:
        qdd = np.diff(qd, axis=0) / (0.5 * (dt[1:] + dt[:-1]))[:, None]
        if np.any(np.abs(qdd) > amax):
            i, j = np.argwhere(np.abs(qdd) > amax)[0]
            raise PlanningError(
                f"timed trajectory: joint {j} acceleration {abs(qdd[i, j]):.3f} > {amax[j]:.3f} rad/s^2 at "
                f"t={t[i + 1]:.3f} s"
            )
