"""The arm driver contract (`ArmDriver`) and the guarded base both drivers share.

A driver connects, reports `ArmState`, runs joint paths, streamed trajectories and linear moves, stops, and drives
a gripper through digital outputs. `GuardedDriver` implements the rules every driver follows, on top of a few
backend primitives: every target is checked against `SafetyLimits` before anything is sent; a protective stop,
e-stop, lost connection or timeout during a move stops the arm, raises a typed `DriverFault` and latches it, so
nothing further is sent until `resume()`; a lost connection is never retried blindly: `resume()` reconnects and
re-reads the state.
"""

from __future__ import annotations

import abc
import logging
import time
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import numpy as np

from normpos_grasp.cell.stream import STREAM_PERIOD_S, stream_samples
from normpos_grasp.errors import (
    ConnectionLost,
    DriverFault,
    DriverTimeout,
    EmergencyStop,
    InputError,
    ProtectiveStop,
    SafetyViolation,
    TerminationRequested,
    ZoneIntrusion,
)
from normpos_grasp.typing import ArrayLike, FloatArray

from .safety import SafetyLimits

log = logging.getLogger(__name__)

STANDARD_OUTPUTS, CONFIGURABLE_OUTPUTS, TOOL_OUTPUTS = 8, 8, 2  # UR digital outputs per bank
INPUT_BITS = 18  # digital input bits: standard 0-7, configurable 8-15, tool 16-17
SAFETY_BIT_PROTECTIVE = 1 << 2
SAFETY_BIT_EMERGENCY = 1 << 7
ROBOT_MODE_RUNNING = 7


@dataclass(frozen=True)
class ArmState:
    """One snapshot of the arm. q, qd: (6,) rad, rad/s. base_from_tcp: (4, 4). timestamp: controller clock, s.

    robot_mode (7 running), safety_mode (1 normal, 3 protective stop, 7 e-stop), runtime_state (2 playing).
    digital_out, digital_in: standard bits 0-7, configurable 8-15, tool 16-17. analog_in: standard analog inputs 0
    and 1 (V or A, as each input's domain is set on the controller).
    """

    q: FloatArray
    qd: FloatArray
    base_from_tcp: FloatArray
    timestamp: float
    robot_mode: int
    safety_mode: int
    safety_status_bits: int
    runtime_state: int
    program_running: bool
    digital_out: int
    digital_in: int
    received_at: float  # time.monotonic() of the read, s
    analog_in: tuple[float, float] = (0.0, 0.0)

    @property
    def protective_stopped(self) -> bool:
        return bool(self.safety_status_bits & SAFETY_BIT_PROTECTIVE) or self.safety_mode == 3

    @property
    def emergency_stopped(self) -> bool:
        return bool(self.safety_status_bits & SAFETY_BIT_EMERGENCY) or self.safety_mode in (6, 7)


@dataclass(frozen=True)
class GripperIO:
    """A gripper wired to standard digital outputs (tool outputs with `tool=True`).

    close_output: output set high to close (parallel) or to suck (suction). open_output: output pulsed high to open
    (None: opening = close_output low). grip_detect_input: digital input high when a part is held (None: unknown).
    settle_s: time the gripper needs to act, s.
    """

    close_output: int = 0
    open_output: int | None = 1
    grip_detect_input: int | None = None
    settle_s: float = 0.3
    tool: bool = False

    def __post_init__(self) -> None:
        """Indices within the controller's ranges: outputs 0-7 standard, 8-15 configurable (tool: 0-1);
        grip-detect input bit 0-17 (standard, configurable, tool 16-17). InputError otherwise, before any motion."""
        n_out = TOOL_OUTPUTS if self.tool else STANDARD_OUTPUTS + CONFIGURABLE_OUTPUTS
        kind = "tool output (0-1)" if self.tool else "digital output (0-7 standard, 8-15 configurable)"
        for name, value in (("close_output", self.close_output), ("open_output", self.open_output)):
            if value is None and name == "open_output":
                continue
            if not isinstance(value, int) or isinstance(value, bool) or not 0 <= value < n_out:
                raise InputError(f"gripper {name} = {value!r} is not a {kind} of a UR controller")
        if self.open_output is not None and self.open_output == self.close_output:
            raise InputError(f"gripper open_output and close_output are both {self.close_output}")
        gi = self.grip_detect_input
        if gi is not None and (not isinstance(gi, int) or isinstance(gi, bool) or not 0 <= gi < INPUT_BITS):
            raise InputError(
                f"gripper grip_detect_input = {gi!r} is not a digital input bit of a UR controller "
                "(0-7 standard, 8-15 configurable, 16-17 tool)"
            )
        if not (np.isfinite(self.settle_s) and 0.0 <= self.settle_s <= 10.0):
            raise InputError(f"gripper settle_s = {self.settle_s!r} s must be in [0, 10]")


