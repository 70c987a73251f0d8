"""Socket servers of the loopback UR controller: RTDE (30004), dashboard (29999), script (30003), the Robotiq
URCap's gripper socket (63352, robotiq_server.py), and the 500 Hz loop.

Ports are fixed (ur_rtde hard-codes them), so one emulator listens per loopback address; run several on
127.0.0.1, 127.0.0.2, ... Faults are injected through the API (`inject_*`) or through dashboard lines starting
with `emu` (see docs/emulator.md).
"""

from __future__ import annotations

import contextlib
import functools
import logging
import os
import socket
import struct
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from normpos_grasp.errors import InputError, NormposError
from normpos_grasp.hosts import is_ipv4_loopback_literal
from normpos_grasp.kinematics.ur_params import ur_params

from . import protocol as P
from .arm import IKSolver
from .controller import EmulatedController, EmulatorOptions
from .robotiq_server import ROBOTIQ_MODELS, RobotiqServer, SimulatedRobotiq

log = logging.getLogger(__name__)

RTDE_PORT, DASHBOARD_PORT, SCRIPT_PORT = 30004, 29999, 30003


def load_ik(model: str) -> IKSolver | None:
    """The kinematics module's IK for `model` if it is available, else None (linear moves then fail loudly)."""
    try:
        from normpos_grasp.kinematics import Robot

        robot = Robot.load(model)
    except (ImportError, AttributeError, NormposError) as exc:
        log.warning("no IK for %s (%s): moveL/moveJ_IK will be refused", model, exc)
        return None
    # the first call loads the compiled one-pose IK (compiles it once per install): here, not inside the control loop
    robot.ik(robot.fk([0.0, -1.0, 1.0, -1.0, -1.5, 0.0]))

    def ik(base_from_flange: Any, q_near: Any) -> Any:
        return robot.ik(base_from_flange, q_near)

    return ik


@dataclass
class _RtdeConn:
    sock: socket.socket
    addr: Any
    output_names: list[str] = field(default_factory=list)
    output_getters: list[Callable[[dict[str, Any]], Any]] = field(default_factory=list)
    output_struct: struct.Struct | None = None
    output_types: list[str] = field(default_factory=list)
    decimation: int = 1
    inputs: dict[int, tuple[list[str], list[str], struct.Struct]] = field(default_factory=dict)
    started: bool = False
    send_lock: threading.Lock = field(default_factory=threading.Lock)
    sent: int = 0
    dropped: int = 0


def _getter(name: str) -> Callable[[dict[str, Any]], Any]:
    for prefix, key in (
        ("output_int_register_", "output_int"),
        ("output_double_register_", "output_double"),
        ("input_int_register_", "input_int"),
        ("input_double_register_", "input_double"),
    ):
        if name.startswith(prefix):
            return functools.partial(_register_value, key, int(name[len(prefix) :]))
    kind = P.OUTPUT_TYPES[name]
    default: Any = (
        (0.0,) * 6
        if kind == "VECTOR6D"
        else (0.0,) * 3
        if kind == "VECTOR3D"
        else ((0,) * 6 if kind.startswith("VECTOR6") else 0.0 if kind == "DOUBLE" else False if kind == "BOOL" else 0)
    )
    return functools.partial(_named_value, name, default)


def _register_value(key: str, index: int, snap: dict[str, Any]) -> Any:
    return snap[key][index]


def _named_value(name: str, default: Any, snap: dict[str, Any]) -> Any:
    return snap.get(name, default)


