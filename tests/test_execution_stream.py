"""The servo stream's targets: what is sent stays within the accelerations that were checked."""

from __future__ import annotations

import numpy as np
import pytest

from normpos_grasp.cell.stream import stream_samples
from normpos_grasp.errors import SafetyViolation
from normpos_grasp.execution.safety import SafetyLimits


def _jerk_limited(
    jerk: float = 50.0, accel: float = 4.85, hold_s: float = 0.3, dt: float = 0.0005
) -> tuple[np.ndarray, np.ndarray]:
    """A rest-to-rest jerk-limited profile (fine steps), its true peak acceleration `accel` rad/s^2."""
    ramp = accel / jerk
    phases = [(jerk, ramp), (0.0, hold_s), (-jerk, ramp), (0.0, 0.2), (-jerk, ramp), (0.0, hold_s), (jerk, ramp)]
    t, q, a, v, x, now = [0.0], [0.0], 0.0, 0.0, 0.0, 0.0
    for j, duration in phases:
        for _ in range(int(round(duration / dt))):
            a += j * dt
            v += a * dt
            x += v * dt
            now += dt
            t.append(now)
            q.append(x)
    return np.asarray(t), np.asarray(q)


def _peak_fd_accel(t: np.ndarray, q: np.ndarray) -> float:
    dt = np.diff(t)
    qd = np.diff(q, axis=0) / dt[:, None]
    return float(np.max(np.abs(np.diff(qd, axis=0) / (0.5 * (dt[1:] + dt[:-1]))[:, None])))


def test_streamed_targets_keep_the_planned_acceleration() -> None:
    fine_t, fine_q = _jerk_limited()
    plan_t = np.append(np.arange(0.0, fine_t[-1], 0.02), fine_t[-1])
    plan_q = np.tile(np.interp(plan_t, fine_t, fine_q)[:, None], (1, 6)) * np.linspace(0.2, 1.0, 6)
    send_t, sent = stream_samples(plan_t, plan_q, 0.008)
    planned = _peak_fd_accel(plan_t, plan_q)
    streamed = _peak_fd_accel(send_t, sent)
    assert planned == pytest.approx(4.85, rel=1e-3)
    assert streamed <= 1.02 * planned  # straight lines between the 20 ms samples would give 2.5x
    linear = np.stack([np.interp(np.minimum(send_t, plan_t[-1]), plan_t, plan_q[:, j]) for j in range(6)], axis=1)
    assert _peak_fd_accel(send_t, linear) > 2.0 * planned  # the failure this guards against
    # the curve follows the profile and ends on the trajectory's end, sent at a fixed period
    truth = np.interp(np.minimum(send_t, fine_t[-1]), fine_t, fine_q)
    assert np.max(np.abs(sent[:, 5] - truth)) < 1e-4
    np.testing.assert_allclose(sent[-1], plan_q[-1], atol=1e-12)
    np.testing.assert_allclose(np.diff(send_t), 0.008, atol=1e-12)


def test_streamed_targets_are_checked_against_the_caps() -> None:
    limits = SafetyLimits.for_model("ur5e", max_joint_accel=4.0)
    fine_t, fine_q = _jerk_limited(accel=4.0)
    plan_t = np.append(np.arange(0.0, fine_t[-1], 0.02), fine_t[-1])
    plan_q = np.tile(np.interp(plan_t, fine_t, fine_q)[:, None], (1, 6)) * 0.5
    plan_q[:, 0] = np.interp(plan_t, fine_t, fine_q)
    limits.check_trajectory(plan_t, plan_q)  # the plan itself peaks at the 4 rad/s^2 cap ...
    send_t, sent = stream_samples(plan_t, plan_q, 0.008)
    with pytest.raises(SafetyViolation, match="streamed commands"):
        limits.check_trajectory(send_t, sent, "streamed commands")  # ... what would be streamed is not
