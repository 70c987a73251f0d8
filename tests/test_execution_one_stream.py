"""One stream per plan (issue 19 item 7): the pieces of a timed plan run in one servo stream that holds the arm at
rest while the arm's own outputs switch the gripper, and a gripper already open and settled is not waited for again.
Every way out of an open stream (another motion, stop, a fault, a trajectory that does not start where it holds)
closes it."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pytest

from normpos_grasp.errors import ProtectiveStop, SafetyViolation
from normpos_grasp.execution import ExecuteOptions, GripperIO, SafetyLimits, SimDriver, execute_plan

HOME = np.array([0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0])
SETTLE = 0.15


def _plan_doc(q0: np.ndarray = HOME, sign: float = 1.0) -> dict[str, Any]:
    """A timed plan home -> grasp -> place -> post_place from `q0`, 0.6 s rest to rest per piece (plan.json's
    layout); `sign` -1 runs the same steps backwards."""
    names = ["home", "grasp", "place", "post_place"]
    steps = [[0.0] * 6, [0.12, 0.05, 0.0, 0.0, 0.0, 0.1], [-0.15, 0.0, 0.05, 0.0, 0.0, 0.0], [0.0, -0.05, 0, 0, 0, 0]]
    qs = q0 + sign * np.cumsum(np.asarray(steps), axis=0)
    samples, t0 = [], 0.0
    for k in range(1, len(qs)):
        s = np.linspace(0.0, 1.0, 21)[(1 if k > 1 else 0) :]
        for u in s:
            w = (1 - np.cos(np.pi * u)) / 2
            samples.append({"t": round(t0 + 0.6 * u, 6), "q": (qs[k - 1] + w * (qs[k] - qs[k - 1])).tolist()})
        t0 += 0.6
    return {
        "status": "ok",
        "robot": "ur5e",
        "joint_waypoints": [{"name": n, "q": q.tolist()} for n, q in zip(names, qs, strict=True)],
        "trajectory": {"samples": samples},
    }


@pytest.fixture()
def sim() -> Iterator[SimDriver]:
    drv = SimDriver(SafetyLimits.for_model("ur5e"), GripperIO(settle_s=SETTLE), q_home=HOME, time_scale=8.0)
    drv.connect()
    yield drv
    drv.shutdown()


def _count(drv: SimDriver, name: str) -> list[float]:
    """Spy on drv.<name>: the returned list gets a time stamp per call."""
    calls: list[float] = []
    inner: Callable[..., Any] = getattr(drv, name)

    def spy(*args: Any, **kwargs: Any) -> Any:
        calls.append(time.monotonic())
        return inner(*args, **kwargs)

    setattr(drv, name, spy)
    return calls


class _Fake:
    """A gripper with its own channel (as the Robotiq socket): the arm driver does not switch it."""

    detects_grip = False

    def connect(self) -> None: ...

    def disconnect(self) -> None: ...

    def open(self, opening_m: float | None = None, watch: Any = None) -> None:
        time.sleep(0.01)

    def close(self, watch: Any = None) -> None:
        time.sleep(0.01)

    def grip_detected(self) -> bool:
        return True


def _trajectory(q0: np.ndarray, dq: list[float], duration: float = 0.6) -> tuple[np.ndarray, np.ndarray]:
    t = np.linspace(0.0, duration, 31)
    return t, q0 + np.outer((1 - np.cos(np.pi * t / duration)) / 2, dq)


def test_a_plan_runs_in_one_stream_held_while_the_gripper_acts(sim: SimDriver) -> None:
    plan_doc = _plan_doc()
    limits = SafetyLimits.for_model("ur5e")
    begins, ends = _count(sim, "_backend_servo_begin"), _count(sim, "_backend_servo_end")
    holds = _count(sim, "_backend_servo")
    waits: list[tuple[float, float]] = []
    wait_io = sim._wait_io

    def timed_wait(settle_s: float) -> None:
        t0 = time.monotonic()
        wait_io(settle_s)
        waits.append((t0, time.monotonic()))

    sim._wait_io = timed_wait  # type: ignore[method-assign]
    report = execute_plan(sim, plan_doc, limits, dry_run=False)
    assert report.status == "executed" and report.final_error_rad is not None and report.final_error_rad < 1e-3
    assert [s.kind for s in report.steps] == [
        "gripper_open", "trajectory", "gripper_close", "trajectory", "gripper_open", "trajectory",
    ]  # fmt: skip
    assert len(begins) == 1 and len(ends) == 1 and not sim.streaming  # one stream, closed at the plan's end
    # the close and the place's open each waited the settle time, the arm held by the stream meanwhile
    assert len(waits) == 3 and all(b - a >= SETTLE - 1e-3 for a, b in waits)
    for a, b in waits[1:]:
        sent = [t for t in holds if a <= t <= b]
        assert len(sent) >= int(SETTLE / sim.options.stream_period_s) // 2  # hold targets within the watchdog

    # a gripper on its own channel: the pieces run as separate streams (nothing would hold the arm meanwhile)
    begins.clear()
    ends.clear()
    back = execute_plan(sim, plan_doc, limits, dry_run=False, gripper=_Fake())
    assert back.status == "executed" and len(begins) == 3 and len(ends) == 3 and not sim.streaming


def test_an_open_gripper_that_settled_is_not_waited_for_again(sim: SimDriver) -> None:
    def timed(call: Callable[[], None]) -> float:
        t0 = time.monotonic()
        call()
        return time.monotonic() - t0

    assert timed(sim.gripper_open) >= SETTLE  # after connect: the state is not known
    assert timed(sim.gripper_open) < SETTLE / 3  # open and settled, the outputs still read open: nothing to wait
    assert timed(sim.gripper_close) >= SETTLE
    assert timed(sim.gripper_open) >= SETTLE  # closed since: the fingers must open
    assert timed(sim.gripper_open) < SETTLE / 3
    sim._backend_set_output(sim.gripper.open_output, False, False)  # type: ignore[arg-type]  # switched elsewhere
    assert timed(sim.gripper_open) >= SETTLE
    sim.resume()  # after a resume (or a fault, a reconnect) the open waits again
    assert timed(sim.gripper_open) >= SETTLE


def test_every_way_out_of_an_open_stream_closes_it(sim: SimDriver) -> None:
    t, q = _trajectory(HOME, [0.2, 0.0, 0.0, 0.0, 0.0, 0.1])
    st = sim.follow_trajectory(t, q, keep_streaming=True)
    assert sim.streaming and np.max(np.abs(st.q - q[-1])) < 1e-3
    goal = q[-1] + np.array([0.0, 0.1, 0.0, 0.0, 0.0, 0.0])
    st = sim.move_joints([goal], 1.0, 2.0)  # another motion: the stream ends first
    assert not sim.streaming and np.max(np.abs(st.q - goal)) < 1e-6

    sim.follow_trajectory(*_trajectory(goal, [-0.1, 0.0, 0.0, 0.0, 0.0, 0.0]), keep_streaming=True)
    with pytest.raises(SafetyViolation, match="away from the current joints"):
        sim.follow_trajectory(*_trajectory(goal, [0.1, 0.0, 0.0, 0.0, 0.0, 0.0]))  # not where it holds
    assert not sim.streaming and sim.fault is None

    here = sim.state().q
    sim.follow_trajectory(*_trajectory(here, [0.1, 0.0, 0.0, 0.0, 0.0, 0.0]), keep_streaming=True)
    threading.Timer(0.05, sim.inject_protective_stop).start()
    with pytest.raises(ProtectiveStop):
        sim.gripper_close()  # a fault while the gripper acts in the open stream
    assert not sim.streaming and isinstance(sim.fault, ProtectiveStop)


def test_a_stream_goes_on_from_where_it_holds(sim: SimDriver) -> None:
    begins, ends = _count(sim, "_backend_servo_begin"), _count(sim, "_backend_servo_end")
    t, q = _trajectory(HOME, [0.2, 0.0, 0.0, 0.0, 0.0, 0.0])
    sim.follow_trajectory(t, q, keep_streaming=True)
    sim.gripper_close()
    t2, q2 = _trajectory(q[-1], [0.0, 0.1, 0.0, 0.0, 0.0, 0.0])
    st = sim.follow_trajectory(t2, q2)
    assert len(begins) == 1 and len(ends) == 1 and not sim.streaming
    assert np.max(np.abs(st.q - q2[-1])) < 1e-3
    sim.stop()  # nothing open: a no-op for the stream
    assert len(ends) == 1


def test_plans_back_to_back_go_on_in_the_stream_held_at_the_end(sim: SimDriver) -> None:
    begins, ends = _count(sim, "_backend_servo_begin"), _count(sim, "_backend_servo_end")
    limits = SafetyLimits.for_model("ur5e")
    held = ExecuteOptions(hold_at_end=True)
    first = _plan_doc()
    report = execute_plan(sim, first, limits, dry_run=False, options=held)
    assert report.status == "executed" and sim.streaming  # left open, holding the plan's end
    end_q = np.asarray(first["joint_waypoints"][-1]["q"])
    report = execute_plan(sim, _plan_doc(end_q, -1.0), limits, dry_run=False, options=held)
    assert report.status == "executed" and len(begins) == 1 and len(ends) == 0  # one stream for both plans
    sim.end_stream()
    assert len(ends) == 1 and not sim.streaming
    # a stream left idle for half the watchdog is restarted by the next trajectory, never raced
    here = sim.state().q
    sim.follow_trajectory(*_trajectory(here, [0.1, 0.0, 0.0, 0.0, 0.0, 0.0]), keep_streaming=True)
    time.sleep(0.6 * sim.options.watchdog_s)
    sim.follow_trajectory(*_trajectory(sim.state().q, [-0.1, 0.0, 0.0, 0.0, 0.0, 0.0]))
    assert len(begins) == 3 and len(ends) == 3 and sim.fault is None and not sim.streaming
