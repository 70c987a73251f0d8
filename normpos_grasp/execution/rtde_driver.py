"""`RtdeDriver`: the arm driver on ur_rtde (RTDEControlInterface, RTDEReceiveInterface, RTDEIOInterface).

Moves are sent asynchronously (movej paths through `moveJ(path, asynchronous=True)`, linear paths through
`moveL(path, asynchronous=True)`) and monitored here at `DriverOptions.poll_s`, so every move has a timeout and
reacts to protective stops, e-stops and stale state within a poll period. Streaming uses `servoJ` with the
controller-side RTDE watchdog armed; the control script is re-uploaded after a stream to disarm it.

Every blocking call into the control and IO interfaces runs on one call thread with a deadline (`_bounded`): ur_rtde
1.6.5 waits without one for its control script to run in moveJ(path), moveL(path) and reuploadScript, and up to
300 s for a command's answer. A call past its deadline stops the program over a fresh dashboard connection, cuts
the stuck client off (`_set_aside_stuck`) and latches `DriverTimeout`; `resume()` connects a fresh client. servoJ
is not bounded here: it only waits for the script to be ready, and while it waits no command reaches the
controller, whose RTDE watchdog (armed for every stream) then stops the program.
"""

from __future__ import annotations

import ctypes
import logging
import queue
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, TypeVar

import numpy as np

from normpos_grasp.errors import ConnectionLost, ControllerMismatch, DriverFault, DriverTimeout, MissingDependency
from normpos_grasp.geometry.transforms import pose_from_ur, pose_to_ur
from normpos_grasp.typing import FloatArray

from .driver import ArmState, DriverOptions, GripperIO, GuardedDriver
from .safety import SafetyLimits

log = logging.getLogger(__name__)

DASHBOARD_PORT = 29999
_BUSY_GRACE_S = 0.3  # s: a just-started async move counts as busy until the joints move
_T = TypeVar("_T")


def _import_rtde() -> tuple[Any, Any, Any]:
    try:
        import rtde_control
        import rtde_io
        import rtde_receive
    except ImportError as exc:  # pragma: no cover - ur-rtde is a core dependency
        raise MissingDependency("ur-rtde==1.6.5", "core", "RtdeDriver") from exc
    return rtde_control, rtde_receive, rtde_io


@dataclass(frozen=True)
class ControllerIdentity:
    """What a controller's dashboard server says it is. model: `get robot model` ("UR5", "UR10", "UR20", ...);
    serial: `get serial number`; software: `PolyscopeVersion` (e-Series and UR20/UR30 run software 5.x)."""

    model: str
    serial: str
    software: str

    @property
    def software_major(self) -> int:
        for token in self.software.replace("URSoftware", " ").split():
            head = token.split(".", 1)[0]
            if head.isdigit():
                return int(head)
        return -1


def dashboard_query(host: str, lines: tuple[str, ...], timeout_s: float = 2.0) -> list[str]:
    """Send dashboard lines over one connection (port 29999) and return the replies; ConnectionLost on failure."""
    try:
        with socket.create_connection((host, DASHBOARD_PORT), timeout=timeout_s) as sock:
            sock.settimeout(timeout_s)
            f = sock.makefile("rwb", buffering=0)
            f.readline()  # welcome line
            replies = []
            for line in lines:
                f.write(line.encode() + b"\n")
                replies.append(f.readline().decode(errors="replace").strip())
            return replies
    except OSError as exc:
        raise ConnectionLost(f"dashboard server of {host} did not answer ({exc}); is the controller on?") from exc


def dashboard_stop(host: str, timeout_s: float = 1.0) -> str | None:
    """Stop the program over a fresh dashboard connection (independent of RTDE). None when the controller answered,
    else a note saying the arm may still be moving."""
    try:
        with socket.create_connection((host, DASHBOARD_PORT), timeout=timeout_s) as sock:
            sock.settimeout(timeout_s)
            f = sock.makefile("rwb", buffering=0)
            f.readline()
            f.write(b"stop\n")
            log.info("dashboard stop -> %s", f.readline().decode(errors="replace").strip())
            return None
    except OSError as exc:
        return f"the dashboard is unreachable too ({exc}): the arm may still be moving"


