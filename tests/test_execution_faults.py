"""Every way out stops the arm; faults become one typed line, never an abort or a hang (issue 18).

The CLI (`normpos-grasp execute ... --execute`, and a library script for moveL) runs as a subprocess with the real
ur_rtde client (in SupervisedRtdeDriver's child process) against the loopback controller in its own process.
`Campaign` (normpos_grasp.sim.ur_emulator.campaign) injects the fault mid-move and measures on the controller: the
stop command's arrival, the arm at rest, motion commands after the stop, and for signals the joint state read over
RTDE (ur_rtde's RTDEReceiveInterface) for 0.6 s after the signal. Timing bounds are loose (a loaded 2-core machine);
benchmarks/bench_faults.py reports the figures.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rtde_control")

from normpos_grasp.errors import ControllerMismatch, InputError, SafetyViolation
from normpos_grasp.execution import GripperIO, SafetyLimits, SimDriver, execute_plan
from normpos_grasp.execution.rtde_driver import check_controller
from normpos_grasp.sim.ur_emulator import EmulatorProcess
from normpos_grasp.sim.ur_emulator.campaign import Campaign, CaseResult, write_plan

HOST = f"127.{100 + os.getpid() % 100}.{os.getpid() // 100 % 250 + 1}.21"
HOME = np.array([0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0])
SLACK_S = 0.25  # s: the issue asks 0.1 s; the bound here leaves room for a loaded CI machine


@pytest.fixture(scope="module")
def campaign(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Campaign]:
    # SCHED_FIFO for the emulator's 500 Hz loop where allowed (else it runs normally and says so in its log): a
    # starved loop makes the emulated servo catch up in jumps on a loaded machine
    with Campaign(HOST, tmp_path_factory.mktemp("faults"), rt_priority=10) as c:
        yield c


def _why(r: CaseResult) -> str:
    return (
        f"{r.case}: exit {r.exit_code}, rest {r.rest_s}, stop {r.stop_cmd} at {r.stop_cmd_s}, send gap "
        f"{r.send_gap_s:.3f}, moved {r.moved_after_fault_rad}, stderr {r.stderr}"
    )


def _assert_clean_exit(r: CaseResult) -> None:
    assert not r.hung and not r.aborted, _why(r)
    assert r.exit_code == r.expected_exit, _why(r)
    assert not r.traceback and len(r.error_lines) == 1, r.stderr
    assert r.exit_after_fault_s is not None and r.exit_after_fault_s < 60.0  # includes the CLI start (imports)


@pytest.mark.slow
@pytest.mark.parametrize("case", ["sigint_movej", "sigterm_movej", "sigint_movel", "sigterm_movel"])
def test_signal_mid_move_stops_the_arm_before_disconnecting(campaign: Campaign, case: str) -> None:
    r = campaign.run(case)
    _assert_clean_exit(r)
    assert r.stop_cmd in ("stopJ", "stopL"), _why(r)  # a stop command, not just a disconnect
    assert r.stop_cmd_s is not None and r.stop_cmd_s < SLACK_S
    assert r.rest_s is not None and r.rest_s < SLACK_S + r.send_gap_s, _why(r)
    # RTDE: still (qd ~ 0, q constant) soon after the signal, and for the rest of the 0.6 s window
    assert r.rtde_still_s is not None and r.rtde_still_s < SLACK_S + 0.05 + r.send_gap_s, _why(r)
    assert r.drift_after_still_rad is not None and r.drift_after_still_rad < 1e-4
    assert r.moved_after_fault_rad is not None and r.moved_after_fault_rad < 0.1  # issue 18 measured 1.18 rad
    assert r.motion_after_stop == 0


@pytest.mark.slow
@pytest.mark.parametrize("case", ["sigint_stream", "sigterm_stream"])
def test_signal_mid_stream_stops_the_arm(campaign: Campaign, case: str) -> None:
    r = campaign.run(case)
    _assert_clean_exit(r)
    assert r.stop_cmd in ("servoStop", "stopJ"), _why(r)
    assert r.rest_s is not None and r.rest_s < SLACK_S + r.send_gap_s, _why(r)
    assert r.rtde_still_s is not None and r.rtde_still_s < SLACK_S + 0.05 + r.send_gap_s
    assert r.motion_after_stop == 0  # no servoJ sample after the stop


@pytest.mark.slow
def test_plan_for_another_robot_is_refused_and_nothing_moves(campaign: Campaign) -> None:
    r = campaign.run("model_mismatch")  # a ur10e plan on a ur5e controller
    _assert_clean_exit(r)
    assert "UR5" in r.error_lines[0] and "ur10e" in r.error_lines[0]
    assert r.motion_cmds_in_run == 0 and r.moved_after_fault_rad == 0.0


@pytest.mark.slow
def test_bad_gripper_output_refused_before_any_motion(campaign: Campaign) -> None:
    r = campaign.run("bad_io")  # --close-output 99
    _assert_clean_exit(r)
    assert "close_output = 99" in r.error_lines[0]
    assert r.motion_cmds_in_run == 0 and r.moved_after_fault_rad == 0.0


@pytest.mark.slow
@pytest.mark.parametrize("case", ["sigint_run", "sigterm_run"])
def test_signal_during_the_cell_loop_stops_the_arm(campaign: Campaign, case: str) -> None:
    """`normpos-grasp run --execute` (synthetic bin, one pick): the signal arrives during one of the loop's moves."""
    r = campaign.run(case)
    _assert_clean_exit(r)
    assert "interrupted by SIG" in r.error_lines[0]
    assert r.stop_cmd in ("stopJ", "stopL", "servoStop"), _why(r)
    assert r.rest_s is not None and r.rest_s < SLACK_S + r.send_gap_s, _why(r)
    assert r.motion_after_stop == 0


