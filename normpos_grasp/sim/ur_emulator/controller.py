"""The emulated UR controller's state: safety, program, RTDE registers, digital I/O and ur_rtde's script protocol.

`EmulatedController.tick()` runs one 2 ms controller cycle: the uploaded ur_rtde control script's main loop
(register handshake, command dispatch), the watchdog, and one arm step. Network servers (server.py) feed it RTDE
input packets, dashboard lines and script text under `lock`; it never touches sockets itself.
"""

from __future__ import annotations

import logging
import re
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from normpos_grasp.geometry.transforms import pose_from_ur, pose_to_ur
from normpos_grasp.kinematics.ur_params import URParams

from .arm import (
    PROTECTIVE_STOP_DECEL,
    IKSolver,
    JointMove,
    LinearMove,
    PathMove,
    ServoControl,
    SimulatedArm,
    SpeedControl,
)

log = logging.getLogger(__name__)

UR_RTDE_BANNER = 'textmsg("RTDE Control Script Loaded ('
KNOWN_BANNER_DATES = ("14.02.2024-12:23",)  # ur_rtde 1.6.5
_PATH_LINE = re.compile(
    r"^\s*(movej|movel|movep)\((p?)\[([-+0-9.eE,\s]+)\],\s*a=([-+0-9.eE]+),\s*v=([-+0-9.eE]+),\s*r=([-+0-9.eE]+)\)\s*$",
    re.MULTILINE,
)
_OFFSET = re.compile(r"reg_offset_(?:float|int)\s*=\s*(?:#[^\n]*\n)?\s*(\d+)")

# robot_mode / safety_mode / runtime_state values (UR's RTDE guide)
ROBOT_MODE_POWER_OFF, ROBOT_MODE_IDLE, ROBOT_MODE_RUNNING = 3, 5, 7
SAFETY_NORMAL, SAFETY_PROTECTIVE_STOP, SAFETY_ROBOT_EMERGENCY_STOP = 1, 3, 7
RUNTIME_STOPPED, RUNTIME_PLAYING = 1, 2
SAFETY_BIT_PROTECTIVE, SAFETY_BIT_EMERGENCY = 2, 7

REALTIME_CMDS = frozenset({24, 11, 9, 10, 6, 25, 26, 27, 38, 58, 66, 67, 68, 69, 70, 71})
CMD_NAMES = {
    1: "moveJ",
    2: "moveJ_IK",
    3: "moveL",
    4: "moveL_FK",
    9: "speedJ",
    11: "servoJ",
    15: "speedStop",
    16: "servoStop",
    17: "setPayload",
    29: "setTcp",
    30: "getInverseKinematics",
    31: "triggerProtectiveStop",
    33: "stopL",
    34: "stopJ",
    35: "setWatchdog",
    43: "getForwardKinematics",
    44: "getForwardKinematics",
    45: "movePath",
    46: "getInverseKinematics",
    255: "stopScript",
}


@dataclass
class EmulatorOptions:
    """Settings of one emulated controller.

    model: UR model name ('ur5e', ...). host: loopback address to bind (127.0.0.x). period_s: control period (s).
    unlock_delay_s: a protective stop cannot be unlocked before this many seconds (UR: 5 s).
    q_home: initial joints (rad). control_version: (major, minor, bugfix, build) reported over RTDE.
    rt_priority: 0 = normal scheduling; 1-99 = SCHED_FIFO for the control loop thread (like a real controller;
    use on a loaded machine to keep the 2 ms period, if the process may). serial: the dashboard's
    `get serial number` answer. robotiq_model: the gripper behind the Robotiq URCap socket ('2F-85', '2F-140'; ''
    serves no such socket, as a controller without the URCap). robotiq_port: its TCP port (63352 on a controller).
    program_start_s: an uploaded script starts this long after it arrived (a controller loads it first; ur_rtde
    clears its stop command on the RTDE socket as it uploads the next script, and a script started at once could
    read the stale stop and end).
    """

    model: str = "ur5e"
    host: str = "127.0.0.1"
    period_s: float = 0.002
    unlock_delay_s: float = 5.0
    q_home: tuple[float, ...] = (0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0)
    control_version: tuple[int, int, int, int] = (5, 15, 0, 0)
    rt_priority: int = 0  # >0: run the 500 Hz loop under SCHED_FIFO at this priority (Linux, needs CAP_SYS_NICE)
    serial: str = "20265500001"
    robotiq_model: str = "2F-85"
    robotiq_port: int = 63352
    program_start_s: float = 0.1