class UREmulator:
    """A loopback UR controller serving the unmodified ur_rtde clients. Use `start()` / `stop()` or a `with` block.

    Must run in a process of its own when the ur_rtde client runs in Python: the client's constructors hold the GIL
    while they wait for data (see `EmulatorProcess`).
    """

    def __init__(self, options: EmulatorOptions | None = None, ik: IKSolver | None = None) -> None:
        self.options = options or EmulatorOptions()
        if not is_ipv4_loopback_literal(self.options.host):
            raise InputError(f"emulator host must be a loopback address 127.x.y.z, got {self.options.host!r}")
        params = ur_params(self.options.model)
        self.controller = EmulatedController(params, self.options, ik if ik is not None else load_ik(params.name))
        self._listeners: list[socket.socket] = []
        self._threads: list[threading.Thread] = []
        self._conns: list[_RtdeConn] = []
        self._other_socks: list[socket.socket] = []
        self._conn_lock = threading.Lock()
        self._input_owner: dict[str, _RtdeConn] = {}
        self._stop = threading.Event()
        self.refuse_rtde_until = 0.0
        self.periods: list[float] = []
        self.overruns = 0
        self.robotiq: SimulatedRobotiq | None = None
        self._robotiq_server: RobotiqServer | None = None
        if self.options.robotiq_model:
            model = ROBOTIQ_MODELS.get(self.options.robotiq_model.upper())
            if model is None:
                raise InputError(
                    f"unknown Robotiq gripper {self.options.robotiq_model!r}; known: {', '.join(ROBOTIQ_MODELS)}"
                )
            self.robotiq = SimulatedRobotiq(model, self._tcp_position)

    def _tcp_position(self) -> Any:
        """TCP position in the base frame, m (the simulated Robotiq's parts are placed relative to it)."""
        with self.controller.lock:
            return self.controller.arm.base_from_tcp()[:3, 3].copy()

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> UREmulator:
        # The 500 Hz loop shares the GIL with the socket threads (ur_rtde polls the dashboard at up to 1 kHz while
        # it waits for a command): hand the GIL over every 0.2 ms instead of Python's default 5 ms.
        sys.setswitchinterval(min(sys.getswitchinterval(), 0.0002))
        for port, handler in (
            (RTDE_PORT, self._serve_rtde),
            (DASHBOARD_PORT, self._serve_dashboard),
            (SCRIPT_PORT, self._serve_script),
        ):
            lst = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            lst.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                lst.bind((self.options.host, port))
            except OSError as exc:
                self.stop()
                raise NormposError(
                    f"cannot bind {self.options.host}:{port} ({exc}); another emulator or controller listens there: "
                    "stop it or use another 127.0.0.x address"
                ) from exc
            lst.listen(8)
            self._listeners.append(lst)
            self._spawn(self._accept_loop, lst, handler)
        if self.robotiq is not None:
            try:
                self._robotiq_server = RobotiqServer(self.robotiq, self.options.host, self.options.robotiq_port).start()
            except NormposError:
                self.stop()
                raise
        self._spawn(self._control_loop)
        log.info("UR emulator (%s) listening on %s", self.options.model, self.options.host)
        return self

    def _spawn(self, target: Callable[..., None], *args: Any) -> None:
        th = threading.Thread(target=target, args=args, daemon=True)
        th.start()
        self._threads.append(th)

    def stop(self) -> None:
        self._stop.set()
        if self._robotiq_server is not None:
            self._robotiq_server.stop()
        for sock in self._listeners:
            with contextlib.suppress(OSError):
                sock.close()
        self.drop_connections(include_all=True)
        deadline = time.monotonic() + 2.0  # s for all threads together (daemons: a stuck one dies with the process)
        for th in self._threads:
            th.join(timeout=max(0.0, deadline - time.monotonic()))

    def __enter__(self) -> UREmulator:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def serve_forever(self) -> None:
        """Block until `stop()` (or KeyboardInterrupt in the caller)."""
        while not self._stop.wait(0.5):
            pass

    # ------------------------------------------------------------------ fault injection API
    def inject_protective_stop(self) -> None:
        self.controller.protective_stop("injected")

    def inject_emergency_stop(self) -> None:
        self.controller.emergency_stop()

    def release_emergency_stop(self) -> None:
        self.controller.release_emergency_stop()

    def inject_stall(self, seconds: float) -> None:
        """Keep the sockets open but send no RTDE data for `seconds`."""
        self.controller.stall_until = time.monotonic() + seconds

    def drop_connections(self, refuse_s: float = 0.0, include_all: bool = False) -> None:
        """Close every RTDE connection (all connections with include_all); refuse new RTDE clients for refuse_s."""
        self.refuse_rtde_until = time.monotonic() + refuse_s
        with self._conn_lock:
            socks = [c.sock for c in self._conns]
            self._conns.clear()
            self._input_owner.clear()
            if include_all:
                socks += self._other_socks
                self._other_socks.clear()
        for sock in socks:
            with contextlib.suppress(OSError):
                sock.shutdown(socket.SHUT_RDWR)
            with contextlib.suppress(OSError):
                sock.close()
        self.controller.events.append(f"dropped {len(socks)} connections")

    # ------------------------------------------------------------------ servers
    def _accept_loop(self, lst: socket.socket, handler: Callable[[socket.socket, Any], None]) -> None:
        lst.settimeout(0.2)
        while not self._stop.is_set():
            try:
                sock, addr = lst.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            sock.settimeout(None)
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self._spawn(handler, sock, addr)

    def _serve_rtde(self, sock: socket.socket, addr: Any) -> None:
        if time.monotonic() < self.refuse_rtde_until:
            sock.close()
            return
        conn = _RtdeConn(sock, addr)
        log.debug("RTDE connection from %s", addr)
        with self._conn_lock:
            self._conns.append(conn)
        try:
            while not self._stop.is_set():
                kind, payload = P.recv_packet(sock)
                self._handle_rtde(conn, kind, payload)
        except (P.PeerClosed, OSError) as exc:
            log.debug("RTDE connection %s closed: %s", addr, exc)
        except NormposError as exc:
            log.error("RTDE client %s: %s", addr, exc)
        finally:
            with self._conn_lock:
                if conn in self._conns:
                    self._conns.remove(conn)
                for name in [n for n, c in self._input_owner.items() if c is conn]:
                    del self._input_owner[name]
            with contextlib.suppress(OSError):
                sock.close()

    def _send(self, conn: _RtdeConn, data: bytes) -> None:
        with conn.send_lock:
            conn.sock.sendall(data)

    def _handle_rtde(self, conn: _RtdeConn, kind: int, payload: bytes) -> None:
        if kind == P.REQUEST_PROTOCOL_VERSION:
            version = struct.unpack(">H", payload[:2])[0]
            self._send(conn, P.pack_packet(kind, struct.pack(">B", 1 if version in (1, 2) else 0)))
        elif kind == P.GET_URCONTROL_VERSION:
            self._send(conn, P.pack_packet(kind, struct.pack(">IIII", *self.options.control_version)))
        elif kind == P.CONTROL_PACKAGE_SETUP_OUTPUTS:
            freq = struct.unpack(">d", payload[:8])[0]
            names = [n for n in payload[8:].decode("ascii").split(",") if n]
            log.debug("output recipe from %s at %g Hz: %s", conn.addr, freq, names)
            types = [P.OUTPUT_TYPES.get(n, "NOT_FOUND") for n in names]
            if "NOT_FOUND" in types:
                missing = [n for n, t in zip(names, types, strict=True) if t == "NOT_FOUND"]
                log.error("RTDE output variables not emulated: %s", missing)
                self._send(conn, P.pack_packet(kind, b"\x00" + ",".join(types).encode()))
                return
            conn.output_names = names
            conn.output_types = types
            conn.output_getters = [_getter(n) for n in names]
            conn.output_struct = P.recipe_struct(types)
            base = 1.0 / self.options.period_s
            conn.decimation = max(1, round(base / freq)) if freq > 0 else 1
            self._send(conn, P.pack_packet(kind, b"\x01" + ",".join(types).encode()))
        elif kind == P.CONTROL_PACKAGE_SETUP_INPUTS:
            names = [n for n in payload.decode("ascii").split(",") if n]
            log.debug("input recipe from %s: %s", conn.addr, names)
            types = [P.INPUT_TYPES.get(n, "NOT_FOUND") for n in names]
            with self._conn_lock:
                for i, n in enumerate(names):
                    owner = self._input_owner.get(n)
                    if types[i] != "NOT_FOUND" and owner is not None and owner is not conn:
                        types[i] = "IN_USE"
                ok = all(t not in ("NOT_FOUND", "IN_USE") for t in types)
                if ok:
                    for n in names:
                        self._input_owner[n] = conn
            if not ok:
                bad = [f"{n}:{t}" for n, t in zip(names, types, strict=True) if t in ("NOT_FOUND", "IN_USE")]
                log.warning("RTDE input recipe refused for %s: %s", conn.addr, bad[:4])
                self._send(conn, P.pack_packet(kind, b"\x00" + ",".join(types).encode()))
                return
            recipe_id = len(conn.inputs) + 1
            conn.inputs[recipe_id] = (names, types, P.recipe_struct(types))
            self._send(conn, P.pack_packet(kind, struct.pack(">B", recipe_id) + ",".join(types).encode()))
        elif kind == P.CONTROL_PACKAGE_START:
            self._send(conn, P.pack_packet(kind, b"\x01"))  # the reply must precede the first data package
            conn.started = True
        elif kind == P.CONTROL_PACKAGE_PAUSE:
            conn.started = False
            self._send(conn, P.pack_packet(kind, b"\x01"))
        elif kind == P.DATA_PACKAGE:
            recipe_id = payload[0]
            recipe = conn.inputs.get(recipe_id)
            if recipe is None:
                log.error("RTDE data package for unknown input recipe %d from %s", recipe_id, conn.addr)
                return
            names, types, st = recipe
            values = P.unflatten(st.unpack(payload[1 : 1 + st.size]), types)
            self.controller.apply_inputs(names, values)
        elif kind == P.TEXT_MESSAGE:
            pass
        else:
            raise P.ProtocolError(f"unexpected RTDE packet type {kind} ({chr(kind)!r})")

    def _serve_script(self, sock: socket.socket, addr: Any) -> None:
        log.debug("script connection from %s", addr)
        with self._conn_lock:
            self._other_socks.append(sock)
        buf = ""
        try:
            while not self._stop.is_set():
                data = sock.recv(65536)
                if not data:
                    break
                buf += data.decode("utf-8", errors="replace")
                buf = self._consume_scripts(buf)
        except OSError:
            pass
        finally:
            if buf.strip():
                self._consume_scripts(buf, final=True)
            with contextlib.suppress(OSError):
                sock.close()

    def _consume_scripts(self, buf: str, final: bool = False) -> str:
        """Run every complete program in buf (a top-level `def`/`sec` ... `end`); return the rest."""
        lines = buf.split("\n")
        start = None
        consumed = 0
        pos = 0
        for i, line in enumerate(lines[:-1] if not final else lines):
            pos_line = pos
            pos += len(line) + 1
            if start is None:
                if line.startswith(("def ", "sec ")):
                    start = pos_line
                elif line.strip():
                    self.controller.load_script(line)  # a bare command: refused loudly
                    consumed = pos
            elif line.rstrip() == "end":
                self.controller.load_script(buf[start:pos])
                start = None
                consumed = pos
            _ = i
        return buf[consumed:]

    def _serve_dashboard(self, sock: socket.socket, addr: Any) -> None:
        with self._conn_lock:
            self._other_socks.append(sock)
        f = sock.makefile("rwb", buffering=0)
        try:
            sock.sendall(b"Connected: Universal Robots Dashboard Server\n")
            buf = b""
            while not self._stop.is_set():
                data = sock.recv(4096)
                if not data:
                    break
                buf += data
                while b"\n" in buf:
                    raw, buf = buf.split(b"\n", 1)
                    reply, close = self.dashboard(raw.decode("utf-8", errors="replace").strip())
                    if not raw.startswith(b"running"):
                        log.debug("dashboard %s: %r -> %r", addr, raw, reply)
                    sock.sendall(reply.encode() + b"\n")
                    if close:
                        return
        except OSError:
            pass
        finally:
            f.close()
            with contextlib.suppress(OSError):
                sock.close()

    def dashboard(self, line: str) -> tuple[str, bool]:
        """Answer one dashboard command; (reply, close connection)."""
        c = self.controller
        cmd = line.lower()
        if cmd.startswith("emu"):
            return self._emu(line.split()[1:]), False
        if cmd == "polyscopeversion":
            v = self.options.control_version
            return f"URSoftware {v[0]}.{v[1]}.{v[2]}.{v[3]} (Nov 23 2026)", False
        if cmd == "get serial number":
            return self.options.serial, False
        if cmd == "is in remote control":
            return "true", False
        if cmd == "get robot model":
            return "UR" + self.options.model.upper().lstrip("UR").rstrip("E"), False
        if cmd == "running":
            return f"Program running: {'true' if c.program is not None else 'false'}", False
        if cmd == "stop":
            c.stop_program("dashboard stop")
            return "Stopped", False
        if cmd == "play":
            return "Failed to execute: play (no program loaded; the emulator runs only uploaded ur_rtde scripts)", False
        if cmd == "pause":
            return "Failed to execute: pause", False
        if cmd == "programstate":
            return ("PLAYING rtde_control" if c.program is not None else "STOPPED <unnamed>"), False
        if cmd == "robotmode":
            names = {3: "POWER_OFF", 5: "IDLE", 7: "RUNNING"}
            return f"Robotmode: {names.get(c.robot_mode, str(c.robot_mode))}", False
        if cmd in ("safetymode", "safetystatus"):
            names = {1: "NORMAL", 3: "PROTECTIVE_STOP", 7: "ROBOT_EMERGENCY_STOP"}
            label = "Safetymode" if cmd == "safetymode" else "Safetystatus"
            return f"{label}: {names.get(c.safety_mode, str(c.safety_mode))}", False
        if cmd == "unlock protective stop":
            _, reply = c.unlock_protective_stop()
            return reply, False
        if cmd == "close safety popup":
            return "closing safety popup", False
        if cmd == "close popup":
            return "closing popup", False
        if cmd == "power on":
            with c.lock:
                if c.safety_mode == 1 and c.robot_mode < 5:
                    c.robot_mode = 5
            return "Powering on", False
        if cmd == "power off":
            c.stop_program("power off")
            with c.lock:
                c.robot_mode = 3
            return "Powering off", False
        if cmd == "brake release":
            with c.lock:
                if c.robot_mode == 5:
                    c.robot_mode = 7
            return "Brake releasing", False
        if cmd == "quit":
            return "Disconnected", True
        if cmd == "restart safety":
            with c.lock:
                c.safety_mode, c.safety_bits, c.robot_mode = 1, 0, 3
            return "Restarting safety", False
        return f"could not understand: '{line}'", False

    def _emu(self, args: list[str]) -> str:
        """Fault-injection verbs: protective_stop, estop, release_estop, drop [refuse_s], stall S,
        unlock_delay S, set_input BIT 0|1, set_analog 0|1 VALUE, state, since T (stops after time.monotonic() T,
        for measurements), gripper part W [X Y Z [R]] | part none | fault CODE | state (the simulated Robotiq: a part
        of width W m at base-frame X Y Z within R m of the TCP, default anywhere; a FLT code; its registers)."""
        c = self.controller
        if not args:
            return (
                "emu: verbs are protective_stop, estop, release_estop, drop [refuse_s], stall S, unlock_delay S, "
                "set_input BIT 0|1, set_analog 0|1 VALUE, state, since T, gripper part|fault|state"
            )
        verb = args[0].lower()
        try:
            if verb == "protective_stop":
                self.inject_protective_stop()
            elif verb == "estop":
                self.inject_emergency_stop()
            elif verb == "release_estop":
                self.release_emergency_stop()
            elif verb == "drop":
                self.drop_connections(float(args[1]) if len(args) > 1 else 0.0)
            elif verb == "stall":
                self.inject_stall(float(args[1]))
            elif verb == "unlock_delay":
                self.options.unlock_delay_s = float(args[1])
            elif verb == "set_input":
                bit, level = int(args[1]), int(args[2])
                with c.lock:
                    c.digital_in = (c.digital_in | (1 << bit)) if level else (c.digital_in & ~(1 << bit))
            elif verb == "set_analog":
                index, value = int(args[1]), float(args[2])
                if index not in (0, 1):
                    return f"emu: standard analog inputs are 0 and 1, got {index}"
                with c.lock:
                    c.analog_in[index] = value
            elif verb == "gripper":
                return self._emu_gripper(args[1:])
            elif verb == "state":
                with c.lock:
                    q = ",".join(f"{v:.6f}" for v in c.arm.q)
                    return (
                        f"emu state pid={os.getpid()} q=[{q}] robot_mode={c.robot_mode} safety_mode={c.safety_mode} "
                        f"program={'running' if c.program else 'stopped'} moving={c.arm.moving} "
                        f"commands={c.commands_seen} refused_scripts={len(c.refused_scripts)} "
                        f"overruns={self.overruns} dout={c.digital_out} motion_cmds={c.motion_cmds}"
                    )
            elif verb == "since":
                info = c.stops_since(float(args[1]))
                return "emu since " + " ".join(f"{k}={v}" for k, v in info.items())
            else:
                return f"emu: unknown verb {verb!r}"
        except (IndexError, ValueError) as exc:
            return f"emu: bad arguments {args!r}: {exc}"
        return f"emu ok {verb}"

    def _emu_gripper(self, args: list[str]) -> str:
        """`gripper part W [X Y Z [R]]`, `gripper part none`, `gripper fault CODE`, `gripper state`."""
        g = self.robotiq
        if g is None:
            return "emu: this emulator serves no Robotiq socket (robotiq_model '')"
        if not args:
            return "emu: gripper part W [X Y Z [R]] | part none | fault CODE | state"
        sub = args[0].lower()
        if sub == "state":
            return "emu " + g.describe()
        if sub == "part" and len(args) == 2 and args[1].lower() == "none":
            g.set_part(None)
        elif sub == "part" and len(args) in (2, 5, 6):
            width = float(args[1])
            if not 0.0 < width < 1.0:
                return f"emu: part width {width} m must be in (0, 1) m"
            position = None if len(args) == 2 else [float(v) for v in args[2:5]]
            radius = float(args[5]) if len(args) == 6 else 0.02
            g.set_part(width, None if position is None else np.array(position), radius)
        elif sub == "fault" and len(args) == 2:
            g.inject_fault(int(args[1], 0))
        else:
            return f"emu: bad gripper arguments {args!r}"
        return f"emu ok gripper {sub}"

    # ------------------------------------------------------------------ the 500 Hz loop
    def _control_loop(self) -> None:
        if self.options.rt_priority > 0:
            try:
                os.sched_setscheduler(
                    threading.get_native_id(), os.SCHED_FIFO, os.sched_param(self.options.rt_priority)
                )
                log.info("control loop runs with SCHED_FIFO priority %d", self.options.rt_priority)
            except (OSError, AttributeError) as exc:
                log.warning("cannot use real-time scheduling (%s); the 2 ms period may jitter under load", exc)
        period = self.options.period_s
        next_t = time.monotonic()
        last = next_t
        tick = 0
        while not self._stop.is_set():
            next_t += period
            delay = next_t - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            elif delay < -10 * period:
                self.overruns += 1
                next_t = time.monotonic()
            now = time.monotonic()
            if len(self.periods) < 200_000:
                self.periods.append(now - last)
            last = now
            try:
                self.controller.tick()
                self._publish(tick)
            except Exception as exc:  # a failed cycle must not leave the arm moving: stop it, as a controller would
                log.exception("emulator control cycle failed; protective stop")
                self.controller.protective_stop(f"internal error: {exc}")
            tick += 1

    def _publish(self, tick: int) -> None:
        if time.monotonic() < self.controller.stall_until:
            return
        with self._conn_lock:
            conns = [c for c in self._conns if c.started and c.output_struct is not None]
        if not conns:
            return
        with self.controller.lock:
            snap = self.controller.snapshot()
        for conn in conns:
            if tick % conn.decimation:
                continue
            if conn.output_struct is None:
                continue
            values = P.flatten([g(snap) for g in conn.output_getters], conn.output_types)
            packet = P.pack_packet(P.DATA_PACKAGE, b"\x01" + conn.output_struct.pack(*values))
            if not conn.send_lock.acquire(blocking=False):
                conn.dropped += 1  # a reply is being written on this connection: skip one data package
                continue
            try:
                sent = conn.sock.send(packet, socket.MSG_DONTWAIT)
                if sent != len(packet):
                    conn.sock.sendall(packet[sent:])
                conn.sent += 1
            except BlockingIOError:
                conn.dropped += 1
            except OSError:
                conn.started = False
            finally:
                conn.send_lock.release()
