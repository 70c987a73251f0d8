"""The reference controller: RTDE (30004), dashboard (29999) and script (30003) servers around one `Arm`.

Written independently of `normpos_grasp.sim.ur_emulator`, from the protocol facts in shared/reference/rtde_notes.md,
so that the campaign can run the same faults against two implementations of UR's controller protocol. One thread
per connection and a 500 Hz cycle thread; all state sits behind one lock.

The control script: ur_rtde uploads its script to 30003; the script is recognised by its banner
(`RTDE Control Script Loaded`), anything else is refused (logged, counted, nothing runs). While the script runs,
the cycle reads the command id from `input_int_register_<base>` (base 0, or 24 when the client set up the upper
registers), acts on a new non-real-time command once (a command id after 0 or after a real-time command), answers
in `output_int_register_<base>` (1 ready, 2 done: at once, or for a synchronous move when the arm rests) and keeps
the asynchronous move status in `output_int_register_<base + 2>` (bit 15 running, bits 0-14 path index, 16-23 a
counter of changes, 24-30 the move's id). Real-time commands (servoJ) are applied every cycle.

Test verbs on the dashboard (`emu ...`, the interface the fault campaign speaks): protective_stop, estop,
release_estop, drop, stall S, unlock_delay S, script_delay S, set_input BIT 0|1, state, since T.
"""

from __future__ import annotations

import contextlib
import logging
import os
import re
import socket
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np

from normpos_grasp.errors import InputError
from normpos_grasp.geometry.transforms import pose_from_ur, pose_to_ur
from normpos_grasp.hosts import is_ipv4_loopback_literal
from normpos_grasp.kinematics.ur_params import ur_params

from . import wire
from .robot import Arm

log = logging.getLogger(__name__)

RTDE_PORT, DASHBOARD_PORT, SCRIPT_PORT = 30004, 29999, 30003
BANNER = "RTDE Control Script Loaded"
PERIOD_S = 0.002  # e-Series: 500 Hz
VERSION = (5, 12, 0, 0)
# command ids of ur_rtde's control script (rtde_notes.md)
MOVEJ, MOVEJ_IK, MOVEL, MOVEL_FK, SPEEDJ, SERVOJ, SPEED_STOP, SERVO_STOP = 1, 2, 3, 4, 9, 11, 15, 16
SET_PAYLOAD, SET_TCP, PROTECTIVE_STOP, STOPL, STOPJ, WATCHDOG, MOVE_PATH, STOP_SCRIPT = 17, 29, 31, 33, 34, 35, 45, 255
GET_FK, GET_FK_Q = 43, 44
REALTIME = frozenset({SERVOJ, SPEEDJ, 10, 24, 25, 26, 27})
MOTION = frozenset({MOVEJ, MOVEJ_IK, MOVEL, MOVEL_FK, SPEEDJ, SERVOJ, MOVE_PATH})
_MOVE_LINE = re.compile(r"(movej|movel)\(\s*(p?)\[([^\]]*)\]\s*,\s*a\s*=\s*([^,]+),\s*v\s*=\s*([^,\)]+)")


@dataclass
class Settings:
    """model: UR model name. host: 127.x.y.z. serial: `get serial number`. unlock_delay_s: a protective stop
    cannot be unlocked sooner (UR: 5 s). q_start: joints at power-up, rad. rt_priority: SCHED_FIFO for the cycle."""

    model: str = "ur5e"
    host: str = "127.0.0.1"
    serial: str = "20235509999"
    unlock_delay_s: float = 5.0
    q_start: tuple[float, ...] = (0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0)
    rt_priority: int = 0
    program_start_s: float = 0.1


class _Client:
    """One RTDE connection: its output recipe, input recipes (id -> names, types, struct) and stream state."""

    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock
        self.out_names: list[str] = []
        self.out_types: list[str] = []
        self.out_struct: Any = None
        self.every = 1
        self.streaming = False
        self.inputs: dict[int, tuple[list[str], list[str], Any]] = {}
        self.owned: set[str] = set()
        self.wlock = threading.Lock()

    def send(self, data: bytes) -> None:
        with self.wlock:
            self.sock.sendall(data)


