"""The servo stream a timed trajectory becomes, for the planner and the driver alike.

Execution sends a plan's trajectory as servo targets every `STREAM_PERIOD_S` (8 ms) through a clamped cubic spline
of its samples (`stream_samples`), and the driver checks those commands against the cell's caps before the first is
sent (`SafetyLimits.check_trajectory(grid, samples, "streamed commands")`), refusing the whole trajectory where they
exceed. The math lives here, below planning and execution, so that the planner can run the very same check on what
it emits (`check_stream`) and never hand execution a plan whose stream would be refused; `execution.driver` imports
it. It sits beside the cell's judge (`cell.limits`, one floor down for the same reason) rather than in `planning`:
importing `normpos_grasp.planning` loads the whole planner (about 230 modules, 0.7 s), which the driver, and the
ur_rtde child process it starts on every connect, have no use for.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from normpos_grasp.cell.limits import SafetyLimits
from normpos_grasp.typing import FloatArray

STREAM_PERIOD_S = 0.008
"""Servo streaming period, s: `execution.driver.DriverOptions.stream_period_s`'s default and the planner's
(`planning.timing.TimingOptions.stream_period_s`)."""


def stream_samples(times: FloatArray, q: FloatArray, period: float) -> tuple[FloatArray, FloatArray]:
    """Servo targets every `period` s through a time-stamped joint trajectory: (send times (K,), joints (K, 6)).

    A cubic spline through the samples (continuous acceleration, zero velocity at both ends: a streamed trajectory
    starts and ends at rest). Straight lines between samples would put each sample's whole change of velocity into
    one streaming period: on 20 ms plan samples streamed at 8 ms, 2.5 times the acceleration that was checked. On a
    jerk-limited profile sampled at 20 ms the spline's accelerations stay within about 1 % of the profile's (the
    planner keeps 3 % of every cap for this, `planning.timing.TimingOptions.cap_share`), but more at sharp
    corners: the caller checks the streamed targets against the caps before the first is sent, and the planner runs
    that check on its plans (`check_stream`, re-timing a plan that fails). The last target is the trajectory's end,
    sent one period after the one before it (never faster than planned)."""
    t = np.asarray(times, dtype=np.float64)
    qs = np.asarray(q, dtype=np.float64)
    n_send = int(np.ceil((t[-1] - t[0]) / period - 1e-9)) + 1
    send = t[0] + period * np.arange(n_send)
    if t.shape[0] < 2:
        return send, np.repeat(qs[:1], n_send, axis=0)
    m = _clamped_spline_accelerations(t, qs)
    x = np.minimum(send, t[-1])
    i = np.clip(np.searchsorted(t, x, side="right") - 1, 0, t.shape[0] - 2)
    h = (t[i + 1] - t[i])[:, None]
    a = (t[i + 1] - x)[:, None]
    b = (x - t[i])[:, None]
    out = (
        m[i] * a**3 / (6 * h)
        + m[i + 1] * b**3 / (6 * h)
        + (qs[i] / h - m[i] * h / 6) * a
        + (qs[i + 1] / h - m[i + 1] * h / 6) * b
    )
    return send, out


def _clamped_spline_accelerations(t: FloatArray, q: FloatArray) -> FloatArray:
    """Knot accelerations (N, 6) of the cubic spline through (t, q) with zero end velocities (tridiagonal solve)."""
    n = t.shape[0]
    h = np.diff(t)
    chord = np.diff(q, axis=0) / h[:, None]
    sub = np.zeros(n)
    diag = np.zeros(n)
    sup = np.zeros(n)
    rhs = np.zeros_like(q)
    diag[0], sup[0], rhs[0] = 2 * h[0], h[0], 6 * chord[0]
    sub[1:-1], diag[1:-1], sup[1:-1] = h[:-1], 2 * (h[:-1] + h[1:]), h[1:]
    rhs[1:-1] = 6 * (chord[1:] - chord[:-1])
    sub[-1], diag[-1], rhs[-1] = h[-1], 2 * h[-1], -6 * chord[-1]
    # Thomas algorithm (the matrix is diagonally dominant)
    c = np.zeros(n)
    d = np.zeros_like(q)
    c[0], d[0] = sup[0] / diag[0], rhs[0] / diag[0]
    for k in range(1, n):
        den = diag[k] - sub[k] * c[k - 1]
        c[k] = sup[k] / den
        d[k] = (rhs[k] - sub[k] * d[k - 1]) / den
    m = np.zeros_like(q)
    m[-1] = d[-1]
    for k in range(n - 2, -1, -1):
        m[k] = d[k] - c[k] * m[k + 1]
    return m


def waypoint_samples(traj_q: FloatArray, waypoint_q: FloatArray) -> tuple[list[int], FloatArray]:
    """Where a trajectory (M, 6) passes its waypoints (N, 6): each waypoint after the first matched in order to its
    nearest sample at or after the previous one's (the first at sample 0), and that sample's distance from the
    waypoint (N,), rad, largest joint difference (0 for the first). Execution splits plan.json's trajectory there
    (refusing a plan whose samples miss a waypoint) and the planner cuts its stream check there (`stream_cuts`)."""
    tq = np.asarray(traj_q, dtype=np.float64)
    wq = np.asarray(waypoint_q, dtype=np.float64)
    idx = [0]
    gap = np.zeros(len(wq))
    for k in range(1, len(wq)):
        start = idx[-1]
        d = np.max(np.abs(tq[start:] - wq[k]), axis=1)
        j = int(np.argmin(d))
        idx.append(start + j)
        gap[k] = d[j]
    return idx, gap


def stream_cuts(traj_q: FloatArray, names: Sequence[str], waypoint_q: FloatArray, at: Sequence[str]) -> list[int]:
    """Sample indices where execution ends one streamed piece and starts the next (`check_stream`'s cuts): 0, the
    waypoints named in `at` (where the gripper acts and the arm rests) and the last waypoint, each at its sample
    (`waypoint_samples`)."""
    idx, _ = waypoint_samples(traj_q, waypoint_q)
    last = len(names) - 1
    return [0] + [idx[k] for k in range(1, len(names)) if names[k] in at or k == last]


def check_stream(
    times: FloatArray,
    q: FloatArray,
    cuts: Sequence[int],
    limits: SafetyLimits,
    period: float = STREAM_PERIOD_S,
) -> None:
    """The driver's check of the servo commands it would stream for trajectory (times (M,), q (M, 6)), cut into the
    pieces execution streams one by one (sample indices `cuts`, increasing, first 0 and last the final sample; the
    arm rests at each): per piece `stream_samples(times[a:b + 1], q[a:b + 1], period)` and
    `limits.check_trajectory(grid, samples, "streamed commands")`, exactly as `GuardedDriver.follow_trajectory`
    does (a piece of one sample is not streamed). Raises the driver's SafetyViolation for the first piece refused."""
    t = np.asarray(times, dtype=np.float64)
    qs = np.asarray(q, dtype=np.float64)
    for a, b in zip(cuts[:-1], cuts[1:], strict=True):
        if b - a < 1:
            continue
        grid, samples = stream_samples(t[a : b + 1], qs[a : b + 1], period)
        limits.check_trajectory(grid, samples, "streamed commands")
