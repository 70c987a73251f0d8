"""The loopback controller's Robotiq 2F-85 / 2F-140 URCap socket (TCP 63352 by default) and its simulated gripper.

Protocol (the Robotiq Gripper URCap's socket server, as Robotiq documents it for the URCap and as ur_rtde's
RobotiqGripper client speaks it; source: Robotiq, "Control Robotiq gripper mounted on UR robot via socket
communication", dof.robotiq.com discussions 1962 and 2420, and ur_rtde src/robotiq_gripper.cpp): ASCII lines
`SET <VAR> <int> [<VAR> <int> ...]` answered `ack` (no line end), `GET <VAR>` answered `<VAR> <int>` and a line end.
Several lines in one packet get their answers in one packet. Variables (Robotiq 2F-85/140 manual, section 4: robot
input/output registers): ACT activation request, GTO go to the requested position, ATR automatic release, ADR/ARD
release direction, POS requested position (SET) or current position (GET), 0 open ... 255 closed, SPE speed and
FOR force (0 minimum ... 255 maximum), PRE echo of the requested position, STA gripper status (0 reset, 1 activation
in progress, 3 activation completed), OBJ object detection (0 fingers moving, 1 stopped by contact while opening,
2 stopped by contact while closing, 3 at the requested position, no object), FLT fault (0 none, 0x07 activation bit
not set before an action, 0x0E overcurrent, ...). A refused or unknown request is answered `?` (the emulator's choice:
anything but `ack` is a refusal for ur_rtde's client).

The simulated gripper moves its fingers at the commanded speed (SPE mapped linearly onto the model's rated finger
speed range), stops at its mechanical ends (`open_counts`, `closed_counts`: a real gripper's ends are not exactly 0
and 255, which is why drivers calibrate them), and catches a part: a part of width w whose position is within its
radius of the TCP (or a part "anywhere") stops closing fingers at opening w (OBJ 2) and then follows the TCP until the
fingers open wider than w; with no part there the fingers reach their target (OBJ 3).
"""

from __future__ import annotations

import contextlib
import logging
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from normpos_grasp.errors import InputError, NormposError
from normpos_grasp.hosts import is_ipv4_loopback_literal

log = logging.getLogger(__name__)

ROBOTIQ_PORT = 63352  # the Robotiq Gripper URCap's socket server
STA_RESET, STA_ACTIVATING, STA_ACTIVE = 0, 1, 3
OBJ_MOVING, OBJ_CONTACT_OPENING, OBJ_CONTACT_CLOSING, OBJ_AT_POSITION = 0, 1, 2, 3
FLT_NONE, FLT_NOT_ACTIVATED, FLT_OVERCURRENT = 0x00, 0x07, 0x0E
WRITABLE = ("ACT", "GTO", "ATR", "ADR", "ARD", "POS", "SPE", "FOR")
READABLE = ("ACT", "GTO", "ATR", "ADR", "ARD", "POS", "SPE", "FOR", "PRE", "STA", "OBJ", "FLT")


@dataclass(frozen=True)
class RobotiqModel:
    """A 2F gripper's parameters. stroke_m: full opening, m. speed range: finger speed at SPE 0 and 255, m/s
    (Robotiq's specifications: 2F-85 20-150 mm/s, 2F-140 30-250 mm/s). open_counts / closed_counts: POS at the
    mechanical ends (emulator settings, not published figures). activation_s: time from ACT 1 to STA 3, s."""

    name: str
    stroke_m: float
    speed_min_m_s: float
    speed_max_m_s: float
    open_counts: int = 3
    closed_counts: int = 229
    activation_s: float = 0.3

    def opening_at(self, counts: float) -> float:
        """Finger opening (m) at position `counts`."""
        span = self.closed_counts - self.open_counts
        return float(np.clip((self.closed_counts - counts) / span, 0.0, 1.0) * self.stroke_m)

    def counts_at(self, opening_m: float) -> float:
        """Position (counts, fractional) at opening `opening_m`, m."""
        frac = np.clip(opening_m / self.stroke_m, 0.0, 1.0)
        return float(self.closed_counts - frac * (self.closed_counts - self.open_counts))

    def speed_m_s(self, spe: int) -> float:
        return self.speed_min_m_s + (self.speed_max_m_s - self.speed_min_m_s) * spe / 255.0


ROBOTIQ_MODELS = {
    "2F-85": RobotiqModel("2F-85", 0.085, 0.020, 0.150),
    "2F-140": RobotiqModel("2F-140", 0.140, 0.030, 0.250),
}