class ReferenceController:
    """The servers and the state of one reference controller. `start()`, then `stop()`."""

    def __init__(self, settings: Settings | None = None) -> None:
        self.s = settings or Settings()
        if not is_ipv4_loopback_literal(self.s.host):
            raise InputError(f"the reference controller binds loopback addresses 127.x.y.z only, got {self.s.host!r}")
        self.params = ur_params(self.s.model)
        self.lock = threading.RLock()
        self.arm = Arm(self.params, np.array(self.s.q_start))
        self.t_start = time.monotonic()
        self.robot_mode, self.safety_mode, self.safety_bits = 7, 1, 0
        self.stopped_at = -1e9
        self.running = False  # the control script
        self.script_path: list[tuple[str, np.ndarray, float, float]] = []
        # an uploaded script waiting to start: (time.monotonic() when it starts, its path entries)
        self.pending: tuple[float, list[tuple[str, np.ndarray, float, float]]] | None = None
        self.base = 0
        self.in_int, self.in_dbl = [0] * 48, [0.0] * 48
        self.out_int, self.out_dbl = [0] * 48, [0.0] * 48
        self.dout, self.din = 0, 0
        self.slider = 1.0
        self.acting = False
        self.sync_wait = False
        self.move_id, self.changes, self.move_async, self.last_status = 0, 0, False, (False, 0)
        self.watchdog_s, self.watchdog_t = 0.0, 0.0
        self.stall_until = 0.0
        self.refuse_until = 0.0
        self.commands = self.motion_cmds = self.refused = self.late = 0
        self.stops: deque[tuple[float, str]] = deque(maxlen=20_000)
        self.rests: deque[float] = deque(maxlen=20_000)
        self.motions: deque[float] = deque(maxlen=200_000)
        self.was_moving = False
        self.clients: list[_Client] = []
        self._socks: list[socket.socket] = []
        self._halt = threading.Event()
        self._threads: list[threading.Thread] = []

    # ------------------------------------------------------------------ life cycle
    def start(self) -> ReferenceController:
        for port, serve in ((RTDE_PORT, self._rtde), (DASHBOARD_PORT, self._dashboard), (SCRIPT_PORT, self._script)):
            lst = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            lst.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                lst.bind((self.s.host, port))
            except OSError as exc:
                lst.close()
                self.stop()
                raise InputError(f"cannot listen on {self.s.host}:{port} ({exc}); use another 127.x address") from exc
            lst.listen(8)
            self._socks.append(lst)
            self._thread(self._accept, lst, serve)
        self._thread(self._cycle_loop)
        log.info("reference controller (%s) on %s", self.s.model, self.s.host)
        return self

    def stop(self) -> None:
        self._halt.set()
        for sock in self._socks + [c.sock for c in self.clients]:
            with contextlib.suppress(OSError):
                sock.close()
        for t in self._threads:
            t.join(timeout=1.0)

    def _thread(self, fn: Any, *args: Any) -> None:
        t = threading.Thread(target=fn, args=args, daemon=True)
        t.start()
        self._threads.append(t)

    def _accept(self, lst: socket.socket, serve: Any) -> None:
        while not self._halt.is_set():
            try:
                sock, _ = lst.accept()
            except OSError:
                return
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            threading.Thread(target=self._guard, args=(serve, sock), daemon=True).start()

    def _guard(self, serve: Any, sock: socket.socket) -> None:
        try:
            serve(sock)
        except (OSError, EOFError, wire.WireError) as exc:
            log.debug("connection ended: %s", exc)
        finally:
            with contextlib.suppress(OSError):
                sock.close()

    # ------------------------------------------------------------------ measurements
    def _stop_event(self, what: str) -> None:
        self.stops.append((time.monotonic(), what))

    def since(self, t: float) -> dict[str, Any]:
        with self.lock:
            first = next(((ts, w) for ts, w in self.stops if ts >= t), None)
            t_stop = first[0] if first else float("inf")
            rest = next((ts for ts in self.rests if ts >= t_stop), None)
            return {
                "stop_t": first[0] if first else -1.0,
                "stop": first[1] if first else "-",
                "rest_t": rest if rest is not None else -1.0,
                "motion_after_stop": sum(ts > t_stop for ts in self.motions),
                "motion_after_t": sum(ts > t for ts in self.motions),
                "moving": self.arm.moving,
            }

    # ------------------------------------------------------------------ safety
    def halt_program(self, why: str) -> None:
        with self.lock:
            self._stop_event(f"programStop:{why}")
            self.running, self.pending = False, None
            self.sync_wait = False
            if self.arm.moving:
                self.arm.safety_stop()
            log.info("program stopped (%s)", why)

    def protective_stop(self, why: str) -> None:
        with self.lock:
            self._stop_event("protectiveStop")
            self.safety_mode, self.safety_bits = 3, self.safety_bits | (1 << 2)
            self.stopped_at = time.monotonic()
            self.running, self.pending = False, None
            self.sync_wait = False
            self.arm.safety_stop()
            log.warning("protective stop: %s", why)

    def emergency_stop(self) -> None:
        with self.lock:
            self._stop_event("emergencyStop")
            self.safety_mode, self.safety_bits = 7, self.safety_bits | (1 << 7)
            self.running, self.pending = False, None
            self.sync_wait = False
            self.arm.safety_stop()

    # ------------------------------------------------------------------ the 500 Hz cycle
    def _cycle_loop(self) -> None:
        if self.s.rt_priority > 0:
            try:
                os.sched_setscheduler(threading.get_native_id(), os.SCHED_FIFO, os.sched_param(self.s.rt_priority))
            except (OSError, AttributeError) as exc:
                log.warning("no real-time scheduling (%s)", exc)
        due = time.monotonic()
        while not self._halt.is_set():
            due += PERIOD_S
            wait = due - time.monotonic()
            if wait > 0:
                time.sleep(wait)
            elif wait < -0.02:
                self.late += 1
                due = time.monotonic()
            try:
                self._cycle()
            except Exception as exc:  # a failed cycle must not leave the arm moving
                log.exception("cycle failed")
                self.protective_stop(f"internal error: {exc}")
            self._stream()

    def _cycle(self) -> None:
        with self.lock:
            now = time.monotonic()
            if self.pending is not None and now >= self.pending[0]:
                self._start_script(self.pending[1])
            if self.running and self.watchdog_s > 0 and now - self.watchdog_t > self.watchdog_s:
                self.halt_program("watchdog")
            if self.running:
                self._script_step()
            self.arm.cycle(PERIOD_S * self.slider)
            if self.arm.fault:
                fault, self.arm.fault = self.arm.fault, ""
                if self.safety_mode == 1:
                    self.protective_stop(fault)
            moving = self.arm.moving
            if self.was_moving and not moving:
                self.rests.append(time.monotonic())
            self.was_moving = moving
            if self.running:
                b = self.base
                if self.sync_wait and not moving:
                    self.sync_wait = False
                    self.out_int[b] = 2
                if self.move_async and not moving:
                    self.move_async = False
                status = (self.move_async, len(self.script_path) - len(self.arm.queue) - 1 if self.arm.queue else 0)
                if status != self.last_status:
                    self.last_status = status
                    self.changes = (self.changes + 1) % 256
                word = (self.move_id << 24) | (self.changes << 16)
                if status[0]:
                    word |= 0x8000 | (max(status[1], 0) & 0x7FFF)
                self.out_int[b + 2] = word

    def _script_step(self) -> None:
        b = self.base
        if self.sync_wait:
            return
        cmd = self.in_int[b]
        if cmd == 0:
            self.acting = False
            self.out_int[b] = 1
        elif cmd in REALTIME:
            self._command(cmd)
            self.acting = False
            self.out_int[b] = 1
        elif not self.acting:
            self.acting = True
            self.commands += 1
            self._command(cmd)

    def _targets(self, n: int = 6) -> np.ndarray:
        return np.array(self.in_dbl[self.base : self.base + n], dtype=np.float64)

    def _command(self, cmd: int) -> None:
        b = self.base
        async_ = self.in_int[b + 1] == 1
        v, a = self.in_dbl[b + 6], self.in_dbl[b + 7]
        if cmd in MOTION:
            self.motion_cmds += 1
            self.motions.append(time.monotonic())
        started = False
        if cmd in (MOVEJ, MOVEL, MOVEJ_IK, MOVEL_FK, MOVE_PATH):
            target = self._targets()
            if cmd == MOVEJ:
                self.arm.move_joints(target, v, a)
            elif cmd == MOVEL:
                self.arm.move_line(pose_from_ur(target), v, a)
            elif cmd == MOVEL_FK:
                self.arm.move_line(self.arm.tcp(target), v, a)
            elif cmd == MOVEJ_IK:
                self.arm.move_joints(self.arm._joints_for(pose_from_ur(target)), v, a)
            else:
                self.arm.run_path(
                    [(k, t if k == "movej" else pose_from_ur(t), vv, aa) for k, t, vv, aa in self.script_path]
                )
            self.move_id = (self.move_id + 1) % 128
            self.move_async = async_
            started = True
        elif cmd == SERVOJ:
            self.arm.servo(self._targets(), self.in_dbl[b + 8])
            return
        elif cmd == SPEEDJ:
            log.error("speedJ is not modelled by the reference controller; nothing moves")
            return
        elif cmd in (SERVO_STOP, SPEED_STOP, STOPJ, STOPL):
            name = {SERVO_STOP: "servoStop", SPEED_STOP: "speedStop", STOPJ: "stopJ", STOPL: "stopL"}[cmd]
            self._stop_event(name)
            decel = self.in_dbl[b] if self.in_dbl[b] > 0 else (2.0 if cmd == STOPJ else 10.0)
            if cmd in (STOPL, SERVO_STOP):
                self.arm.stop_line(decel)
            else:
                self.arm.stop_joints(decel)
            if cmd in (STOPJ, STOPL) and not async_ and self.arm.moving:
                self.sync_wait = True
                return
        elif cmd == SET_TCP:
            self.arm.flange_from_tcp = pose_from_ur(self._targets())
        elif cmd == SET_PAYLOAD:
            pass  # a kinematic arm: the payload changes nothing
        elif cmd == WATCHDOG:
            freq = self.in_dbl[b]
            self.watchdog_s = 1.0 / freq if freq > 0 else 0.0
            self.watchdog_t = time.monotonic()
        elif cmd == PROTECTIVE_STOP:
            self.protective_stop("triggerProtectiveStop from the client")
            return
        elif cmd in (GET_FK, GET_FK_Q):
            q = self.arm.q if cmd == GET_FK else self._targets()
            self.out_dbl[b : b + 6] = pose_to_ur(self.arm.tcp(q)).tolist()
        elif cmd == STOP_SCRIPT:
            self.halt_program("stopScript")
            return
        else:
            log.error("command %d is not modelled; answered done, nothing moved", cmd)
        if started and not async_:
            self.sync_wait = True
        else:
            self.out_int[b] = 2

    # ------------------------------------------------------------------ RTDE
    def _stream(self) -> None:
        if time.monotonic() < self.stall_until:
            return
        targets = [c for c in list(self.clients) if c.streaming and c.out_struct is not None]
        if not targets:
            return
        self._ticks = getattr(self, "_ticks", 0) + 1
        with self.lock:
            values = self._values()
        for c in targets:
            if self._ticks % c.every:
                continue
            flat: list[Any] = []
            for name, kind in zip(c.out_names, c.out_types, strict=True):
                val = values.get(name)
                if val is None:  # not modelled: zeros of the variable's type
                    flat.extend([0] * wire.WIDTH[kind])
                elif isinstance(val, (tuple, list)):
                    flat.extend(val)
                else:
                    flat.append(val)
            try:
                data = wire.packet(wire.DATA, b"\x01" + c.out_struct.pack(*flat))
                if c.wlock.acquire(timeout=0.001):
                    try:
                        c.sock.sendall(data)
                    finally:
                        c.wlock.release()
            except OSError:
                c.streaming = False

    def _values(self) -> dict[str, Any]:
        arm = self.arm
        q, qd, tcp = tuple(arm.q), tuple(arm.qd), tuple(pose_to_ur(arm.tcp()))
        out: dict[str, Any] = {
            "timestamp": time.monotonic() - self.t_start,
            "actual_q": q,
            "target_q": q,
            "actual_qd": qd,
            "target_qd": qd,
            "actual_TCP_pose": tcp,
            "target_TCP_pose": tcp,
            "robot_mode": self.robot_mode,
            "safety_mode": self.safety_mode,
            "safety_status": self.safety_mode,
            "runtime_state": 2 if self.running else 1,
            "robot_status_bits": (1 if self.robot_mode >= 5 else 0) | (2 if self.running else 0),
            "safety_status_bits": self.safety_bits,
            "actual_digital_output_bits": self.dout,
            "actual_digital_input_bits": self.din,
            "speed_scaling": self.slider,
            "target_speed_fraction": self.slider,
            "joint_mode": (253 if self.robot_mode == 7 else 236,) * 6,
            "actual_main_voltage": 48.0,
            "actual_robot_voltage": 48.0,
            "joint_temperatures": (32.0,) * 6,
            "actual_execution_time": 0.0002,
        }
        for i in range(48):
            out[f"output_int_register_{i}"] = self.out_int[i]
            out[f"output_double_register_{i}"] = self.out_dbl[i]
            out[f"input_int_register_{i}"] = self.in_int[i]
            out[f"input_double_register_{i}"] = self.in_dbl[i]
        return out

    def _rtde(self, sock: socket.socket) -> None:
        if time.monotonic() < self.refuse_until:
            return
        c = _Client(sock)
        self.clients.append(c)
        try:
            while not self._halt.is_set():
                kind, body = wire.read_packet(sock)
                self._rtde_packet(c, kind, body)
        finally:
            c.streaming = False
            if c in self.clients:
                self.clients.remove(c)

    def _rtde_packet(self, c: _Client, kind: int, body: bytes) -> None:
        if kind == wire.PROTOCOL_VERSION:
            c.send(wire.packet(kind, bytes([1 if body[:2] in (b"\x00\x01", b"\x00\x02") else 0])))
        elif kind == wire.CONTROL_VERSION:
            c.send(wire.packet(kind, b"".join(n.to_bytes(4, "big") for n in VERSION)))
        elif kind == wire.SETUP_OUTPUTS:
            freq = float(np.frombuffer(body[:8], dtype=">f8")[0])
            names = [n for n in body[8:].decode().split(",") if n]
            unknown = [n for n in names if n not in wire.OUTPUT_TYPES]
            if unknown:
                log.error("output variables not known: %s", unknown)
                reply = ",".join(wire.OUTPUT_TYPES.get(n, "NOT_FOUND") for n in names)
                c.send(wire.packet(kind, b"\x00" + reply.encode()))
                return
            types = [wire.OUTPUT_TYPES[n] for n in names]
            c.out_names = names
            c.out_types = types
            c.out_struct = wire.recipe_struct(types)
            c.every = max(1, round((1.0 / PERIOD_S) / freq)) if freq > 0 else 1
            c.send(wire.packet(kind, b"\x01" + ",".join(types).encode()))
        elif kind == wire.SETUP_INPUTS:
            names = [n for n in body.decode().split(",") if n]
            with self.lock:
                taken = {n for other in self.clients if other is not c for n in other.owned}
            if any(n not in wire.INPUT_TYPES for n in names):
                reply = ",".join(wire.INPUT_TYPES.get(n, "NOT_FOUND") for n in names)
                c.send(wire.packet(kind, b"\x00" + reply.encode()))
                return
            if any(n in taken for n in names):
                reply = ",".join("IN_USE" if n in taken else wire.INPUT_TYPES[n] for n in names)
                c.send(wire.packet(kind, b"\x00" + reply.encode()))
                return
            rid = len(c.inputs) + 1
            types = [wire.INPUT_TYPES[n] for n in names]
            c.inputs[rid] = (names, types, wire.recipe_struct(types))
            c.owned.update(names)
            regs = [int(n.rsplit("_", 1)[1]) for n in names if n.startswith("input_int_register_")]
            if regs:
                with self.lock:
                    self.base = 24 if min(regs) >= 24 else 0
            c.send(wire.packet(kind, bytes([rid]) + ",".join(types).encode()))
        elif kind == wire.START:
            c.streaming = True
            c.send(wire.packet(kind, b"\x01"))
        elif kind == wire.PAUSE:
            c.streaming = False
            c.send(wire.packet(kind, b"\x01"))
        elif kind == wire.DATA:
            recipe = c.inputs.get(body[0])
            if recipe is None:
                log.error("data package for unknown input recipe %d", body[0])
                return
            names, types, st = recipe
            self._apply(names, wire.split_values(types, st.unpack(body[1:])))
        elif kind == wire.TEXT:
            log.info("client message: %r", body[:120])

    def _apply(self, names: list[str], values: list[Any]) -> None:
        with self.lock:
            got = dict(zip(names, values, strict=True))
            for name, val in got.items():
                if name.startswith("input_int_register_"):
                    i = int(name.rsplit("_", 1)[1])
                    self.in_int[i] = int(val)
                    if i == self.base:
                        self.watchdog_t = time.monotonic()
                elif name.startswith("input_double_register_"):
                    self.in_dbl[int(name.rsplit("_", 1)[1])] = float(val)
            for bank, shift in (
                ("standard_digital_output", 0),
                ("configurable_digital_output", 8),
                ("tool_digital_output", 16),
            ):
                mask = int(got.get(bank + "_mask", 0))
                if mask and bank in got:
                    level = int(got[bank])
                    self.dout = (self.dout & ~(mask << shift)) | ((level & mask) << shift)
            if int(got.get("speed_slider_mask", 0)) & 1 and "speed_slider_fraction" in got:
                self.slider = min(1.0, max(0.0, float(got["speed_slider_fraction"])))

    # ------------------------------------------------------------------ script port
    def _script(self, sock: socket.socket) -> None:
        chunks: list[bytes] = []
        sock.settimeout(0.3)
        while not self._halt.is_set():
            try:
                part = sock.recv(65536)
            except TimeoutError:
                if chunks:
                    self._run_script(b"".join(chunks).decode(errors="replace"))
                    chunks = []
                continue
            if not part:
                break
            chunks.append(part)
            text = b"".join(chunks).decode(errors="replace")
            if text.rstrip().endswith("end") and text.count("def ") and _balanced(text):
                self._run_script(text)
                chunks = []
        if chunks:
            self._run_script(b"".join(chunks).decode(errors="replace"))

    def _run_script(self, text: str) -> None:
        if BANNER not in text:
            with self.lock:
                self.refused += 1
            log.error("refused a script that is not ur_rtde's control script: %r", text.strip()[:100])
            return
        path = []
        for m in _MOVE_LINE.finditer(text):
            values = np.array([float(x) for x in m.group(3).split(",")])
            path.append(("movej" if m.group(1) == "movej" else "movel", values, float(m.group(5)), float(m.group(4))))
        with self.lock:
            if self.safety_mode != 1 or self.robot_mode != 7:
                log.error(
                    "script not started: the robot is not ready (safety %d, mode %d)", self.safety_mode, self.robot_mode
                )
                return
            if self.running:
                self.halt_program("replaced by a new script")
            self.pending = (time.monotonic() + self.s.program_start_s, path)
        log.info("control script received (%d path entries); it starts in %.2f s", len(path), self.s.program_start_s)

    def _start_script(self, path: list[tuple[str, np.ndarray, float, float]]) -> None:
        """Start the pending script (in the cycle, under the lock), unless the robot stopped meanwhile."""
        self.pending = None
        if self.safety_mode != 1 or self.robot_mode != 7:
            log.error("script not started: the robot stopped while it loaded (safety %d)", self.safety_mode)
            return
        self.script_path = path
        self.running, self.acting, self.sync_wait, self.watchdog_s = True, False, False, 0.0
        self.out_int[self.base] = 1
        log.info("control script running (%d path entries)", len(path))

    # ------------------------------------------------------------------ dashboard
    def _dashboard(self, sock: socket.socket) -> None:
        f = sock.makefile("rwb", buffering=0)
        f.write(b"Connected: Universal Robots Dashboard Server\n")
        while not self._halt.is_set():
            line = f.readline()
            if not line:
                return
            reply, close = self.answer(line.decode(errors="replace").strip())
            f.write(reply.encode() + b"\n")
            if close:
                return

    def answer(self, line: str) -> tuple[str, bool]:
        """The dashboard's reply to one line, and whether the connection closes."""
        low = line.lower()
        with self.lock:
            if low.startswith("emu"):
                return self._test_verb(line.split()[1:]), False
            if low == "quit":
                return "Disconnected", True
            if low == "polyscopeversion":
                return "URSoftware {}.{}.{}.{} (reference)".format(*VERSION), False
            if low == "get serial number":
                return self.s.serial, False
            if low == "get robot model":
                return "UR" + self.s.model.upper().removeprefix("UR").removesuffix("E"), False
            if low == "is in remote control":
                return "true", False
            if low == "running":
                return f"Program running: {'true' if self.running else 'false'}", False
            if low == "programstate":
                return ("PLAYING" if self.running else "STOPPED") + " <unnamed>", False
            if low == "stop":
                self.halt_program("dashboard stop")
                return "Stopped", False
            if low == "robotmode":
                names = {3: "POWER_OFF", 5: "IDLE", 7: "RUNNING"}
                return f"Robotmode: {names.get(self.robot_mode, str(self.robot_mode))}", False
            if low in ("safetymode", "safetystatus"):
                names = {1: "NORMAL", 3: "PROTECTIVE_STOP", 7: "ROBOT_EMERGENCY_STOP"}
                return f"Safetystatus: {names.get(self.safety_mode, str(self.safety_mode))}", False
            if low == "unlock protective stop":
                if self.safety_mode != 3:
                    return "Protective stop releasing", False
                if time.monotonic() - self.stopped_at < self.s.unlock_delay_s:
                    return (
                        f"Cannot unlock protective stop until {self.s.unlock_delay_s:g}s after occurrence. "
                        "Always inspect cause of protective stop before unlocking"
                    ), False
                self.safety_mode, self.safety_bits = 1, self.safety_bits & ~(1 << 2)
                return "Protective stop releasing", False
            if low == "close safety popup":
                return "closing safety popup", False
            if low == "power on":
                if self.safety_mode == 1 and self.robot_mode < 5:
                    self.robot_mode = 5
                return "Powering on", False
            if low == "power off":
                self.halt_program("power off")
                self.robot_mode = 3
                return "Powering off", False
            if low == "brake release":
                if self.robot_mode == 5:
                    self.robot_mode = 7
                return "Brake releasing", False
            if low in ("play", "pause"):
                return f"Failed to execute: {low}", False
        return f"could not understand: '{line}'", False

    def _test_verb(self, args: list[str]) -> str:
        verb = args[0].lower() if args else ""
        try:
            if verb == "protective_stop":
                self.protective_stop("injected")
            elif verb == "estop":
                self.emergency_stop()
            elif verb == "release_estop":
                if self.safety_mode == 7:
                    self.safety_mode, self.safety_bits, self.robot_mode = 1, self.safety_bits & ~(1 << 7), 3
            elif verb == "drop":
                self.refuse_until = time.monotonic() + (float(args[1]) if len(args) > 1 else 0.0)
                for c in list(self.clients):
                    c.streaming = False
                    with contextlib.suppress(OSError):
                        c.sock.shutdown(socket.SHUT_RDWR)
            elif verb == "script_delay":  # uploaded scripts start this late (a huge value: they never start)
                self.s.program_start_s = float(args[1])
            elif verb == "stall":
                self.stall_until = time.monotonic() + float(args[1])
            elif verb == "unlock_delay":
                self.s.unlock_delay_s = float(args[1])
            elif verb == "set_input":
                bit, level = int(args[1]), int(args[2])
                self.din = self.din | (1 << bit) if level else self.din & ~(1 << bit)
            elif verb == "state":
                q = ",".join(f"{v:.6f}" for v in self.arm.q)
                return (
                    f"emu state pid={os.getpid()} q=[{q}] robot_mode={self.robot_mode} safety_mode={self.safety_mode} "
                    f"program={'running' if self.running else 'stopped'} moving={self.arm.moving} "
                    f"commands={self.commands} refused_scripts={self.refused} overruns={self.late} dout={self.dout} "
                    f"motion_cmds={self.motion_cmds}"
                )
            elif verb == "since":
                return "emu since " + " ".join(f"{k}={v}" for k, v in self.since(float(args[1])).items())
            else:
                return f"emu: unknown verb {verb!r}"
        except (IndexError, ValueError) as exc:
            return f"emu: bad arguments {args!r}: {exc}"
        return f"emu ok {verb}"


def _balanced(text: str) -> bool:
    """A URScript program is complete when its `def`/`thread`/`if`/`while` blocks are closed (rough count)."""
    opens = len(re.findall(r"^\s*(def|thread|while|if|for)\b.*:\s*$", text, re.MULTILINE))
    closes = len(re.findall(r"^\s*end\s*$", text, re.MULTILINE))
    return closes >= opens