@dataclass
class Program:
    """The script running on the emulated controller (only ur_rtde's control script is accepted)."""

    kind: str
    banner: str
    path: list[tuple[str, np.ndarray, float, float]] = field(default_factory=list)
    reg_offset: int = 0
    keep_running: bool = True
    executing_cmd: bool = False
    waiting_done: bool = False  # a synchronous move is running; signal done when it ends
    async_op_id: int = 0
    async_running: bool = False
    async_wr_count: int = 0
    async_state: tuple[bool, int] = (False, 0)


class EmulatedController:
    """State of one emulated UR controller. All public methods take `lock`; callers must not hold it."""

    def __init__(self, params: URParams, options: EmulatorOptions, ik: IKSolver | None = None) -> None:
        self.params = params
        self.options = options
        self.lock = threading.RLock()
        self.arm = SimulatedArm(params, np.array(options.q_home, dtype=np.float64), options.period_s, ik)
        self.t0 = time.monotonic()
        self.timestamp = 0.0
        self.robot_mode = ROBOT_MODE_RUNNING
        self.safety_mode = SAFETY_NORMAL
        self.safety_bits = 0
        self.program: Program | None = None
        self.pending: tuple[float, Program] | None = None  # an uploaded script and when it starts (time.monotonic())
        self.in_int = [0] * 48
        self.in_double = [0.0] * 48
        self.out_int = [0] * 48
        self.out_double = [0.0] * 48
        self.digital_out = 0  # standard bits 0-7, configurable 8-15, tool 16-17
        self.digital_in = 0
        self.analog_in = [0.0, 0.0]  # standard analog inputs 0 and 1 (V or A, as the input's domain is set)
        self.speed_slider = 1.0
        self.payload = 0.0
        self.protective_stop_time = -1e9
        self.watchdog_period = 0.0
        self.watchdog_last = time.monotonic()
        self.refused_scripts: list[str] = []
        self.events: list[str] = []
        self.stall_until = 0.0
        self.commands_seen = 0
        # measurement of stops, times in time.monotonic() (CLOCK_MONOTONIC is system-wide on Linux: comparable
        # across processes): stop commands (stopJ/stopL/servoStop/speedStop, program stops), rests, motion commands
        self.stop_events: deque[tuple[float, str]] = deque(maxlen=10_000)
        self.rest_times: deque[float] = deque(maxlen=10_000)
        self.motion_times: deque[float] = deque(maxlen=200_000)
        self.motion_cmds = 0  # motion commands received (moveJ/moveL/path/speedJ/servoJ)
        self._was_moving = False

    # ------------------------------------------------------------------ state read by the RTDE publisher
    @property
    def runtime_state(self) -> int:
        return RUNTIME_PLAYING if self.program is not None else RUNTIME_STOPPED

    @property
    def robot_status_bits(self) -> int:
        power = 1 if self.robot_mode >= ROBOT_MODE_IDLE else 0
        return power | (2 if self.program is not None else 0)

    def snapshot(self) -> dict[str, Any]:
        """Values of the output variables this emulator models (vectors as tuples)."""
        arm = self.arm
        q = tuple(arm.q.tolist())
        qd = tuple(arm.qd.tolist())
        tcp = tuple(arm.tcp_pose_vector().tolist())
        return {
            "timestamp": self.timestamp,
            "actual_q": q,
            "target_q": q,
            "actual_qd": qd,
            "target_qd": qd,
            "actual_TCP_pose": tcp,
            "target_TCP_pose": tcp,
            "robot_mode": self.robot_mode,
            "safety_mode": self.safety_mode,
            "safety_status": self.safety_mode,
            "runtime_state": self.runtime_state,
            "robot_status_bits": self.robot_status_bits,
            "safety_status_bits": self.safety_bits,
            "actual_digital_output_bits": self.digital_out,
            "actual_digital_input_bits": self.digital_in,
            "standard_analog_input0": self.analog_in[0],
            "standard_analog_input1": self.analog_in[1],
            "speed_scaling": self.speed_slider,
            "target_speed_fraction": self.speed_slider,
            "payload": self.payload,
            "joint_mode": (253,) * 6 if self.robot_mode == ROBOT_MODE_RUNNING else (236,) * 6,
            "joint_temperatures": (30.0,) * 6,
            "actual_main_voltage": 48.0,
            "actual_robot_voltage": 48.0,
            "actual_joint_voltage": (48.0,) * 6,
            "output_int": self.out_int,
            "output_double": self.out_double,
            "input_int": self.in_int,
            "input_double": self.in_double,
        }

    # ------------------------------------------------------------------ RTDE input
    def apply_inputs(self, names: list[str], values: list[Any]) -> None:
        """Apply one RTDE input data package (variable names and decoded values)."""
        with self.lock:
            masks: dict[str, int] = {}
            for name, value in zip(names, values, strict=True):
                if name.startswith("input_int_register_"):
                    idx = int(name.rsplit("_", 1)[1])
                    self.in_int[idx] = int(value)
                    if self.program is not None and idx == self.program.reg_offset:
                        self.watchdog_last = time.monotonic()
                elif name.startswith("input_double_register_"):
                    self.in_double[int(name.rsplit("_", 1)[1])] = float(value)
                elif name.endswith("_mask"):
                    masks[name[: -len("_mask")]] = int(value)
            values_by_name = dict(zip(names, values, strict=True))
            for group, shift in (
                ("standard_digital_output", 0),
                ("configurable_digital_output", 8),
                ("tool_digital_output", 16),
            ):
                mask = masks.get(group, 0)
                if mask and group in values_by_name:
                    level = int(values_by_name[group])
                    self.digital_out = (self.digital_out & ~(mask << shift)) | ((level & mask) << shift)
            if masks.get("speed_slider", 0) & 1 and "speed_slider_fraction" in values_by_name:
                self.speed_slider = min(1.0, max(0.0, float(values_by_name["speed_slider_fraction"])))

    # ------------------------------------------------------------------ script port
    def load_script(self, text: str) -> None:
        """Run an uploaded script: ur_rtde's control script (recognised by its banner) or a loud refusal.

        The text is parsed before the controller lock is taken, so the 500 Hz loop keeps running meanwhile."""
        log.debug("script received (%d chars):\n%s", len(text), text)
        if UR_RTDE_BANNER not in text:
            first = text.strip().splitlines()[0] if text.strip() else "<empty>"
            msg = f"refused unknown script (no ur_rtde banner), first line: {first[:120]!r}"
            log.error(msg)
            with self.lock:
                self.refused_scripts.append(first[:120])
                self.events.append(msg)
            return
        banner = text.split(UR_RTDE_BANNER, 1)[1].split(")", 1)[0]
        if banner not in KNOWN_BANNER_DATES:
            log.warning("ur_rtde control script with unknown banner date %r; expected %s", banner, KNOWN_BANNER_DATES)
        path = [
            (m.group(1), np.array([float(x) for x in m.group(3).split(",")]), float(m.group(5)), float(m.group(4)))
            for m in _PATH_LINE.finditer(text)
        ]
        if any(kind == "movep" for kind, _, _, _ in path):
            log.error("movep in a path is not emulated; it runs as movel")
        offsets = {int(x) for x in _OFFSET.findall(text)}
        offset = max(offsets) if offsets else 0
        with self.lock:
            if self.safety_mode != SAFETY_NORMAL or self.robot_mode != ROBOT_MODE_RUNNING:
                msg = (
                    f"script not started: robot not ready (robot_mode {self.robot_mode}, "
                    f"safety_mode {self.safety_mode}); unlock / power on first"
                )
                log.error(msg)
                self.events.append(msg)
                return
            if self.program is not None:
                self.stop_program("replaced by an uploaded script")
            self.pending = (
                time.monotonic() + self.options.program_start_s,
                Program("rtde_control", banner, path, offset),
            )
        log.info("ur_rtde control script received (banner %s, %d path entries)", banner, len(path))

    def _start_pending(self) -> None:
        """Start the uploaded script once it has loaded (in the control cycle, under the lock)."""
        assert self.pending is not None
        prog, self.pending = self.pending[1], None
        if self.safety_mode != SAFETY_NORMAL or self.robot_mode != ROBOT_MODE_RUNNING:
            self.events.append("script not started: the robot stopped while it loaded")
            return
        self.program = prog
        self.watchdog_period = 0.0
        self.out_int[prog.reg_offset + 0] = 1  # signal_ready()
        self.events.append(f"control script started (banner {prog.banner}, {len(prog.path)} path entries)")

    # ------------------------------------------------------------------ faults and dashboard actions
    def _stop_arrived(self, name: str) -> None:
        self.stop_events.append((time.monotonic(), name))

    def stops_since(self, t: float) -> dict[str, Any]:
        """For a fault at time.monotonic() `t`: the first stop command after it, the first rest after that stop,
        and the motion commands received after that stop (and after `t`)."""
        with self.lock:
            stop = next(((ts, n) for ts, n in self.stop_events if ts >= t), None)
            t_stop = stop[0] if stop is not None else float("inf")
            rest = next((ts for ts in self.rest_times if ts >= t_stop), None)
            return {
                "stop_t": -1.0 if stop is None else stop[0],
                "stop": "-" if stop is None else stop[1].split(" ")[0],
                "rest_t": -1.0 if rest is None else rest,
                "motion_after_stop": sum(1 for ts in self.motion_times if ts > t_stop),
                "motion_after_t": sum(1 for ts in self.motion_times if ts > t),
                "moving": self.arm.moving,
            }

    def stop_program(self, reason: str) -> None:
        with self.lock:
            self._stop_arrived(f"program stop ({reason})")
            if self.program is not None:
                log.info("program stopped: %s", reason)
                self.events.append(f"program stopped: {reason}")
            self.program, self.pending = None, None
            if self.arm.moving:
                self.arm.stop(PROTECTIVE_STOP_DECEL)

    def protective_stop(self, reason: str = "injected") -> None:
        with self.lock:
            self.safety_mode = SAFETY_PROTECTIVE_STOP
            self.safety_bits |= 1 << SAFETY_BIT_PROTECTIVE
            self.protective_stop_time = time.monotonic()
            self._stop_arrived("protectiveStop")
            self.arm.stop(PROTECTIVE_STOP_DECEL)
            self.program, self.pending = None, None
            self.events.append(f"protective stop: {reason}")
            log.warning("protective stop: %s", reason)

    def emergency_stop(self) -> None:
        with self.lock:
            self.safety_mode = SAFETY_ROBOT_EMERGENCY_STOP
            self.safety_bits |= 1 << SAFETY_BIT_EMERGENCY
            self._stop_arrived("emergencyStop")
            self.arm.stop(PROTECTIVE_STOP_DECEL * 2)
            self.program, self.pending = None, None
            self.events.append("emergency stop")
            log.warning("emergency stop")

    def release_emergency_stop(self) -> None:
        """The e-stop button is released: safety back to normal, arm powered off until `power on` + `brake release`."""
        with self.lock:
            if self.safety_mode == SAFETY_ROBOT_EMERGENCY_STOP:
                self.safety_mode = SAFETY_NORMAL
                self.safety_bits &= ~(1 << SAFETY_BIT_EMERGENCY)
                self.robot_mode = ROBOT_MODE_POWER_OFF

    def unlock_protective_stop(self) -> tuple[bool, str]:
        with self.lock:
            if self.safety_mode != SAFETY_PROTECTIVE_STOP:
                return True, "Protective stop releasing"
            waited = time.monotonic() - self.protective_stop_time
            if waited < self.options.unlock_delay_s:
                return False, (
                    f"Cannot unlock protective stop until {self.options.unlock_delay_s:g}s after occurrence. "
                    "Always inspect cause of protective stop before unlocking"
                )
            self.safety_mode = SAFETY_NORMAL
            self.safety_bits &= ~(1 << SAFETY_BIT_PROTECTIVE)
            self.arm.fault = ""
            self.events.append("protective stop unlocked")
            return True, "Protective stop releasing"

    # ------------------------------------------------------------------ the control cycle
    def tick(self) -> None:
        """One control period: timestamp, watchdog, the control script's loop, one arm step."""
        with self.lock:
            self.timestamp = time.monotonic() - self.t0
            if self.pending is not None and time.monotonic() >= self.pending[0]:
                self._start_pending()
            prog = self.program
            if (
                prog is not None
                and self.watchdog_period > 0.0
                and time.monotonic() - self.watchdog_last > self.watchdog_period
            ):
                self.events.append("watchdog expired: program stopped")
                log.warning("RTDE watchdog expired (no input for %.3f s): stopping program", self.watchdog_period)
                self.stop_program("watchdog")
                prog = None
            if prog is not None:
                self._script_cycle(prog)
            self.arm.dt = self.options.period_s * self.speed_slider
            self.arm.step()
            self.arm.dt = self.options.period_s
            if self.arm.fault and self.safety_mode == SAFETY_NORMAL:
                self.protective_stop(f"motion fault: {self.arm.fault}")
            moving = self.arm.moving
            if self._was_moving and not moving:
                self.rest_times.append(time.monotonic())
            self._was_moving = moving
            prog = self.program
            if prog is not None:
                if prog.waiting_done and not self.arm.moving:
                    prog.waiting_done = False
                    self.out_int[prog.reg_offset] = 2  # signal_done_with_cmd()
                running = prog.async_running and self.arm.moving
                if prog.async_running and not self.arm.moving:
                    prog.async_running = False
                progress = getattr(self.arm.motion, "progress", 0) if self.arm.motion is not None else 0
                state = (running, progress)
                if state != prog.async_state:
                    prog.async_state = state
                    prog.async_wr_count = (prog.async_wr_count + 1) & 0xFF
                reg = (prog.async_op_id << 24) | (prog.async_wr_count << 16)
                if running:  # bit 15 running, bits 0-14 progress (path waypoint); as the control script writes it
                    reg |= 0x8000 | min(progress, 0x7FFF)
                self.out_int[prog.reg_offset + 2] = reg

    def _script_cycle(self, prog: Program) -> None:
        off = prog.reg_offset
        if prog.waiting_done:
            return  # the script is blocked in a synchronous move
        cmd = self.in_int[off]
        if cmd in REALTIME_CMDS:
            self._process(prog, cmd)
            self.out_int[off] = 1
        elif cmd == 0:
            prog.executing_cmd = False
            self.out_int[off] = 1
        elif not prog.executing_cmd:
            prog.executing_cmd = True
            self.commands_seen += 1
            self._process(prog, cmd)

    def _d(self, prog: Program, start: int, n: int) -> np.ndarray:
        off = prog.reg_offset
        return np.array(self.in_double[off + start : off + start + n], dtype=np.float64)

    def _process(self, prog: Program, cmd: int) -> None:
        off = prog.reg_offset
        is_async = self.in_int[off + 1] == 1
        done = True
        if cmd in (1, 2, 3, 4, 9, 11, 45):
            self.motion_cmds += 1
            self.motion_times.append(time.monotonic())
        elif cmd in (15, 16, 31, 33, 34):
            self._stop_arrived(CMD_NAMES[cmd])
        if cmd in (1, 2, 3, 4):
            target = self._d(prog, 0, 6)
            speed, accel = self.in_double[off + 6], self.in_double[off + 7]
            try:
                if cmd == 1:
                    motion: Any = JointMove(self.arm.q_cmd, target, speed, accel)
                elif cmd == 2:
                    motion = JointMove(self.arm.q_cmd, self.arm.solve_tcp(pose_from_ur(target)), speed, accel)
                elif cmd == 3:
                    motion = LinearMove(self.arm, pose_from_ur(target), speed, accel)
                else:
                    motion = LinearMove(self.arm, self.arm.base_from_tcp(target), speed, accel)
            except Exception as exc:
                log.error("%s refused: %s", CMD_NAMES[cmd], exc)
                self.events.append(f"{CMD_NAMES[cmd]} refused: {exc}")
                self.protective_stop(f"{CMD_NAMES[cmd]} target unreachable: {exc}")
                return
            self.arm.start(motion)
            prog.async_op_id = (prog.async_op_id + 1) & 0x7F
            prog.async_running = is_async
            done = is_async
        elif cmd == 45:
            if not prog.path:
                log.error("movePath without an injected path in the running script")
            self.arm.start(PathMove(prog.path))
            prog.async_op_id = (prog.async_op_id + 1) & 0x7F
            prog.async_running = is_async
            done = is_async
        elif cmd == 9:
            qd = self._d(prog, 0, 6)
            accel, duration = self.in_double[off + 6], self.in_double[off + 7]
            motion = self.arm.motion
            if isinstance(motion, SpeedControl):
                motion.qd_target, motion.accel = qd, max(accel, 1e-6)
            else:
                self.arm.start(SpeedControl(self.arm.qd, qd, accel, 0.0))
            _ = duration
        elif cmd == 11:
            q = self._d(prog, 0, 6)
            servo_time = self.in_double[off + 8]
            motion = self.arm.motion
            if isinstance(motion, ServoControl):
                motion.retarget(q, servo_time)
            else:
                self.arm.start(ServoControl(q, servo_time))
        elif cmd in (15, 16):
            # speedStop(a): joint deceleration, rad/s^2; servoStop(a): tool deceleration, m/s^2 (ur_rtde default 10),
            # turned into a joint deceleration as for stopL
            a = self.in_double[off + 0]
            log.debug("%s registers: %s", CMD_NAMES[cmd], self.in_double[off : off + 8])
            decel = (a if a > 0 else 10.0) if cmd == 15 else max((a if a > 0 else 10.0) * 2.0, 1.0)
            if isinstance(self.arm.motion, (SpeedControl, ServoControl)):
                self.arm.stop(decel)
        elif cmd in (33, 34):
            decel = self.in_double[off + 0] or (10.0 if cmd == 33 else 2.0)
            if cmd == 33:
                decel = max(decel * 2.0, 1.0)  # tool deceleration (m/s^2) -> a joint deceleration, conservatively
            if self.arm.moving:
                self.arm.stop(decel)
            done = is_async or not self.arm.moving
        elif cmd == 17:
            self.payload = self.in_double[off + 0]
        elif cmd == 29:
            self.arm.tcp_offset = pose_from_ur(self._d(prog, 0, 6))
        elif cmd == 31:
            self.protective_stop("triggerProtectiveStop() from the client")
            return
        elif cmd == 35:
            freq = self.in_double[off + 0]
            self.watchdog_period = 1.0 / freq if freq > 0 else 0.0
            self.watchdog_last = time.monotonic()
        elif cmd in (43, 44):
            q = self.arm.q if cmd == 43 else self._d(prog, 0, 6)
            self.out_double[off : off + 6] = pose_to_ur(self.arm.base_from_tcp(q)).tolist()
        elif cmd in (30, 46):
            try:
                q = self.arm.solve_tcp(pose_from_ur(self._d(prog, 0, 6)))
                self.out_double[off : off + 6] = q.tolist()
            except Exception as exc:
                log.error("getInverseKinematics failed: %s", exc)
        elif cmd == 255:
            prog.keep_running = False
            self.stop_program("stopScript (command 255)")
            return
        elif cmd not in REALTIME_CMDS:
            log.error("command %d is not emulated; nothing moved (signalling done so the client does not hang)", cmd)
            self.events.append(f"command {cmd} not emulated")
        if cmd in REALTIME_CMDS:
            return
        if done:
            self.out_int[off] = 2
        else:
            prog.waiting_done = True
