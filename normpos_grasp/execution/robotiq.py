"""A client for Robotiq 2F-85 / 2F-140 grippers over the Robotiq Gripper URCap's socket (TCP 63352 on the controller).

Protocol source: Robotiq's socket interface of the Gripper URCap (dof.robotiq.com, "Control Robotiq gripper
mounted on UR robot via socket communication", discussions 1962 and 2420) and the register meanings of the
2F-85/2F-140 instruction manual (section 4, "Control": ACT, GTO, POS, SPE, FOR; status STA, OBJ, FLT, PRE).
Requests are ASCII lines: `SET <VAR> <int> [<VAR> <int> ...]` is answered `ack`, `GET <VAR>` is answered
`<VAR> <int>`. Positions run 0 (open) ... 255 (closed); a gripper's mechanical ends lie inside that range, so the
opening (m) maps linearly between the calibrated `open_counts` and `closed_counts`. OBJ: 0 moving, 1 / 2 stopped by
contact while opening / closing (an object is caught), 3 at the requested position (no object).

Every call is bounded in time: connecting, each reply (`reply_timeout_s`), activation and each motion; a missing
socket (no URCap, gripper not connected), a timeout, a dropped link or a fault code raise `GripperFault`.
"""

from __future__ import annotations

import logging
import socket
import time
from collections.abc import Callable
from dataclasses import dataclass

from normpos_grasp.cell.gripper_driver import RobotiqDriverSpec
from normpos_grasp.errors import GripperFault, InputError

log = logging.getLogger(__name__)

ROBOTIQ_PORT = 63352
STA_ACTIVE = 3
OBJ_MOVING, OBJ_CONTACT_OPENING, OBJ_CONTACT_CLOSING, OBJ_AT_POSITION = 0, 1, 2, 3
FAULTS = {  # gFLT codes, 2F-85/2F-140 manual section 4.4
    0x05: "action delayed: the (re)activation must complete first",
    0x07: "the activation bit must be set before an action",
    0x08: "maximum operating temperature exceeded",
    0x09: "no communication for at least 1 s",
    0x0A: "under the minimum operating voltage",
    0x0B: "automatic release in progress",
    0x0C: "internal fault",
    0x0D: "activation fault: check for interference",
    0x0E: "overcurrent",
    0x0F: "automatic release completed",
}


@dataclass(frozen=True)
class RobotiqStatus:
    """One status read: position (0-255), requested position echo, STA, OBJ and FLT registers; opening_m: m."""

    position: int
    requested: int
    sta: int
    obj: int
    flt: int
    opening_m: float

    @property
    def object_caught(self) -> bool:
        return self.obj in (OBJ_CONTACT_OPENING, OBJ_CONTACT_CLOSING)