@pytest.mark.slow
@pytest.mark.parametrize("case", ["protective_stop", "estop"])
def test_safety_stops_become_one_typed_line(campaign: Campaign, case: str) -> None:
    """The controller stops the arm itself; the CLI reports the stop in one line (exit 2) and sends nothing more."""
    r = campaign.run(case)
    _assert_clean_exit(r)
    assert ("protective stop" if case == "protective_stop" else "emergency stop") in r.error_lines[0]
    assert r.rest_s is not None and r.rest_s < SLACK_S, _why(r)
    assert r.motion_after_stop == 0


@pytest.mark.slow
@pytest.mark.parametrize("case", ["link_drop", "short_stall", "stall", "killed_controller"])
def test_link_faults_become_one_typed_line(campaign: Campaign, case: str) -> None:
    r = campaign.run(case)
    _assert_clean_exit(r)  # exit 2 within seconds: no SIGABRT from ur_rtde, no hang
    assert "link" in r.error_lines[0] or "state" in r.error_lines[0] or "ur_rtde" in r.error_lines[0]
    if case != "killed_controller":
        assert r.rest_s is not None and r.rest_s < r.stop_budget_s + SLACK_S, _why(r)
        assert r.motion_after_stop == 0


# ---------------------------------------------------------------------- in-process checks (no subprocess CLI)
def test_controller_identity_checked_against_the_model(tmp_path: Path) -> None:
    host = HOST.rsplit(".", 1)[0] + ".22"
    with EmulatorProcess(
        host, "ur5e", ready_timeout_s=60.0, log_path=tmp_path / "emu.log", extra_args=("--serial", "S42")
    ):
        ident = check_controller(host, "ur5e", "S42")
        assert ident.model == "UR5" and ident.software_major >= 5
        with pytest.raises(ControllerMismatch, match="ur10e"):
            check_controller(host, "ur10e")
        with pytest.raises(ControllerMismatch, match="serial"):
            check_controller(host, "ur5e", "S43")


@pytest.mark.parametrize(
    "kwargs",
    [
        {"close_output": 99},
        {"close_output": -1},
        {"close_output": 16},
        {"close_output": 2, "tool": True},
        {"open_output": 0, "close_output": 0},
        {"grip_detect_input": 18},
    ],
)
def test_gripper_io_out_of_range_refused(kwargs: dict[str, object]) -> None:
    with pytest.raises(InputError):
        GripperIO(**kwargs)  # type: ignore[arg-type]


def test_gripper_io_in_range_accepted() -> None:
    GripperIO(close_output=15, open_output=8, grip_detect_input=17)
    GripperIO(close_output=1, open_output=0, tool=True)