@dataclass(frozen=True)
class DriverOptions:
    """Timeouts and defaults. All times in seconds.

    connect_timeout_s: connecting. stale_state_s: the stall watchdog: no new controller timestamp for this long
    during a move = connection lost (the arm is stopped over the dashboard). 0.15 s is 75 packets of the 500 Hz
    RTDE stream; the age is taken where the stream is read (the ur_rtde client's process), so a descheduled caller
    does not trip it. move_margin_s, move_factor: a move times out after move_factor * expected duration +
    move_margin_s. poll_s: monitor period during moves. arrive_tol_rad: a move is complete when every joint is this
    close. stop_decel: joint deceleration for stops, rad/s^2. halt_decel, halt_time_s, halt_decel_max: the stop
    issued when a motion call is left by an interrupt (SIGINT/SIGTERM) or an exception decelerates the joints at
    max(halt_decel, peak joint speed / halt_time_s) rad/s^2, at most halt_decel_max (ur_rtde's joint acceleration
    ceiling): the arm rests within halt_time_s (UR's e-Series stopping time, 50 ms) up to 2 rad/s.
    stream_period_s: servo streaming period (`cell.stream.STREAM_PERIOD_S`, the period the planner checks its plans'
    streams at; `stream_samples` lives there too). watchdog_s: controller-side watchdog while streaming (the program
    stops if no command arrives for this long) and the most a stream tick may be late.
    """

    connect_timeout_s: float = 10.0
    stale_state_s: float = 0.15
    move_margin_s: float = 5.0
    move_factor: float = 2.0
    poll_s: float = 0.004
    arrive_tol_rad: float = 1e-4
    stop_decel: float = 3.0
    halt_decel: float = 10.0
    halt_time_s: float = 0.05
    halt_decel_max: float = 40.0
    stream_period_s: float = STREAM_PERIOD_S
    watchdog_s: float = 0.2

    def halt_decel_for(self, peak_speed: float) -> float:
        """Joint deceleration (rad/s^2) of an interrupt's stop for a leading joint at `peak_speed` rad/s."""
        return float(min(self.halt_decel_max, max(self.halt_decel, 1.1 * abs(peak_speed) / self.halt_time_s)))


@runtime_checkable
class ArmDriver(Protocol):
    """What execution needs from an arm. Every motion call checks its targets against `limits` first."""

    limits: SafetyLimits

    def connect(self) -> None: ...

    def disconnect(self) -> None: ...

    def state(self) -> ArmState: ...

    def move_joints(self, waypoints: ArrayLike, speed: float, accel: float, timeout_s: float | None = None) -> ArmState:
        """Run through joint waypoints (N, 6) with movej semantics (rad/s, rad/s^2); returns the final state."""
        ...

    def follow_trajectory(self, times: ArrayLike, q: ArrayLike, keep_streaming: bool = False) -> ArmState:
        """Stream time-stamped joint samples (N,), (N, 6) with servoj; returns the final state. keep_streaming: the
        stream stays open at the end, holding the last sample (GuardedDriver: the next trajectory goes on from there
        without a stop and restart of the stream)."""
        ...

    def move_linear(self, base_from_tcp: ArrayLike, speed: float, accel: float) -> ArmState:
        """Straight TCP line(s) to pose(s) (4, 4) or (N, 4, 4) in the base frame (m/s, m/s^2)."""
        ...

    def stop(self) -> None: ...

    def gripper_open(self) -> None: ...

    def gripper_close(self) -> None: ...

    def grip_detected(self) -> bool: ...

    def resume(self) -> None: ...

    @property
    def fault(self) -> DriverFault | None: ...