class _CallThread:
    """One long-lived daemon thread that runs a driver's ur_rtde calls in order (a queue hand-off costs ~0.2 ms on
    a loaded 2-core machine, starting a thread per call ~4 ms)."""

    def __init__(self) -> None:
        self._queue: queue.SimpleQueue[Any] = queue.SimpleQueue()
        threading.Thread(target=self._serve, name="ur_rtde calls", daemon=True).start()

    def submit(self, call: Callable[..., Any], args: tuple[Any, ...], out: list[Any], done: threading.Event) -> None:
        self._queue.put((call, args, out, done))

    def close(self) -> None:
        self._queue.put(None)

    def _serve(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                return
            call, args, out, done = item
            try:
                out.append((True, call(*args)))
            except BaseException as exc:  # handed to the waiting caller
                out.append((False, exc))
            finally:
                done.set()


def _disconnect_all(clients: list[Any]) -> None:
    for client in clients:
        try:
            client.disconnect()
        except RuntimeError as exc:
            log.warning("disconnecting a client set aside: %s", exc)


def read_controller_identity(host: str, timeout_s: float = 2.0) -> ControllerIdentity:
    model, serial, software = dashboard_query(
        host, ("get robot model", "get serial number", "PolyscopeVersion"), timeout_s
    )
    return ControllerIdentity(model, serial, software)


def check_controller(host: str, model: str, serial: str | None = None, timeout_s: float = 2.0) -> ControllerIdentity:
    """Refuse (ControllerMismatch) a controller that is not a `model` (ur_params name, e.g. "ur5e") with `serial`.

    The dashboard names the family ("UR5" for a UR5 and a UR5e); an e-Series model also needs software 5.x."""
    ident = read_controller_identity(host, timeout_s)
    want = model.lower()
    family = "UR" + want.upper().removeprefix("UR").removesuffix("E")
    if ident.model.strip().upper() != family:
        raise ControllerMismatch(
            f"the controller at {host} is a {ident.model!r} (dashboard `get robot model`), the plan/cell is for "
            f"{want}; nothing was sent"
        )
    if want.endswith("e") and 0 <= ident.software_major < 5:
        raise ControllerMismatch(
            f"the controller at {host} runs {ident.software!r}, a CB-series arm, the plan/cell is for the e-Series "
            f"{want}; nothing was sent"
        )
    if serial is not None and ident.serial.strip() != str(serial).strip():
        raise ControllerMismatch(
            f"the controller at {host} has serial number {ident.serial!r}, the cell names {serial!r}; nothing was sent"
        )
    return ident


class RtdeDriver(GuardedDriver):
    """Arm driver for a UR controller (or the loopback emulator) at `host`.

    limits: SafetyLimits checked before sending. gripper: digital-output wiring. options: timeouts.
    servo_lookahead_s, servo_gain: servoJ parameters for streaming. verify_controller: before connecting, read the
    robot model (and `expected_serial` where given) from the dashboard and refuse a mismatch (ControllerMismatch).
    call_timeout_s: the deadline of a control call that hands a command over (async move, stop, I/O), s.
    script_timeout_s: the deadline of a call that (re)starts the control script (path moves, the re-arm after a
    stream), s; 5 s is ur_rtde's own limit for its script to start (RTDEControlInterface::waitForProgramRunning).

    The ur_rtde client runs in this process: its aborts end the process. `SupervisedRtdeDriver` runs it in a child.
    """

    def __init__(
        self,
        host: str,
        limits: SafetyLimits,
        gripper: GripperIO | None = None,
        options: DriverOptions | None = None,
        servo_lookahead_s: float = 0.1,
        servo_gain: float = 300.0,
        verify_controller: bool = True,
        expected_serial: str | None = None,
        call_timeout_s: float = 2.0,
        script_timeout_s: float = 5.0,
    ) -> None:
        super().__init__(limits, gripper, options)
        self.call_timeout_s = call_timeout_s
        self.script_timeout_s = script_timeout_s
        self.host = host
        self.verify_controller = verify_controller
        self.expected_serial = expected_serial
        self.servo_lookahead_s = servo_lookahead_s
        self.servo_gain = servo_gain
        self._c: Any = None
        self._r: Any = None
        self._io: Any = None
        self._last_ts = -1.0
        self._last_change = 0.0
        self._move_started = 0.0
        self._seen_running = False
        self._still_since = -1.0
        self._still_window = 0.02
        self._streaming = False
        self._link_lost = False
        self._abandoned: list[Any] = []  # control interfaces left after a link loss (see _backend_link_lost)
        self._calls: _CallThread | None = None  # runs the bounded calls, one at a time (made at connect)

    # ------------------------------------------------------------------ bounded calls
    def _bounded(self, what: str, timeout_s: float, call: Callable[..., _T], *args: Any) -> _T:
        """`call(*args)` (a ur_rtde method) on the driver's call thread, waited for at most `timeout_s` s.

        Calls run one at a time in order (a stop sent while an interrupted move call is still handing its command
        over goes after it). Past the deadline: `_set_aside_stuck` (the program is stopped over the dashboard) and a
        latched DriverTimeout."""
        if self._calls is None:
            raise ConnectionLost(f"not connected to {self.host}; call connect() or resume()")
        result: list[tuple[bool, Any]] = []
        done = threading.Event()
        self._calls.submit(call, args, result, done)
        if not done.wait(timeout_s):
            note = self._set_aside_stuck(what)
            raise self._latch(
                DriverTimeout(
                    f"ur_rtde's {what} did not return within {timeout_s:.1f} s; the program was stopped over the "
                    f"dashboard{'' if note is None else ' (' + note + ')'}; resume() connects a fresh client"
                )
            )
        ok, value = result[0]
        if not ok:
            raise value
        return value

    def _set_aside_stuck(self, what: str) -> str | None:
        """A control call did not return: stop the program over the dashboard, then cut the client off.

        The stuck call may still be waiting inside ur_rtde (for its script to run, for an answer). Disconnecting the
        client ends its receive thread (so it cannot reconnect on its own) and turns its sends into no-ops (ur_rtde
        writes only while connected), so whatever that call would send next never leaves. The client object is kept
        alive for good: the waiting thread still reads its state. `resume()` connects a fresh client."""
        self._calls = None  # its thread waits in the stuck call for good; a fresh one comes with the next connect
        note = dashboard_stop(self.host)
        clients = [c for c in (self._c, self._io) if c is not None]
        self._c = self._io = None
        for client in clients:
            ctypes.pythonapi.Py_IncRef(ctypes.py_object(client))  # never freed under the waiting thread
        cut = threading.Thread(target=_disconnect_all, args=(clients,), name="ur_rtde set aside", daemon=True)
        cut.start()
        cut.join(self.call_timeout_s)
        log.error("ur_rtde's %s did not return: program stopped over the dashboard, client cut off", what)
        return note

    # ------------------------------------------------------------------ backend
    def _release_abandoned(self) -> None:
        """Disconnect control interfaces set aside after a link loss (frees the controller's input registers)."""
        while self._abandoned:
            control = self._abandoned.pop()
            try:
                control.disconnect()
            except RuntimeError as exc:
                log.warning("disconnecting the control interface after the link loss: %s", exc)

    def _backend_connect(self) -> None:
        self._release_abandoned()
        if self.verify_controller:
            check_controller(self.host, self.limits.model, self.expected_serial)
        rtde_control, rtde_receive, rtde_io = _import_rtde()
        try:
            self._r = rtde_receive.RTDEReceiveInterface(self.host)
            self._c = rtde_control.RTDEControlInterface(self.host)
            self._io = rtde_io.RTDEIOInterface(self.host)
        except RuntimeError as exc:
            self._backend_disconnect()
            text = str(exc)
            if "already in use" in text:
                raise DriverFault(
                    f"controller {self.host} is already driven by another RTDE client (its input registers are in "
                    f"use): disconnect that client first. ur_rtde said: {text}"
                ) from exc
            raise ConnectionLost(f"cannot connect to the UR controller at {self.host}: {text}") from exc
        if self._calls is not None:
            self._calls.close()
        self._calls = _CallThread()
        self._last_ts = -1.0
        deadline = time.monotonic() + self.options.connect_timeout_s
        while time.monotonic() < deadline:
            self._backend_state()
            if self._last_ts >= 0.0 and time.monotonic() - self._last_change < self.options.stale_state_s:
                return
            time.sleep(0.01)
        raise ConnectionLost(
            f"connected to {self.host} but no robot state arrived within {self.options.connect_timeout_s} s"
        )

    def _backend_disconnect(self) -> None:
        self._release_abandoned()
        # Order matters with ur_rtde 1.6.5: the control interface first (disconnect() also ends its internal
        # reconnect loop after a dropped link); the IO interface aborts the process if disconnected on a dead
        # socket, so it is reconnected first when its link is gone.
        if self._c is not None:
            try:
                self._c.disconnect()
            except RuntimeError as exc:
                log.warning("disconnecting the control interface: %s", exc)
        if self._io is not None:
            try:
                if self._link_lost:
                    self._io.reconnect()
                self._io.disconnect()
            except RuntimeError as exc:
                log.warning("disconnecting the IO interface: %s", exc)
        if self._r is not None:
            try:
                self._r.disconnect()
            except RuntimeError as exc:
                log.warning("disconnecting the receive interface: %s", exc)
        self._c = self._io = self._r = None
        self._link_lost = False
        if self._calls is not None:
            self._calls.close()  # after any call still queued
            self._calls = None

    def _backend_connected(self) -> bool:
        return bool(self._r is not None and self._c is not None and not self._link_lost and self._r.isConnected())

    def _backend_link_lost(self) -> str | None:
        """Stop the program over a fresh dashboard connection (independent of RTDE); never re-send motion."""
        self._link_lost = True
        note = dashboard_stop(self.host)
        # ur_rtde 1.6.5's control interface reconnects on its own after a dropped link, re-uploading its script in a
        # loop, and calling into it right after a hard drop (disconnect() included) can crash the process. Set it
        # aside so this fault reaches the caller first; resume() or disconnect() ends it (_release_abandoned). The
        # client's own reconnect thread may still crash the process: see docs/execution.md.
        if self._c is not None:
            self._abandoned.append(self._c)
            self._c = None
        return note

    def _backend_state(self) -> ArmState:
        if self._r is None:
            raise ConnectionLost(f"not connected to {self.host}; call connect() or resume()")
        r = self._r
        now = time.monotonic()
        ts = float(r.getTimestamp())
        if ts != self._last_ts:
            self._last_ts = ts
            self._last_change = now
        q = np.array(r.getActualQ(), dtype=np.float64)
        if q.shape != (6,):
            raise ConnectionLost(f"receive interface returned joints of shape {q.shape}; stream not ready")
        status = int(r.getRobotStatus())
        return ArmState(
            q=q,
            qd=np.array(r.getActualQd(), dtype=np.float64),
            base_from_tcp=pose_from_ur(r.getActualTCPPose()),
            timestamp=ts,
            robot_mode=int(r.getRobotMode()),
            safety_mode=int(r.getSafetyMode()),
            safety_status_bits=int(r.getSafetyStatusBits()),
            runtime_state=int(r.getRuntimeState()),
            program_running=bool(status & 2),
            digital_out=int(r.getActualDigitalOutputBits()),
            digital_in=int(r.getActualDigitalInputBits()),
            analog_in=(float(r.getStandardAnalogInput0()), float(r.getStandardAnalogInput1())),
            received_at=self._last_change,
        )

    def _sent(self, ok: bool, what: str) -> None:
        if not ok:
            st = self._backend_state()
            self._check_state(st, during=what, stop=True)
            raise self._latch(DriverFault(f"controller refused {what} (control script not ready or not running)"))

    def _backend_move_path(self, waypoints: FloatArray, speed: float, accel: float) -> None:
        self._move_started, self._seen_running, self._still_since = time.monotonic(), False, -1.0
        self._still_window = 0.02 if len(waypoints) == 1 else 0.15
        if len(waypoints) == 1:
            self._sent(
                self._bounded("moveJ", self.call_timeout_s, self._c.moveJ, waypoints[0].tolist(), speed, accel, True),
                "moveJ",
            )
        else:
            path = [list(map(float, w)) + [speed, accel, 0.0] for w in waypoints]
            self._sent(self._bounded("moveJ path", self.script_timeout_s, self._c.moveJ, path, True), "moveJ path")

    def _backend_move_linear(self, poses: FloatArray, speed: float, accel: float) -> None:
        self._move_started, self._seen_running, self._still_since = time.monotonic(), False, -1.0
        self._still_window = 0.02 if len(poses) == 1 else 0.15
        if len(poses) == 1:
            pose = pose_to_ur(poses[0]).tolist()
            self._sent(self._bounded("moveL", self.call_timeout_s, self._c.moveL, pose, speed, accel, True), "moveL")
        else:
            path = [pose_to_ur(p).tolist() + [speed, accel, 0.0] for p in poses]
            self._sent(self._bounded("moveL path", self.script_timeout_s, self._c.moveL, path, True), "moveL path")

    def _backend_busy(self) -> bool:
        # Judged from the receive interface only (joint speeds): calls into the control interface block, holding
        # the GIL, while ur_rtde 1.6.5 reconnects it after a dropped link, and that reconnect loop must be ended
        # quickly (see _backend_link_lost).
        if self._r is None or not self._r.isConnected():
            return False
        now = time.monotonic()
        if float(np.max(np.abs(np.asarray(self._r.getActualQd())))) > 1e-4:
            self._seen_running, self._still_since = True, -1.0
            return True
        if not self._seen_running:
            return now - self._move_started < _BUSY_GRACE_S
        if self._still_since < 0.0:
            self._still_since = now
        return now - self._still_since < self._still_window  # a path stops for an instant at each waypoint

    def _backend_servo_begin(self) -> None:
        self._sent(
            self._bounded("setWatchdog", self.call_timeout_s, self._c.setWatchdog, 1.0 / self.options.watchdog_s),
            "setWatchdog",
        )
        self._streaming = True

    def _backend_servo(self, q: FloatArray, period_s: float) -> None:
        self._c.servoJ(q.tolist(), 0.0, 0.0, period_s, self.servo_lookahead_s, self.servo_gain)

    def _backend_servo_end(self) -> None:
        if not self._streaming:
            return
        self._streaming = False
        if self._fault is not None or self._c is None:
            return
        self._bounded("servoStop", self.call_timeout_s, self._c.servoStop, self.options.stop_decel)
        self._rearm_program()

    def _rearm_program(self) -> None:
        """Re-upload the control script (disarms the stream watchdog) and wait until it runs."""
        self._bounded("reuploadScript", self.script_timeout_s, self._c.reuploadScript)
        deadline = time.monotonic() + self.options.connect_timeout_s
        while not (self._c.isProgramRunning() and self._backend_state().program_running):
            if time.monotonic() > deadline:
                raise self._latch(DriverFault("control script did not restart within the connect timeout"))
            time.sleep(0.005)

    def _backend_stop(self, decel: float) -> None:
        if self._c is None or self._link_lost:
            return
        if self._streaming:
            self._bounded("servoStop", self.call_timeout_s, self._c.servoStop, decel)
        # synchronous: returns when the arm rests (3.5 rad at most to shed)
        self._bounded("stopJ", self.call_timeout_s + 3.5 / max(decel, 0.5), self._c.stopJ, decel, False)

    def _backend_protective_stop(self) -> None:
        if self._c is None or self._link_lost:
            return
        # the protective stop ends the control script, so the call may report failure although the stop happened;
        # the receive interface's safety mode is the judge (GuardedDriver checks it)
        if not self._bounded("triggerProtectiveStop", self.call_timeout_s, self._c.triggerProtectiveStop):
            log.info("triggerProtectiveStop() returned false (the control script ended with the stop)")

    def _backend_set_output(self, index: int, level: bool, tool: bool) -> None:
        if self._io is None:
            raise ConnectionLost("not connected")
        setter = self._io.setToolDigitalOut if tool else self._io.setStandardDigitalOut
        ok = self._bounded("set digital output", self.call_timeout_s, setter, index, level)
        if not ok:
            raise self._latch(DriverFault(f"setting digital output {index} failed"))
        deadline = time.monotonic() + 1.0
        bit = index + (16 if tool else 0)
        while time.monotonic() < deadline:
            if bool(int(self._r.getActualDigitalOutputBits()) >> bit & 1) == level:
                return
            time.sleep(0.004)
        raise self._latch(DriverFault(f"digital output {bit} did not change to {level} within 1 s"))

    def _backend_reset_faults(self) -> None:
        if self._c is None:
            raise ConnectionLost("not connected")
        if not self._c.isProgramRunning():
            self._rearm_program()
