"""`SupervisedRtdeDriver`: the ur_rtde client in a supervised child process, the guarded logic in the caller.

ur_rtde 1.6.5 can end its process on link failures (SIGABRT or a segmentation fault from its reconnect thread after
a dropped link or a killed controller) and blocks inside calls while a controller stalls. Here an `RtdeDriver` lives
in a child process (multiprocessing, spawn) that serves its `_backend_*` primitives over a pipe; checks, monitoring
and the fault latch run in the caller (`GuardedDriver`). Every call has a deadline. A child that dies (abort, crash,
killed) or does not answer in time becomes a typed fault in the caller within that deadline (`ConnectionLost`,
`DriverTimeout`), latched: the caller stops the program over a fresh dashboard connection of its own, kills the
child, and sends nothing further; `resume()` starts a fresh child and reconnects. The child (`rtde_child`, started
with `python -m` in a session of its own, so no main-module guard is needed) ignores SIGINT/SIGTERM (the caller
handles them and stops the arm through it) and, if the caller dies, stops the arm and exits.
"""

from __future__ import annotations

import logging
import os
import socket
import subprocess
import sys
import threading
import time
from dataclasses import replace
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

from normpos_grasp import errors as E
from normpos_grasp.errors import ConnectionLost, DriverFault, DriverTimeout
from normpos_grasp.interrupts import uninterrupted
from normpos_grasp.typing import FloatArray

from .driver import ArmState, DriverOptions, GripperIO, GuardedDriver
from .rtde_driver import DASHBOARD_PORT, check_controller, dashboard_stop
from .safety import SafetyLimits

log = logging.getLogger(__name__)

CHILD_LOG_ENV = "NORMPOS_GRASP_RTDE_LOG"  # file for the child's log and ur_rtde's console output (default: none)
_CALLS = frozenset(
    {
        "connect",
        "disconnect",
        "state",
        "busy",
        "move_path",
        "move_linear",
        "servo",
        "servo_begin",
        "servo_end",
        "stop",
        "protective_stop",
        "set_output",
        "reset_faults",
    }
)


def _rebuild(type_name: str, message: str) -> Exception:
    """The caller-side exception for a child's failure (ur_rtde's RuntimeError: a lost connection)."""
    cls = getattr(E, type_name, None)
    if isinstance(cls, type) and issubclass(cls, E.NormposError):
        try:
            return cls(message)
        except TypeError:
            return DriverFault(f"{type_name}: {message}")
    if type_name in ("RuntimeError", "OSError", "BrokenPipeError", "ConnectionResetError"):
        return ConnectionLost(f"ur_rtde: {message}")
    return DriverFault(f"the ur_rtde client failed: {type_name}: {message}")