def movej_duration(q_from: FloatArray, q_to: FloatArray, speed: float, accel: float) -> float:
    """Duration (s) of a UR movej trapezoid between two configurations."""
    d = float(np.max(np.abs(np.asarray(q_to) - np.asarray(q_from))))
    if d == 0.0:
        return 0.0
    if d * accel < speed * speed:
        return 2.0 * float(np.sqrt(d / accel))
    return d / speed + speed / accel


class GuardedDriver(abc.ABC):
    """Safety checks, fault latch and move monitoring on top of backend primitives (`_backend_*`)."""

    def __init__(self, limits: SafetyLimits, gripper: GripperIO | None = None, options: DriverOptions | None = None):
        self.limits = limits
        self.gripper = gripper or GripperIO()
        self.options = options or DriverOptions()
        self._fault: DriverFault | None = None
        self.commands_sent = 0
        # (reason, protective, detail) set by another thread (`request_stop`); honoured at the next state poll
        self._stop_request: tuple[str, bool, Any] | None = None
        self.stop_sent_at = -1.0  # time.monotonic() when the last requested stop was sent, s
        self._peak_qd = 0.0  # rad/s: the leading joint's speed in the last state checked (sizes an interrupt's stop)
        # rad/s: the fastest the running motion call may drive a joint (its speed cap or its trajectory's peak; 0 at
        # rest). An interrupt's stop is sized for the larger of the two: the state last checked may be up to the stall
        # watchdog old, read while the arm was still accelerating.
        self._planned_qd = 0.0
        # follow_trajectory(keep_streaming=True) left the stream open, holding these joints (6,) rad
        self._hold: FloatArray | None = None
        self._hold_sent_at = 0.0  # time.monotonic() of the last command the open stream got, s
        # the last gripper command was an open that settled fully, and nothing has switched the gripper since
        self._open_settled = False

    # ------------------------------------------------------------------ backend primitives (override)
    @abc.abstractmethod
    def _backend_connect(self) -> None: ...

    @abc.abstractmethod
    def _backend_disconnect(self) -> None: ...

    @abc.abstractmethod
    def _backend_state(self) -> ArmState: ...

    @abc.abstractmethod
    def _backend_connected(self) -> bool: ...

    @abc.abstractmethod
    def _backend_move_path(self, waypoints: FloatArray, speed: float, accel: float) -> None:
        """Start (asynchronously) a movej path through `waypoints` (N, 6)."""
        ...

    @abc.abstractmethod
    def _backend_move_linear(self, poses: FloatArray, speed: float, accel: float) -> None: ...

    @abc.abstractmethod
    def _backend_servo(self, q: FloatArray, period_s: float) -> None: ...

    @abc.abstractmethod
    def _backend_servo_begin(self) -> None: ...

    @abc.abstractmethod
    def _backend_servo_end(self) -> None: ...

    @abc.abstractmethod
    def _backend_stop(self, decel: float) -> None: ...

    @abc.abstractmethod
    def _backend_link_lost(self) -> str | None:
        """The state stream is gone: halt the arm by a path that does not need it (no motion is re-sent).

        Returns a note for the fault message when that path failed too (None: the arm was stopped)."""
        ...

    @abc.abstractmethod
    def _backend_busy(self) -> bool:
        """True while the controller still executes the last motion."""
        ...

    @abc.abstractmethod
    def _backend_set_output(self, index: int, level: bool, tool: bool) -> None: ...

    @abc.abstractmethod
    def _backend_reset_faults(self) -> None:
        """Make the backend ready for motion again after an unlocked stop (e.g. re-upload the control script)."""
        ...

    def _backend_protective_stop(self) -> None:
        """Put the controller into a protective stop (a requested stop of the `protective` kind); backends without
        one stop with `halt_decel`."""
        self._backend_stop(self.options.halt_decel)

    # ------------------------------------------------------------------ public API
    @property
    def fault(self) -> DriverFault | None:
        return self._fault

    def connect(self) -> None:
        self._open_settled = False
        self._backend_connect()
        st = self._backend_state()
        self._check_state(st, during="connect", stop=False)

    def disconnect(self) -> None:
        """Stop the arm if it still moves (every way out stops it first), then close the connection."""
        self._open_settled = False
        try:
            self.end_stream()
            # after a protective or emergency stop the controller is already bringing the arm to rest (its program
            # has ended, so a stop command would only wait for a script that no longer runs)
            safety_stopped = isinstance(self._fault, ProtectiveStop | EmergencyStop)
            if (
                not safety_stopped
                and self._backend_connected()
                and float(np.max(np.abs(self._backend_state().qd))) > 1e-4
            ):
                log.warning("disconnect while the arm moves: stopping it first")
                self._backend_stop(self.options.halt_decel_for(self._stop_speed()))
        except (OSError, RuntimeError, DriverFault) as exc:
            log.warning("stop before disconnect failed (%s); stopping the program another way", exc)
            self._halt_fallback()
        finally:
            self._backend_disconnect()

    def _halt_fallback(self) -> None:
        """Stop the arm without the motion channel (e.g. the dashboard); never raises."""
        try:
            note = self._backend_link_lost()
            if note:
                log.warning("%s", note)
        except (OSError, RuntimeError, DriverFault) as exc:
            log.error("could not stop the arm by any channel: %s", exc)

    def _stop_speed(self) -> float:
        """rad/s an interrupt's stop is sized for: the measured peak or the running motion's planned one."""
        return max(self._peak_qd, self._planned_qd)

    def _halt_on_exit(self, exc: BaseException, what: str) -> None:
        """A motion call is being left by `exc`. Faults the driver raised itself have already stopped the arm (or the
        controller has); anything else (KeyboardInterrupt, TerminationRequested, an unexpected error) stops the arm
        now with `halt_decel`, before the exception travels on, and latches a fault so nothing further is sent."""
        if isinstance(exc, DriverFault) and self._fault is not None:
            return
        if isinstance(exc, TerminationRequested):
            reason = "SIGTERM"
        else:  # SIGINT arrives as a KeyboardInterrupt subclass (normpos_grasp.interrupts.Interrupted)
            reason = "KeyboardInterrupt" if isinstance(exc, KeyboardInterrupt) else type(exc).__name__
        try:
            if not self._backend_connected():
                raise ConnectionLost("not connected")
            decel = self.options.halt_decel_for(self._stop_speed())
            self._backend_stop(decel)
            log.info("%s left by %s: arm stopped (%.1f rad/s^2)", what, reason, decel)
        except (OSError, RuntimeError, DriverFault) as err:
            log.warning("stop after %s in %s failed (%s); stopping the program another way", reason, what, err)
            self._halt_fallback()
        if self._fault is None:
            self._fault = DriverFault(f"{what} interrupted by {reason}; arm stopped")

    def state(self) -> ArmState:
        if not self._backend_connected():
            raise self._latch(ConnectionLost("not connected to the controller; call connect() or resume()"))
        return self._backend_state()

    def resume(self) -> None:
        """Clear a latched fault after the cause is fixed: reconnect if needed, re-read state, re-arm the program.

        Raises the fault again if the controller is still stopped (protective stop not unlocked, e-stop pressed).
        """
        self._open_settled = False
        if self._fault is not None:
            log.info("resume after %s", type(self._fault).__name__)
        if not self._backend_connected() or isinstance(self._fault, ConnectionLost):
            self._backend_disconnect()
            self._backend_connect()
        st = self._fresh_state(time.monotonic())
        if st.emergency_stopped:
            raise self._latch(EmergencyStop("emergency stop still active: release it, power on, then resume()"))
        if st.protective_stopped:
            raise self._latch(
                ProtectiveStop("protective stop still active: unlock it (dashboard / pendant), then resume()")
            )
        self._backend_reset_faults()
        self._fault = None
        self._stop_request = None

    def _fresh_state(self, after: float) -> ArmState:
        """The first state received after `after` (time.monotonic()); ConnectionLost if none within stale_state_s."""
        deadline = after + max(self.options.stale_state_s, 0.1)
        ts0 = self._backend_state().timestamp
        while True:
            st = self._backend_state()
            if st.received_at > after and st.timestamp > ts0 + 0.003:  # at least one full controller cycle later
                return st
            if time.monotonic() > deadline:
                raise self._latch(
                    ConnectionLost(f"no fresh robot state within {self.options.stale_state_s} s; check the link")
                )
            time.sleep(0.002)

    def stop(self) -> None:
        """Decelerate to rest (allowed even when faulted); an open stream (`keep_streaming`) is ended."""
        if self._backend_connected():
            self._backend_stop(self.options.stop_decel)
        self.end_stream()

    @property
    def streaming(self) -> bool:
        """A stream is open, holding the arm where the last trajectory ended (`keep_streaming=True`)."""
        return self._hold is not None

    def end_stream(self) -> None:
        """End the stream `follow_trajectory(keep_streaming=True)` left open (the arm rests at its end); no-op when
        none is open."""
        if self._hold is None:
            return
        self._hold = None
        self._backend_servo_end()

    def request_stop(self, reason: str, protective: bool = False, detail: Any = None) -> None:
        """Ask, from another thread (the zone watch), for the arm to stop; returns at once.

        The motion call in progress stops the arm at its next state poll (within `poll_s` or `stream_period_s`):
        stopJ with `stop_decel`, or a protective stop when `protective`; it then raises `ZoneIntrusion` (latched:
        nothing further is sent until `resume()`, which clears the request). Without a motion in progress the next
        motion or gripper call raises it before sending anything. `detail` (a mapping) travels in the error."""
        self._stop_request = (str(reason), bool(protective), detail)

    def _honour_stop_request(self, stop: bool) -> None:
        request = self._stop_request
        if request is None:
            return
        reason, protective, detail = request
        sent = -1.0
        if stop and self._fault is None:
            sent = time.monotonic()
            try:
                if protective:
                    self._backend_protective_stop()
                else:
                    self._backend_stop(self.options.stop_decel)
            except (OSError, RuntimeError, DriverFault) as exc:
                log.warning("requested stop failed (%s); stopping the program another way", exc)
                self._halt_fallback()
            self.stop_sent_at = sent
        info = dict(detail) if isinstance(detail, dict) else {"detail": detail}
        info.update({"stop_sent_at": sent, "stop_kind": "protective" if protective else "stop"})
        raise self._latch(ZoneIntrusion(f"arm stopped on request: {reason}", info))

    def move_joints(self, waypoints: ArrayLike, speed: float, accel: float, timeout_s: float | None = None) -> ArmState:
        self._require_ready()
        self.end_stream()
        wps = np.asarray(waypoints, dtype=np.float64)
        if wps.ndim == 1:
            wps = wps[None]
        self.limits.check_joint_speed(speed, accel)
        self.limits.check_joints(wps, "waypoint")
        start = self.state()
        self._check_state(start, during="move start", stop=False)
        chain = np.vstack([start.q[None], wps])
        for i in range(len(wps)):
            self.limits.check_segment(chain[i], chain[i + 1], f"segment {i}")
        expected = sum(movej_duration(chain[i], chain[i + 1], speed, accel) for i in range(len(wps)))
        timeout = (
            timeout_s if timeout_s is not None else expected * self.options.move_factor + self.options.move_margin_s
        )
        self.commands_sent += 1
        self._planned_qd = float(speed)
        try:
            self._backend_move_path(wps, speed, accel)
            return self._monitor(wps[-1], timeout, "move_joints")
        except BaseException as exc:
            self._halt_on_exit(exc, "move_joints")
            raise
        finally:
            self._planned_qd = 0.0

    def move_linear(self, base_from_tcp: ArrayLike, speed: float, accel: float) -> ArmState:
        self._require_ready()
        self.end_stream()
        poses = np.asarray(base_from_tcp, dtype=np.float64)
        if poses.ndim == 2:
            poses = poses[None]
        self.limits.check_tool_speed(speed, accel)
        start = self.state()
        self._check_state(start, during="move start", stop=False)
        prev = start.base_from_tcp[:3, 3]
        length = 0.0
        for i, pose in enumerate(poses):
            self.limits.check_tcp_pose(pose, f"linear target {i}")
            seg = np.linspace(prev, pose[:3, 3], 16)  # the line itself stays in the box (it is convex: ends suffice)
            self.limits.check_tcp_positions(seg, f"linear segment {i}")
            length += float(np.linalg.norm(pose[:3, 3] - prev))
            prev = pose[:3, 3]
        timeout = (length / speed + speed / accel) * self.options.move_factor + self.options.move_margin_s
        self.commands_sent += 1
        self._planned_qd = float(np.max(self.limits.max_joint_speed))  # a line's joint speeds: up to the caps
        try:
            self._backend_move_linear(poses, speed, accel)
            return self._monitor_linear(poses[-1], timeout)
        except BaseException as exc:
            self._halt_on_exit(exc, "move_linear")
            raise
        finally:
            self._planned_qd = 0.0

    def follow_trajectory(self, times: ArrayLike, q: ArrayLike, keep_streaming: bool = False) -> ArmState:
        """Stream a time-parameterised joint trajectory with servoj at `stream_period_s`, then settle on its end.

        The trajectory is checked whole before the first sample is sent (limits, workspace, speed and acceleration
        caps, and its start must be the current joints). While streaming, the controller-side watchdog stops the
        program if this process stalls. A late tick slows the trajectory's clock instead of skipping ahead, so the servo
        target never jumps; a gap longer than `watchdog_s` stops the arm with a DriverTimeout.

        keep_streaming: once the arm has settled on the end, the stream stays open, holding it there (the gripper
        calls keep sending that target within the watchdog while they wait), and the next `follow_trajectory` goes on
        in the same stream: no servo stop and control-script restart between trajectories (about 0.12 s each on the
        loopback controller). Any other motion call, `stop`, `disconnect`, a fault or `end_stream` ends it; a stream
        left without a command for half of `watchdog_s` is restarted by the next trajectory (as without it).
        """
        self._require_ready()
        if self._hold is not None and time.monotonic() - self._hold_sent_at > 0.5 * self.options.watchdog_s:
            # nothing was sent for half the stream watchdog (the caller was busy): restart the stream rather than
            # race the controller's watchdog
            log.info("open stream idle %.3f s: restarted", time.monotonic() - self._hold_sent_at)
            self.end_stream()
        held = self._hold is not None
        try:
            t = np.asarray(times, dtype=np.float64).reshape(-1)
            qs = np.asarray(q, dtype=np.float64).reshape(-1, 6)
            self.limits.check_trajectory(t, qs)
            start = self.state()
            self._check_state(start, during="stream start", stop=False)
            gap = float(np.max(np.abs(qs[0] - start.q)))
            if gap > 0.01:
                raise SafetyViolation(
                    f"trajectory starts {gap:.4f} rad away from the current joints (> 0.01 rad); move there first",
                    detail={"start": qs[0], "current": start.q},
                )
            period = self.options.stream_period_s
            grid, samples = stream_samples(t, qs, period)
            # What is streamed is checked too: the commands, at the times they are sent, within the same caps.
            self.limits.check_trajectory(grid, samples, "streamed commands")
        except BaseException:
            self.end_stream()  # nothing of this trajectory was sent: an open stream ends at rest where it held
            raise
        self.commands_sent += 1
        self._hold = None
        if len(samples) > 1:
            self._planned_qd = float(np.max(np.abs(np.diff(samples, axis=0)))) / period
        if not held:
            self._backend_servo_begin()
        t0 = time.monotonic()
        slowed_s = 0.0
        settled = False
        try:
            for k, target in enumerate(samples):
                deadline = t0 + k * period
                now = time.monotonic()
                lag = now - deadline
                if lag > self.options.watchdog_s:
                    self._backend_stop(self.options.stop_decel)
                    raise self._latch(
                        DriverTimeout(
                            f"stream stalled {lag:.3f} s at sample {k} (> the {self.options.watchdog_s} s watchdog); "
                            "arm stopped"
                        )
                    )
                if lag > period:
                    # Late: run the trajectory slower rather than jump ahead; targets stay one period apart.
                    t0 += lag
                    slowed_s += lag
                elif lag < 0:
                    time.sleep(-lag)
                st = self._backend_state()
                self._check_state(st, during=f"stream sample {k}", stop=True)
                self._backend_servo(target, period)
            if slowed_s > 0:
                log.info("trajectory stream ran %.3f s slower than planned (late ticks)", slowed_s)
            self._settle_servo(samples[-1])
            settled = True
        except BaseException as exc:
            self._halt_on_exit(exc, "follow_trajectory")
            raise
        finally:
            self._planned_qd = 0.0  # settled on the end, or stopped
            if not (settled and keep_streaming):
                self._backend_servo_end()
        if keep_streaming:
            self._hold = np.array(samples[-1], dtype=np.float64)
            self._hold_sent_at = time.monotonic()
            return self._backend_state()  # at rest on the end (the settle checked the state it read)
        try:
            return self._monitor(
                qs[-1], self.options.move_margin_s, "follow_trajectory", tol=10 * self.options.arrive_tol_rad
            )
        except BaseException as exc:
            self._halt_on_exit(exc, "follow_trajectory")
            raise

    def _settle_servo(self, target: FloatArray) -> None:
        deadline = time.monotonic() + 2.0
        while time.monotonic() < deadline:
            st = self._backend_state()
            self._check_state(st, during="stream settle", stop=True)
            if float(np.max(np.abs(st.q - target))) < 0.25 * self.options.arrive_tol_rad:
                return
            self._backend_servo(target, self.options.stream_period_s)
            time.sleep(self.options.stream_period_s)

    # ------------------------------------------------------------------ gripper
    def gripper_close(self) -> None:
        self._require_ready()
        self._open_settled = False
        g = self.gripper
        if g.open_output is not None:
            self._backend_set_output(g.open_output, False, g.tool)
        self._backend_set_output(g.close_output, True, g.tool)
        self._wait_io(g.settle_s)

    def gripper_open(self) -> None:
        """Switch the outputs to open and wait `settle_s`. When the last gripper command was an open that settled
        and the controller's outputs still read open, no output changes and there is nothing to wait for: returns at
        once (the open before each plan, right after the last plan's place opened the gripper)."""
        self._require_ready()
        g = self.gripper
        if self._open_settled and self._outputs_read_open(self.state().digital_out):
            return
        self._open_settled = False
        self._backend_set_output(g.close_output, False, g.tool)
        if g.open_output is not None:
            self._backend_set_output(g.open_output, True, g.tool)
        self._wait_io(g.settle_s)
        self._open_settled = True

    def _outputs_read_open(self, bits: int) -> bool:
        g = self.gripper
        shift = 16 if g.tool else 0
        closed = bool(bits >> (g.close_output + shift) & 1)
        return not closed and (g.open_output is None or bool(bits >> (g.open_output + shift) & 1))

    def grip_detected(self) -> bool:
        """True when the grip-detect input is high; DriverFault if the gripper has no such input."""
        g = self.gripper
        if g.grip_detect_input is None:
            raise DriverFault("this gripper has no grip-detect input configured (GripperIO.grip_detect_input)")
        return bool(self.state().digital_in >> g.grip_detect_input & 1)

    def _wait_io(self, settle_s: float) -> None:
        """Wait `settle_s` watching the state; an open stream (`keep_streaming`) gets its hold target every stream
        period meanwhile (the controller's stream watchdog)."""
        end = time.monotonic() + settle_s
        try:
            while time.monotonic() < end:
                self._check_state(self.state(), during="gripper", stop=True)
                if self._hold is not None:
                    self._backend_servo(self._hold, self.options.stream_period_s)
                    self._hold_sent_at = time.monotonic()
                    time.sleep(min(self.options.stream_period_s, max(0.0, end - time.monotonic())))
                else:
                    time.sleep(min(0.02, max(0.0, end - time.monotonic())))
        except BaseException:
            self.end_stream()
            raise

    # ------------------------------------------------------------------ monitoring
    def _require_ready(self) -> None:
        if self._fault is None and self._stop_request is not None:
            self._honour_stop_request(stop=False)
        if self._fault is not None:
            raise DriverFault(
                f"driver halted by {type(self._fault).__name__}: {self._fault}; nothing was sent. "
                "Fix the cause and call resume()"
            )

    def _latch(self, fault: DriverFault) -> DriverFault:
        self._fault = fault
        self._open_settled = False
        log.info("driver fault latched: %s", fault)
        if self._hold is not None:  # the stream was open: the stop that came with the fault ended its motion
            self._hold = None
            try:
                self._backend_servo_end()
            except (OSError, RuntimeError, DriverFault) as exc:
                log.warning("ending the open stream after %s failed: %s", type(fault).__name__, exc)
        return fault

    def _check_state(self, st: ArmState, during: str, stop: bool) -> None:
        """Raise (and latch) the typed fault the state shows; stop the arm first when `stop`. A pending
        `request_stop` is honoured first."""
        if self._stop_request is not None and self._fault is None:
            self._honour_stop_request(stop)
        self._peak_qd = float(np.max(np.abs(st.qd))) if st.qd.shape == (6,) else self._peak_qd
        fault: DriverFault | None = None
        if st.emergency_stopped:
            fault = EmergencyStop(f"emergency stop during {during} (safety_mode {st.safety_mode})")
        elif st.protective_stopped:
            fault = ProtectiveStop(f"protective stop during {during} (safety_mode {st.safety_mode})")
        elif not self._backend_connected():
            fault = ConnectionLost(
                f"the link to the controller went down during {during}; not retrying: reconnect with resume()"
            )
        elif time.monotonic() - st.received_at > self.options.stale_state_s:
            fault = ConnectionLost(
                f"no fresh robot state for {time.monotonic() - st.received_at:.2f} s during {during} (controller "
                "stalled or link lost); not retrying: reconnect with resume()"
            )
        elif st.robot_mode != ROBOT_MODE_RUNNING:
            fault = DriverFault(f"robot not running (robot_mode {st.robot_mode}) during {during}: power on first")
        elif not st.program_running:
            fault = DriverFault(f"control program not running on the controller during {during}")
        if fault is not None:
            if stop:
                try:
                    if isinstance(fault, ConnectionLost):
                        note = self._backend_link_lost()
                        if note:
                            fault = ConnectionLost(f"{fault}; {note}")
                    elif not isinstance(fault, EmergencyStop | ProtectiveStop):
                        self._backend_stop(self.options.stop_decel)
                except (OSError, RuntimeError, DriverFault) as exc:
                    log.warning("stop after %s failed: %s", type(fault).__name__, exc)
            raise self._latch(fault)

    def _monitor(self, q_goal: FloatArray, timeout_s: float, what: str, tol: float | None = None) -> ArmState:
        """Poll state until the arm rests within `tol` (rad; default arrive_tol_rad) of q_goal; faults and timeouts
        stop the arm and raise."""
        tol = self.options.arrive_tol_rad if tol is None else tol
        start = time.monotonic()
        while True:
            st = self._backend_state()
            self._check_state(st, during=what, stop=True)
            at_goal = float(np.max(np.abs(st.q - q_goal))) <= max(tol, 1e-5)
            if at_goal and not self._backend_busy():
                return st
            if not self._backend_busy() and float(np.max(np.abs(st.qd))) < 1e-6 and not at_goal:
                # the controller ended the motion elsewhere (e.g. a stop from another client)
                time.sleep(self.options.poll_s)
                st2 = self._backend_state()
                self._check_state(st2, during=what, stop=True)
                if not self._backend_busy() and float(np.max(np.abs(st2.q - q_goal))) > tol:
                    raise self._latch(
                        DriverFault(
                            f"{what} ended {float(np.max(np.abs(st2.q - q_goal))):.4f} rad short of its goal "
                            "without a fault from the controller"
                        )
                    )
            if time.monotonic() - start > timeout_s:
                self._backend_stop(self.options.stop_decel)
                raise self._latch(DriverTimeout(f"{what} did not finish within {timeout_s:.1f} s; arm stopped"))
            time.sleep(self.options.poll_s)

    def _monitor_linear(self, goal: FloatArray, timeout_s: float) -> ArmState:
        start = time.monotonic()
        while True:
            st = self._backend_state()
            self._check_state(st, during="move_linear", stop=True)
            if not self._backend_busy():
                err = float(np.linalg.norm(st.base_from_tcp[:3, 3] - goal[:3, 3]))
                if err > 1e-3:
                    raise self._latch(DriverFault(f"move_linear ended {err * 1000:.2f} mm from its goal"))
                return st
            if time.monotonic() - start > timeout_s:
                self._backend_stop(self.options.stop_decel)
                raise self._latch(DriverTimeout(f"move_linear did not finish within {timeout_s:.1f} s; arm stopped"))
            time.sleep(self.options.poll_s)