@pytest.mark.parametrize(
    "kwargs",
    [{"max_joint_accel": 1e9}, {"max_joint_accel": 40.01}, {"max_joint_accel": float("nan")}, {"max_tool_speed": 5.0}],
)
def test_caps_above_the_ceilings_refused(kwargs: dict[str, float]) -> None:
    with pytest.raises(SafetyViolation):
        SafetyLimits.for_model("ur5e", **kwargs)  # type: ignore[arg-type]


def test_cell_caps_above_rated_refused() -> None:
    from dataclasses import replace

    base = SafetyLimits.for_model("ur5e")
    with pytest.raises(SafetyViolation, match="max_joint_accel"):
        replace(base, max_joint_accel=np.full(6, 100000.0))
    with pytest.raises(SafetyViolation, match="rated"):
        replace(base, max_joint_speed=np.full(6, 4.0))


def test_plan_whose_samples_exceed_the_caps_refused(tmp_path: Path) -> None:
    import json

    q1 = HOME + np.array([0.3, 0, 0, 0, 0, 0])
    plan = json.loads(write_plan(tmp_path / "p.json", "ur5e", HOME, q1, 0.25).read_text())  # peak 23.7 rad/s^2
    with pytest.raises(SafetyViolation, match="acceleration"):
        execute_plan(None, plan, SafetyLimits.for_model("ur5e", max_joint_accel=4.0))  # dry run: nothing sent


def test_missed_grip_stops_the_pick(tmp_path: Path) -> None:
    import json

    q_grasp = HOME + np.array([0.2, 0, 0, 0, 0, 0])
    plan = json.loads(write_plan(tmp_path / "p.json", "ur5e", HOME, q_grasp, None).read_text())
    plan["joint_waypoints"][1]["name"] = "grasp"
    plan["joint_waypoints"].append({"name": "place", "q": (HOME - 0.2 * np.eye(6)[0]).tolist()})
    lim = SafetyLimits.for_model("ur5e")
    drv = SimDriver(lim, GripperIO(close_output=0, open_output=1, grip_detect_input=2, settle_s=0.05), q_home=HOME)
    drv.connect()
    try:
        report = execute_plan(drv, plan, lim, dry_run=False)
        assert report.status == "grip_failed" and report.grip_detected is False
        assert np.max(np.abs(drv.state().q - q_grasp)) < 1e-3  # stopped at the grasp: never went on to the place
    finally:
        drv.disconnect()
        drv.shutdown()


def test_supervised_driver_survives_a_dropped_link_and_resumes(tmp_path: Path) -> None:
    """The client runs in SupervisedRtdeDriver's child: a hard drop of every RTDE link is a latched ConnectionLost in
    this process within the stale-state time (this process never aborts), the arm is stopped and not moved again, and
    resume() starts a fresh client that drives the arm (issue 18: 3 of 3 resume() calls aborted before)."""
    import threading
    import time

    from normpos_grasp.errors import ConnectionLost, DriverFault
    from normpos_grasp.execution import SupervisedRtdeDriver

    host = HOST.rsplit(".", 1)[0] + ".23"
    with EmulatorProcess(host, "ur5e", ready_timeout_s=60.0, log_path=tmp_path / "emu.log") as emu:
        drv = SupervisedRtdeDriver(host, SafetyLimits.for_model("ur5e"))
        drv.connect()
        try:
            for round_ in range(3):
                start = drv.state().q
                goal = start + np.array([1.0 if round_ % 2 == 0 else -1.0, 0, 0, 0, 0, 0])
                t_drop: list[float] = []

                def drop(marks: list[float] = t_drop) -> None:
                    marks.append(time.monotonic())
                    emu.emu("drop")

                threading.Timer(0.5, drop).start()
                with pytest.raises(ConnectionLost):
                    drv.move_joints([goal], 0.6, 1.0)
                assert time.monotonic() - t_drop[0] < 2.0
                with pytest.raises(DriverFault, match="resume"):
                    drv.move_joints([start], 0.6, 1.0)  # latched: nothing sent
                time.sleep(0.3)
                info = dict(p.split("=", 1) for p in emu.emu("since", f"{t_drop[0]:.6f}").split()[2:])
                assert info["moving"] == "False" and info["motion_after_stop"] == "0"
                drv.resume()
                st = drv.move_joints([start], 2.0, 4.0)
                assert np.max(np.abs(st.q - start)) < 1e-3
        finally:
            drv.disconnect()