class RobotiqSocket:
    """The raw URCap protocol on one TCP connection: `set(VAR=value, ...)` and `get(VAR)`."""

    def __init__(self, host: str, port: int = ROBOTIQ_PORT, reply_timeout_s: float = 1.0) -> None:
        self.host, self.port, self.reply_timeout_s = host, port, reply_timeout_s
        self._sock: socket.socket | None = None

    def connect(self, timeout_s: float = 2.0) -> None:
        try:
            self._sock = socket.create_connection((self.host, self.port), timeout=timeout_s)
        except ConnectionRefusedError as exc:
            raise GripperFault(
                f"no Robotiq gripper socket at {self.host}:{self.port} (connection refused): is the Robotiq Gripper "
                "URCap installed on the controller and the gripper connected? (gripper.driver.port sets the port)"
            ) from exc
        except OSError as exc:
            raise GripperFault(f"cannot reach the Robotiq gripper socket at {self.host}:{self.port}: {exc}") from exc
        self._sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._sock.settimeout(self.reply_timeout_s)

    @property
    def connected(self) -> bool:
        return self._sock is not None

    def close(self) -> None:
        if self._sock is not None:
            try:
                self._sock.close()
            finally:
                self._sock = None

    def _request(self, line: str, complete: Callable[[bytes], bool]) -> str:
        if self._sock is None:
            raise GripperFault(f"not connected to the Robotiq socket at {self.host}:{self.port}")
        deadline = time.monotonic() + self.reply_timeout_s
        buf = b""
        try:
            self._sock.sendall(line.encode("ascii") + b"\n")
            while not complete(buf):
                left = deadline - time.monotonic()
                if left <= 0:
                    raise TimeoutError
                self._sock.settimeout(left)
                data = self._sock.recv(1024)
                if not data:
                    raise GripperFault(f"the Robotiq socket at {self.host}:{self.port} closed during {line!r}")
                buf += data
        except TimeoutError as exc:
            self.close()
            raise GripperFault(
                f"the Robotiq socket at {self.host}:{self.port} did not answer {line!r} within "
                f"{self.reply_timeout_s} s (got {buf!r:.40})"
            ) from exc
        except OSError as exc:
            self.close()
            raise GripperFault(f"the Robotiq socket at {self.host}:{self.port} failed during {line!r}: {exc}") from exc
        return buf.decode("ascii", errors="replace").strip()

    def set(self, **values: int) -> None:
        """`SET VAR value ...` in one line (in the order given); GripperFault unless answered `ack`."""
        for var, value in values.items():
            if not (var.isalpha() and var.isupper() and len(var) == 3):
                raise InputError(f"Robotiq variable names are three capitals, got {var!r}")
            if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= 255:
                raise InputError(f"Robotiq {var} takes a whole number 0-255, got {value!r}")
        line = "SET " + " ".join(f"{k} {v}" for k, v in values.items())
        reply = self._request(line, lambda b: len(b.strip()) >= 3 or b"\n" in b or b.strip() == b"?")
        if reply != "ack":
            raise GripperFault(f"the Robotiq gripper refused {line!r} (answered {reply!r})", detail=reply)

    def get(self, var: str) -> int:
        """`GET VAR` -> its value; GripperFault on any other answer ('?': not readable in this state)."""
        reply = self._request(f"GET {var}", lambda b: b"\n" in b or b.strip() == b"?")
        words = reply.split()
        if len(words) != 2 or words[0] != var or not words[1].isdigit():
            raise GripperFault(f"the Robotiq gripper answered {reply!r} to 'GET {var}'", detail=reply)
        return int(words[1])