class SupervisedRtdeDriver(GuardedDriver):
    """Arm driver for a UR controller at `host` with the ur_rtde client in a supervised child process.

    Same contract and options as `RtdeDriver`. call_timeout_s: deadline of a quick call (state, servo, move
    start), s; longer calls (connect, script re-upload, stops) get deadlines from `options`. verify_controller /
    expected_serial: check the dashboard's robot model (and serial) against `limits.model` before connecting.
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
        call_timeout_s: float = 1.0,
    ) -> None:
        super().__init__(limits, gripper, options)
        self.host = host
        self.servo = (servo_lookahead_s, servo_gain)
        self.verify_controller = verify_controller
        self.expected_serial = expected_serial
        self.call_timeout_s = call_timeout_s
        self._proc: Any = None
        self._conn: Connection | None = None
        self._seq = 0
        self._child_connected = False
        self._streaming = False
        self._lock = threading.RLock()
        self._dash: Any = None  # a dashboard connection kept open for stops: (socket, file)

    @property
    def child_pid(self) -> int | None:
        return None if self._proc is None else int(self._proc.pid)

    # ------------------------------------------------------------------ the child process
    def _spawn(self) -> None:
        ours, theirs = socket.socketpair()
        target = os.environ.get(CHILD_LOG_ENV) or os.devnull
        try:
            with open(target, "ab") as out:
                proc = subprocess.Popen(
                    [sys.executable, "-m", "normpos_grasp.execution.rtde_child", str(theirs.fileno())],
                    pass_fds=(theirs.fileno(),),
                    stdin=subprocess.DEVNULL,
                    stdout=out,
                    stderr=out,
                    start_new_session=True,  # terminal and process-group signals go to the caller (it stops the arm)
                )
        finally:
            theirs.close()
        conn = Connection(ours.detach())
        conn.send((self.host, self.limits, self.gripper, self.options, self.servo))
        self._proc, self._conn, self._child_connected = proc, conn, False

    def _kill_child(self) -> None:
        proc, conn = self._proc, self._conn
        self._proc = self._conn = None
        self._child_connected = False
        if conn is not None:
            conn.close()
        if proc is not None:
            if proc.poll() is None:
                proc.kill()
            try:
                proc.wait(timeout=2.0)
            except subprocess.TimeoutExpired:
                log.error("the ur_rtde client process %d did not end after SIGKILL", proc.pid)

    def _open_dashboard(self) -> None:
        """Keep a dashboard connection for stops: a fresh one costs a connect, an accept and the welcome line on
        the controller before the stop gets there (tens of ms on a loaded machine). Failing here is not fatal:
        the stop then opens a fresh connection."""
        self._close_dashboard()
        try:
            sock = socket.create_connection((self.host, DASHBOARD_PORT), timeout=1.0)
            f = sock.makefile("rwb", buffering=0)
            f.readline()
            self._dash = (sock, f)
        except OSError as exc:
            log.warning("no standing dashboard connection to %s (%s); stops will open one", self.host, exc)

    def _close_dashboard(self) -> None:
        dash, self._dash = self._dash, None
        if dash is not None:
            for part in (dash[1], dash[0]):
                try:
                    part.close()
                except OSError:
                    log.debug("closing the dashboard connection failed")

    def _stop_program(self) -> str | None:
        """Stop the program over the standing dashboard connection, else a fresh one (`dashboard_stop`)."""
        dash = self._dash
        if dash is not None:
            try:
                dash[1].write(b"stop\n")
                reply = dash[1].readline().decode(errors="replace").strip()
                if reply:
                    log.info("dashboard stop -> %s", reply)
                    return None
            except OSError as exc:
                log.warning("standing dashboard connection failed (%s); opening a fresh one", exc)
            self._close_dashboard()
        return dashboard_stop(self.host)

    def _child_lost(self, fault: DriverFault) -> DriverFault:
        """The child died or stalled: stop the program from here, kill the child, latch `fault`."""
        note = self._stop_program()
        self._kill_child()
        if note:
            fault = type(fault)(f"{fault}; {note}")
        return self._latch(fault)

    def _call(self, name: str, *args: Any, timeout_s: float | None = None) -> Any:
        with self._lock:  # a live view may read state from another thread
            return self._call_locked(name, *args, timeout_s=timeout_s)

    def _call_locked(self, name: str, *args: Any, timeout_s: float | None = None) -> Any:
        assert name in _CALLS or name == "exit"
        conn = self._conn
        if conn is None:
            raise ConnectionLost(
                f"not connected to {self.host} (no ur_rtde client process); call connect() or resume()"
            )
        self._seq += 1
        seq = self._seq
        limit = self.call_timeout_s if timeout_s is None else timeout_s
        try:
            with uninterrupted():  # a signal mid-message would leave the pipe out of step: raised after it
                conn.send((seq, name, args))
        except (OSError, EOFError, ValueError) as exc:
            raise self._child_lost(self._gone_fault(f"sending {name}: {exc}")) from None
        deadline = time.monotonic() + limit
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0.0:
                raise self._child_lost(
                    DriverTimeout(
                        f"the ur_rtde client did not answer {name} within {limit:.1f} s (controller stalled?); "
                        "program stopped over the dashboard, client ended: resume() reconnects"
                    )
                ) from None
            try:
                if not conn.poll(remaining):  # a signal may interrupt the wait (the caller then stops the arm)
                    continue
                with uninterrupted():
                    reply = conn.recv()
            except (EOFError, OSError) as exc:
                raise self._child_lost(self._gone_fault(f"{name}: {type(exc).__name__}")) from None
            if reply[0] != seq:
                continue  # the answer to a call an interrupt abandoned
            if reply[1] == "ok":
                return reply[2]
            failure = _rebuild(reply[2], reply[3])
            if isinstance(failure, ConnectionLost):
                raise self._child_lost(failure)
            if isinstance(failure, DriverFault):
                raise self._latch(failure)
            raise failure

    def _gone_fault(self, what: str) -> ConnectionLost:
        code = None
        if self._proc is not None:
            try:
                code = self._proc.wait(timeout=0.2)
            except subprocess.TimeoutExpired:
                code = None
        how = "" if code is None else (f" (killed by signal {-code})" if code < 0 else f" (exit code {code})")
        return ConnectionLost(
            f"the ur_rtde client process ended{how} during {what}: link to {self.host} lost; program stopped over "
            "the dashboard, nothing re-sent: resume() reconnects"
        )

    # ------------------------------------------------------------------ backend
    def _backend_connect(self) -> None:
        if self.verify_controller:
            check_controller(self.host, self.limits.model, self.expected_serial)
        self._kill_child()
        self._open_dashboard()
        self._spawn()
        try:
            self._call("connect", timeout_s=3 * self.options.connect_timeout_s + 10.0)
        except DriverFault:
            self._kill_child()
            self._fault = None  # a failed connect is reported, not latched: connect() may simply be retried
            raise
        self._child_connected = True

    def _backend_disconnect(self) -> None:
        if self._conn is not None and self._proc is not None and self._proc.poll() is None:
            try:
                self._call("disconnect", timeout_s=5.0)
                self._call("exit", timeout_s=2.0)
            except DriverFault as exc:
                log.warning("disconnecting the ur_rtde client: %s", exc)
        self._kill_child()
        self._close_dashboard()
        self._streaming = False

    def _backend_connected(self) -> bool:
        return bool(
            self._conn is not None and self._child_connected and self._proc is not None and self._proc.poll() is None
        )

    def _backend_state(self) -> ArmState:
        st, connected, age_s = self._call("state")
        self._child_connected = bool(connected)
        assert isinstance(st, ArmState)
        # The stall watchdog (stale_state_s) judges the stream's age where it is read, in the child: the age is
        # carried over and re-based on this process's clock, so time this process spent descheduled between the
        # reply and the check does not count as a stalled controller.
        return replace(st, received_at=time.monotonic() - float(age_s))

    def _backend_link_lost(self) -> str | None:
        note = self._stop_program()
        self._kill_child()
        return note

    def _backend_busy(self) -> bool:
        return bool(self._call("busy"))

    def _backend_move_path(self, waypoints: FloatArray, speed: float, accel: float) -> None:
        self._call("move_path", waypoints, speed, accel, timeout_s=self.call_timeout_s + 1.0)

    def _backend_move_linear(self, poses: FloatArray, speed: float, accel: float) -> None:
        self._call("move_linear", poses, speed, accel, timeout_s=self.call_timeout_s + 1.0)

    def _backend_servo_begin(self) -> None:
        self._call("servo_begin", timeout_s=self.call_timeout_s + 1.0)
        self._streaming = True

    def _backend_servo(self, q: FloatArray, period_s: float) -> None:
        self._call("servo", q, period_s)

    def _backend_servo_end(self) -> None:
        if not self._streaming:
            return
        self._streaming = False
        if self._conn is None:
            return
        self._call("servo_end", self._fault is not None, timeout_s=self.options.connect_timeout_s + 2.0)

    def _backend_stop(self, decel: float) -> None:
        # stopJ waits until the arm rests: at most (rated speed / decel) s
        self._call("stop", decel, timeout_s=3.5 / max(decel, 0.5) + self.call_timeout_s + 1.0)
        # (program stops over the dashboard are the fallback when this fails: GuardedDriver._halt_fallback)

    def _backend_protective_stop(self) -> None:
        self._call("protective_stop", timeout_s=self.call_timeout_s + 1.0)

    def _backend_set_output(self, index: int, level: bool, tool: bool) -> None:
        self._call("set_output", index, level, tool, timeout_s=self.call_timeout_s + 1.5)

    def _backend_reset_faults(self) -> None:
        self._call("reset_faults", timeout_s=self.options.connect_timeout_s + 2.0)


def child_log_path() -> Path | None:
    """Where the child writes its log and ur_rtde's console output (env NORMPOS_GRASP_RTDE_LOG), or None."""
    value = os.environ.get(CHILD_LOG_ENV)
    return Path(value) if value else None