@dataclass
class SimPart:
    """A part the fingers can catch: width_m across the fingers; position (3,) in the base frame (None: wherever
    the TCP is); radius_m: how near the TCP it must be to sit between the fingers."""

    width_m: float
    position: np.ndarray | None = None
    radius_m: float = 0.02


class SimulatedRobotiq:
    """The gripper behind the socket, integrated lazily: every request first advances it to the present.

    tcp_position: returns the TCP position (3,) in the base frame, m (None: no arm, parts 'anywhere' only).
    clock: seconds (time.monotonic by default)."""

    def __init__(
        self,
        model: RobotiqModel,
        tcp_position: Callable[[], np.ndarray] | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.model = model
        self.tcp_position = tcp_position
        self.clock = clock
        self.lock = threading.RLock()
        self.reg = {name: 0 for name in READABLE}
        self.pos = float(model.open_counts)  # current finger position, counts
        self.requested = 0
        self.activate_at = -1.0
        self.last = clock()
        self.parts: list[SimPart] = []
        self.held: SimPart | None = None
        self.held_offset = np.zeros(3)
        self.requests = 0

    # ------------------------------------------------------------------ test / sim API
    def set_part(self, width_m: float | None, position: np.ndarray | None = None, radius_m: float = 0.02) -> None:
        """Replace the parts with one of `width_m` (None: no part) at `position` (None: wherever the TCP is)."""
        with self.lock:
            self.advance()
            self.parts = [] if width_m is None else [SimPart(float(width_m), position, float(radius_m))]
            self.held = None

    def inject_fault(self, code: int) -> None:
        """A gripper fault (FLT code): the fingers stop where they are."""
        with self.lock:
            self.advance()
            self.reg["FLT"] = int(code)

    # ------------------------------------------------------------------ protocol
    def handle_line(self, line: str) -> str:
        """Answer one request line (without its line end)."""
        with self.lock:
            self.requests += 1
            self.advance()
            words = line.split()
            if not words:
                return "?"
            verb = words[0].upper()
            if verb == "GET" and len(words) == 2:
                var = words[1].upper()
                if var not in READABLE:
                    return "?\n"
                value = int(round(self.pos)) if var == "POS" else self.reg[var]
                return f"{var} {value}\n"
            if verb == "SET" and len(words) >= 3 and len(words) % 2 == 1:
                pairs = []
                for var, text in zip(words[1::2], words[2::2], strict=True):
                    if var.upper() not in WRITABLE or not text.isdigit() or not 0 <= int(text) <= 255:
                        return "?"
                    pairs.append((var.upper(), int(text)))
                for var, value in pairs:
                    self._set(var, value)
                return "ack"
            return "?"

    def _set(self, var: str, value: int) -> None:
        now = self.clock()
        if var == "ACT":
            if value == 0:
                self.reg.update(ACT=0, STA=STA_RESET, GTO=0, OBJ=OBJ_MOVING, FLT=FLT_NONE, PRE=0)
                self.activate_at = -1.0
            elif self.reg["ACT"] == 0:
                self.reg.update(ACT=1, STA=STA_ACTIVATING)
                self.activate_at = now + self.model.activation_s
            return
        if var == "POS":
            self.requested = value
            if self.reg["GTO"]:
                self._start_motion()
            return
        if var == "GTO":
            self.reg["GTO"] = value
            if value:
                self._start_motion()
            return
        if var == "ARD":
            var = "ADR"
        self.reg[var] = value

    def _start_motion(self) -> None:
        if self.reg["STA"] != STA_ACTIVE:
            self.reg["FLT"] = FLT_NOT_ACTIVATED
            return
        self.reg["PRE"] = self.requested
        self.reg["OBJ"] = OBJ_MOVING

    def advance(self) -> None:
        """Move the simulated gripper from the last request to now."""
        now = self.clock()
        dt, self.last = max(0.0, now - self.last), now
        r, m = self.reg, self.model
        if r["STA"] == STA_ACTIVATING and 0.0 <= self.activate_at <= now:
            r["STA"], r["FLT"] = STA_ACTIVE, FLT_NONE
        if self.held is not None and self.tcp_position is not None:
            self.held.position = self.tcp_position() + self.held_offset  # a held part follows the TCP
        if r["STA"] != STA_ACTIVE or not r["GTO"] or r["FLT"] or r["OBJ"] != OBJ_MOVING:
            return
        target = float(np.clip(r["PRE"], m.open_counts, m.closed_counts))
        counts_per_m = (m.closed_counts - m.open_counts) / m.stroke_m
        step = m.speed_m_s(r["SPE"]) * counts_per_m * dt
        gap = target - self.pos
        new = self.pos + float(np.sign(gap)) * min(step, abs(gap))
        if gap > 0:  # closing: a part between the fingers stops them at its width
            part = self.held or self._part_between()
            if part is not None:
                contact = m.counts_at(part.width_m)
                if self.pos <= contact + 1e-9 and new >= contact - 1e-9 and contact < target:
                    self.pos = contact
                    r["OBJ"] = OBJ_CONTACT_CLOSING
                    if self.held is None:
                        self.held = part
                        here = self.tcp_position() if self.tcp_position is not None else np.zeros(3)
                        self.held_offset = (part.position - here) if part.position is not None else np.zeros(3)
                    return
        elif gap < 0 and self.held is not None and m.opening_at(new) > self.held.width_m:
            self.held = None  # released where it is
        self.pos = new
        if abs(target - self.pos) < 1e-9:
            r["OBJ"] = OBJ_AT_POSITION

    def _part_between(self) -> SimPart | None:
        for part in self.parts:
            if part.position is None:
                return part
            if self.tcp_position is not None and np.linalg.norm(self.tcp_position() - part.position) <= part.radius_m:
                return part
        return None

    def describe(self) -> str:
        with self.lock:
            self.advance()
            vals = " ".join(f"{k}={self.reg[k]}" for k in ("ACT", "GTO", "PRE", "STA", "OBJ", "FLT", "SPE", "FOR"))
            held = f"{self.held.width_m:.4f}" if self.held is not None else "none"
            return (
                f"robotiq {self.model.name} POS={self.pos:.2f} opening_m={self.model.opening_at(self.pos):.5f} "
                f"{vals} held={held} parts={len(self.parts)} requests={self.requests}"
            )


class RobotiqServer:
    """Serves `gripper` on host:port (127.x.y.z only). port 0 binds a free port (`port` tells which)."""

    def __init__(self, gripper: SimulatedRobotiq, host: str = "127.0.0.1", port: int = ROBOTIQ_PORT) -> None:
        if not is_ipv4_loopback_literal(host):
            raise InputError(f"the Robotiq socket binds only loopback addresses (127.x.y.z), got {host!r}")
        self.gripper = gripper
        self.host = host
        self.port = port
        self._stop = threading.Event()
        self._listener: socket.socket | None = None
        self._socks: list[socket.socket] = []
        self._threads: list[threading.Thread] = []
        self._lock = threading.Lock()

    def start(self) -> RobotiqServer:
        lst = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        lst.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            lst.bind((self.host, self.port))
        except OSError as exc:
            lst.close()
            raise NormposError(
                f"cannot bind the Robotiq socket {self.host}:{self.port} ({exc}): another gripper server listens "
                "there; use another port (--robotiq-port) or address"
            ) from exc
        lst.listen(4)
        self.port = lst.getsockname()[1]
        self._listener = lst
        self._spawn(self._accept_loop)
        log.info("Robotiq %s socket on %s:%d", self.gripper.model.name, self.host, self.port)
        return self

    def _spawn(self, target: Callable[..., None], *args: object) -> None:
        th = threading.Thread(target=target, args=args, daemon=True)
        th.start()
        self._threads.append(th)

    def stop(self) -> None:
        self._stop.set()
        if self._listener is not None:
            with contextlib.suppress(OSError):
                self._listener.close()
        with self._lock:
            socks, self._socks = self._socks, []
        for sock in socks:
            with contextlib.suppress(OSError):
                sock.shutdown(socket.SHUT_RDWR)
            with contextlib.suppress(OSError):
                sock.close()
        deadline = time.monotonic() + 2.0  # s for all threads together (daemons: a stuck one dies with the process)
        for th in self._threads:
            th.join(timeout=max(0.0, deadline - time.monotonic()))

    def __enter__(self) -> RobotiqServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _accept_loop(self) -> None:
        assert self._listener is not None
        self._listener.settimeout(0.2)
        while not self._stop.is_set():
            try:
                sock, _ = self._listener.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            with self._lock:
                self._socks.append(sock)
            self._spawn(self._serve, sock)

    def _serve(self, sock: socket.socket) -> None:
        buf = b""
        try:
            while not self._stop.is_set():
                data = sock.recv(4096)
                if not data:
                    return
                buf += data
                if len(buf) > 65536:
                    log.warning("Robotiq socket: request without a line end over 64 KiB; closing the connection")
                    return
                replies = []
                while b"\n" in buf:
                    raw, buf = buf.split(b"\n", 1)
                    replies.append(self.gripper.handle_line(raw.decode("ascii", errors="replace").strip()))
                if replies:
                    sock.sendall("".join(replies).encode("ascii"))
        except OSError:
            pass
        finally:
            with self._lock:
                if sock in self._socks:
                    self._socks.remove(sock)
            with contextlib.suppress(OSError):
                sock.close()