@pytest.mark.parametrize("sig", ["SIGINT", "SIGTERM"])
def test_signal_mid_move_stops_the_sim_arm_and_latches(sig: str) -> None:
    """In-process: under stop_signals() a signal mid-move_joints leaves through the driver's exception path, which
    stops the arm (halt_decel) before the exception reaches the caller, and latches a fault."""
    import signal
    import threading
    import time

    from normpos_grasp.errors import DriverFault, TerminationRequested
    from normpos_grasp.execution import exit_code, stop_signals

    lim = SafetyLimits.for_model("ur5e")
    drv = SimDriver(lim, q_home=HOME)
    drv.connect()
    try:
        signum = getattr(signal, sig)
        with stop_signals():
            threading.Timer(0.6, os.kill, (os.getpid(), signum)).start()
            with pytest.raises(KeyboardInterrupt) as info:
                drv.move_joints([HOME + np.array([1.2, 0, 0, 0, 0, 0])], 0.8, 1.2)
        assert isinstance(info.value, TerminationRequested) == (sig == "SIGTERM")
        assert exit_code(info.value) == (143 if sig == "SIGTERM" else 130)
        st = drv.state()
        assert np.max(np.abs(st.qd)) < 1e-6  # at rest when the exception arrives (stopJ waits for rest)
        q = st.q.copy()
        time.sleep(0.2)
        assert np.max(np.abs(drv.state().q - q)) < 1e-9
        assert 0.05 < abs(q[0] - HOME[0]) < 1.0  # stopped mid-move
        assert drv.fault is not None
        assert ("SIGTERM" if sig == "SIGTERM" else "KeyboardInterrupt") in str(drv.fault)
        with pytest.raises(DriverFault, match="resume"):
            drv.move_joints([HOME], 0.8, 1.2)
    finally:
        drv.disconnect()
        drv.shutdown()


def test_an_interrupts_stop_is_sized_for_the_planned_speed_when_the_state_lags() -> None:
    """The state last checked may be old (read while the arm still accelerated, up to the stall watchdog's age): the
    stop after a Ctrl-C is sized for the larger of the measured and the planned joint speed, so the arm still rests
    within halt_time_s. Here every state reads the joints at rest."""
    import signal
    import threading

    from normpos_grasp.execution import stop_signals
    from normpos_grasp.execution.driver import ArmState

    decels: list[float] = []

    class LaggingState(SimDriver):
        def _backend_state(self) -> ArmState:
            st = super()._backend_state()
            st.qd[:] = 0.0  # a reading from before the arm sped up
            return st

        def _backend_stop(self, decel: float) -> None:
            decels.append(decel)
            super()._backend_stop(decel)

    lim = SafetyLimits.for_model("ur5e")
    drv = LaggingState(lim, q_home=HOME)
    drv.connect()
    try:
        with stop_signals():
            threading.Timer(0.5, os.kill, (os.getpid(), signal.SIGINT)).start()
            with pytest.raises(KeyboardInterrupt):
                drv.move_joints([HOME + np.array([1.2, 0, 0, 0, 0, 0])], 1.5, 3.0)
        assert decels and decels[0] == pytest.approx(drv.options.halt_decel_for(1.5))
        assert decels[0] > drv.options.halt_decel  # the measured speed alone (0) would give the floor
    finally:
        drv.disconnect()
        drv.shutdown()


@pytest.mark.parametrize("sig", ["SIGINT", "SIGTERM"])
def test_a_signal_inside_an_uninterrupted_block_is_raised_after_it(sig: str) -> None:
    """The supervised driver reads and writes each pipe message inside `uninterrupted()`: a signal between a
    message's header and body would leave the pipe to the ur_rtde child out of step (the child died of it)."""
    import signal

    from normpos_grasp.interrupts import Interrupted, exit_code, signals_raise, uninterrupted

    reached_end = False
    with pytest.raises(Interrupted) as info, signals_raise(), uninterrupted():
        os.kill(os.getpid(), getattr(signal, sig))
        for _ in range(1000):  # the handler has run by now; nothing was raised inside the block
            pass
        reached_end = True
    assert reached_end
    assert exit_code(info.value) == (143 if sig == "SIGTERM" else 130)