class RobotiqGripper:
    """A Robotiq 2F gripper driven over the URCap socket of the controller at `host`.

    spec: the cell's `gripper.driver` (model, stroke, port, speed, force, calibrated ends, timeouts). poll_s: status
    poll period while waiting, s. The gripper is the `ToolDriver` of execution: `connect()` activates it,
    `open(opening_m)` commands an opening (the plan's), `close()` closes on the part and `grip_detected()` reports
    whether the last close caught an object (OBJ 1/2) or closed on nothing (OBJ 3)."""

    detects_grip = True

    def __init__(self, host: str, spec: RobotiqDriverSpec | None = None, poll_s: float = 0.01) -> None:
        self.spec = spec or RobotiqDriverSpec()
        self.host = host
        self.poll_s = poll_s
        self.link = RobotiqSocket(host, self.spec.port)
        self.open_counts = self.spec.open_counts
        self.closed_counts = self.spec.closed_counts
        self.last: RobotiqStatus | None = None

    # ------------------------------------------------------------------ conversions
    def counts_for(self, opening_m: float) -> int:
        """Position register value (0-255) for an opening (m), between the calibrated ends."""
        if not 0.0 <= opening_m <= self.spec.stroke_m + 1e-6:
            raise InputError(
                f"opening {opening_m * 1000:.1f} mm is outside the {self.spec.model}'s stroke "
                f"0-{self.spec.stroke_m * 1000:.0f} mm"
            )
        span = self.closed_counts - self.open_counts
        return int(round(self.closed_counts - span * min(opening_m, self.spec.stroke_m) / self.spec.stroke_m))

    def opening_for(self, counts: int) -> float:
        """Opening (m) at a position register value."""
        span = self.closed_counts - self.open_counts
        frac = (self.closed_counts - counts) / span
        return float(min(max(frac, 0.0), 1.0) * self.spec.stroke_m)

    # ------------------------------------------------------------------ lifecycle
    def connect(self) -> None:
        """Open the socket and activate the gripper (and calibrate its ends if the spec asks); bounded in time."""
        if not self.link.connected:
            self.link.connect()
        self.activate()
        if self.spec.calibrate:
            self.calibrate()

    def disconnect(self) -> None:
        self.link.close()

    def activate(self) -> None:
        """Activate (ACT 1) unless active (STA 3); GripperFault after `activation_timeout_s` or on a fault."""
        if self.link.get("STA") == STA_ACTIVE and self.link.get("ACT") == 1:
            return
        self.link.set(ACT=0)  # a clean reset first (clears a latched fault), as Robotiq's activation sequence does
        self.link.set(ACT=1)
        deadline = time.monotonic() + self.spec.activation_timeout_s
        while True:
            sta, flt = self.link.get("STA"), self.link.get("FLT")
            if sta == STA_ACTIVE:
                log.info("Robotiq %s at %s:%d active", self.spec.model, self.host, self.spec.port)
                return
            if flt not in (0, 0x05):  # 0x05: activation still in progress
                raise GripperFault(f"the Robotiq gripper faulted while activating: {_fault_text(flt)}", detail=flt)
            if time.monotonic() > deadline:
                raise GripperFault(
                    f"the Robotiq gripper did not activate within {self.spec.activation_timeout_s} s (STA {sta}): "
                    "check its power and that nothing blocks the fingers",
                    detail=sta,
                )
            time.sleep(self.poll_s)

    def calibrate(self) -> None:
        """Measure the ends: open fully, read POS, close fully, read POS (the fingers must be empty)."""
        opened = self.goto(0)
        if opened.obj != OBJ_AT_POSITION:
            raise GripperFault("calibration: the fingers did not open freely (something blocks them)", detail=opened)
        closed = self.goto(255)
        if closed.obj != OBJ_AT_POSITION:
            raise GripperFault(
                "calibration: the fingers closed on an object; empty the gripper and calibrate again", detail=closed
            )
        if closed.position - opened.position < 50:
            raise GripperFault(
                f"calibration: the ends {opened.position} and {closed.position} are too close (< 50 counts)",
                detail=(opened, closed),
            )
        self.open_counts, self.closed_counts = opened.position, closed.position
        log.info("Robotiq calibrated: open %d, closed %d counts", self.open_counts, self.closed_counts)

    # ------------------------------------------------------------------ motion
    def status(self) -> RobotiqStatus:
        pos = self.link.get("POS")
        st = RobotiqStatus(
            pos,
            self.link.get("PRE"),
            self.link.get("STA"),
            self.link.get("OBJ"),
            self.link.get("FLT"),
            self.opening_for(pos),
        )
        self.last = st
        return st

    def goto(
        self, counts: int, speed: int | None = None, force: int | None = None, watch: Callable[[], None] | None = None
    ) -> RobotiqStatus:
        """Command a position (0-255) and wait until the fingers stop (OBJ != 0); `watch` runs every poll (the arm's
        state check). GripperFault on a fault code, a refused request or after `move_timeout_s`."""
        spe = self.spec.speed if speed is None else speed
        frc = self.spec.force if force is None else force
        self.link.set(POS=int(counts), SPE=int(spe), FOR=int(frc), GTO=1)
        deadline = time.monotonic() + self.spec.move_timeout_s
        acknowledged = False
        while True:
            if watch is not None:
                watch()
            if not acknowledged:
                acknowledged = self.link.get("PRE") == counts  # the gripper took the new request
            flt = self.link.get("FLT")
            if flt not in (0,):
                raise GripperFault(f"the Robotiq gripper reports a fault: {_fault_text(flt)}", detail=flt)
            if acknowledged and self.link.get("OBJ") != OBJ_MOVING:
                return self.status()
            if time.monotonic() > deadline:
                st = self.status()
                raise GripperFault(
                    f"the Robotiq gripper did not reach position {counts} within {self.spec.move_timeout_s} s "
                    f"(at {st.position}, OBJ {st.obj}, STA {st.sta})",
                    detail=st,
                )
            time.sleep(self.poll_s)

    def open(self, opening_m: float | None = None, watch: Callable[[], None] | None = None) -> RobotiqStatus:
        """Open to `opening_m` (m; None: fully)."""
        counts = self.open_counts if opening_m is None else self.counts_for(opening_m)
        st = self.goto(counts, watch=watch)
        log.info("Robotiq open to %d counts: at %d (%.1f mm), OBJ %d", counts, st.position, st.opening_m * 1e3, st.obj)
        return st

    def close(self, watch: Callable[[], None] | None = None) -> RobotiqStatus:
        """Close fully with the spec's speed and force; the fingers stop on a part (OBJ 2)."""
        st = self.goto(255, watch=watch)
        log.info("Robotiq close: at %d (%.1f mm), OBJ %d", st.position, st.opening_m * 1e3, st.obj)
        return st

    def grip_detected(self) -> bool:
        """Whether the last close caught an object (OBJ 1 or 2) rather than reaching its position (OBJ 3)."""
        st = self.status()
        return st.object_caught


def _fault_text(code: int) -> str:
    return f"FLT 0x{code:02X} ({FAULTS.get(code, 'unknown fault code')})"
