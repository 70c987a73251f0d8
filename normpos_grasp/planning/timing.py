"""Time parameterisation of joint paths within velocity and acceleration caps.

Each segment (a list of joint configurations along one geometric curve: a Cartesian straight line sampled densely,
or a straight joint edge) is traversed with a trapezoidal profile of its path parameter, starting and ending at
rest; the parameter's speed and acceleration limits come from the largest joint derivative along the segment, so
every joint stays within its caps (checked again on the samples, with a safety factor for curvature).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from normpos_grasp.errors import PlanningError
from normpos_grasp.records.plan import Trajectory
from normpos_grasp.typing import FloatArray


@dataclass(frozen=True)
class TimingOptions:
    """dt_s: sample period of the output trajectory, s. safety: share of the caps the profile plans for (the
    remainder absorbs the curvature of Cartesian segments in joint space)."""

    dt_s: float = 0.02
    safety: float = 0.9


def _trapezoid(length: float, v: float, a: float) -> tuple[float, float, float]:
    """(accel time, cruise time, peak speed) of a rest-to-rest trapezoid over `length`."""
    if length <= 0:
        return 0.0, 0.0, 0.0
    t_acc = v / a
    if a * t_acc * t_acc >= length:  # triangle
        t_acc = float(np.sqrt(length / a))
        return t_acc, 0.0, a * t_acc
    return t_acc, (length - a * t_acc * t_acc) / v, v


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
