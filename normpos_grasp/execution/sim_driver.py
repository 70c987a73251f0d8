"""`SimDriver`: the arm driver on an in-process simulated arm, with the RtdeDriver's timing behaviour.

A background thread steps `SimulatedArm` (the loopback controller's arm model) every `period_s` of wall time
divided by `time_scale` (1.0 = real time, like a robot). Faults can be injected (`inject_*`) to exercise the
same guarded code paths as on a real controller; no network is involved.
"""

from __future__ import annotations

import threading
import time

import numpy as np

from normpos_grasp.errors import ConnectionLost
from normpos_grasp.kinematics.ur_params import ur_params
from normpos_grasp.sim.ur_emulator.arm import (
    PROTECTIVE_STOP_DECEL,
    IKSolver,
    JointMove,
    LinearMove,
    PathMove,
    ServoControl,
    SimulatedArm,
)
from normpos_grasp.sim.ur_emulator.server import load_ik
from normpos_grasp.typing import ArrayLike, FloatArray

from .driver import ArmState, DriverOptions, GripperIO, GuardedDriver
from .safety import SafetyLimits

DEFAULT_HOME = (0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0)


class SimDriver(GuardedDriver):
    """Simulated arm driver. q_home: initial joints (rad). time_scale: simulated seconds per wall second.

    unlock_delay_s: a protective stop cannot be unlocked earlier (UR: 5 s). ik: IK solver for linear moves
    (default: normpos_grasp.kinematics when available).
    """

    def __init__(
        self,
        limits: SafetyLimits,
        gripper: GripperIO | None = None,
        options: DriverOptions | None = None,
        q_home: ArrayLike = DEFAULT_HOME,
        time_scale: float = 1.0,
        period_s: float = 0.002,
        unlock_delay_s: float = 5.0,
        ik: IKSolver | None = None,
    ) -> None:
        super().__init__(limits, gripper, options)
        self.time_scale = time_scale
        self.period_s = period_s
        self.unlock_delay_s = unlock_delay_s
        self.arm = SimulatedArm(
            ur_params(limits.model),
            np.asarray(q_home, dtype=np.float64),
            period_s,
            ik if ik is not None else load_ik(limits.model),
        )
        self.arm.tcp_offset = limits.flange_from_tcp
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._stop_evt = threading.Event()
        self._connected = False
        self._link_up = True
        self._safety_mode = 1
        self._robot_mode = 7
        self._program = False
        self._pstop_time = -1e9
        self._digital_out = 0
        self._digital_in = 0
        self._sim_time = 0.0
        self._last_tick = time.monotonic()

    # ------------------------------------------------------------------ the simulation thread
    def _run(self) -> None:
        wall_period = self.period_s / self.time_scale
        next_t = time.monotonic()
        while not self._stop_evt.is_set():
            next_t += wall_period
            delay = next_t - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            elif delay < -0.05:
                next_t = time.monotonic()
            with self._lock:
                self.arm.step()
                self._sim_time += self.period_s
                if self.arm.fault and self._safety_mode == 1:
                    self._enter_pstop()
                if self._link_up:
                    self._last_tick = time.monotonic()

    def _enter_pstop(self) -> None:
        self._safety_mode = 3
        self._pstop_time = time.monotonic()
        self._program = False
        self.arm.stop(PROTECTIVE_STOP_DECEL)

    # ------------------------------------------------------------------ fault injection
    def inject_protective_stop(self) -> None:
        with self._lock:
            self._enter_pstop()

    def inject_emergency_stop(self) -> None:
        with self._lock:
            self._safety_mode = 7
            self._program = False
            self.arm.stop(2 * PROTECTIVE_STOP_DECEL)

    def release_emergency_stop(self) -> None:
        with self._lock:
            if self._safety_mode == 7:
                self._safety_mode = 1

    def unlock_protective_stop(self) -> bool:
        """Unlock like the dashboard: refused (False) within `unlock_delay_s` of the stop."""
        with self._lock:
            if self._safety_mode != 3:
                return True
            if time.monotonic() - self._pstop_time < self.unlock_delay_s:
                return False
            self._safety_mode = 1
            self.arm.fault = ""
            return True

    def inject_link_loss(self) -> None:
        """The state stream stops (the program keeps running, as on a real controller)."""
        with self._lock:
            self._link_up = False

    def restore_link(self) -> None:
        with self._lock:
            self._link_up = True

    def set_digital_input(self, bit: int, level: bool) -> None:
        with self._lock:
            self._digital_in = (self._digital_in | (1 << bit)) if level else (self._digital_in & ~(1 << bit))

    # ------------------------------------------------------------------ backend
    def _backend_connect(self) -> None:
        if not self._link_up:
            raise ConnectionLost("simulated link is down; call restore_link() first")
        if self._thread is None:
            self._stop_evt.clear()
            self._thread = threading.Thread(target=self._run, daemon=True)
            self._thread.start()
        with self._lock:
            if self._safety_mode == 1:
                self._program = True
        self._connected = True
        deadline = time.monotonic() + self.options.connect_timeout_s
        while time.monotonic() - self._last_tick > self.options.stale_state_s:
            if time.monotonic() > deadline:
                raise ConnectionLost("simulation thread does not tick")
            time.sleep(0.001)

    def _backend_disconnect(self) -> None:
        self._connected = False

    def shutdown(self) -> None:
        """Stop the simulation thread."""
        self._connected = False
        self._stop_evt.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None

    def _backend_connected(self) -> bool:
        return self._connected and self._link_up

    def _backend_state(self) -> ArmState:
        if not self._connected:
            raise ConnectionLost("SimDriver not connected; call connect()")
        with self._lock:
            arm = self.arm
            return ArmState(
                q=arm.q.copy(),
                qd=arm.qd.copy(),
                base_from_tcp=arm.base_from_tcp(),
                timestamp=self._sim_time,
                robot_mode=self._robot_mode,
                safety_mode=self._safety_mode,
                safety_status_bits=(4 if self._safety_mode == 3 else 0) | (128 if self._safety_mode == 7 else 0),
                runtime_state=2 if self._program else 1,
                program_running=self._program,
                digital_out=self._digital_out,
                digital_in=self._digital_in,
                received_at=self._last_tick,
            )

    def _backend_move_path(self, waypoints: FloatArray, speed: float, accel: float) -> None:
        with self._lock:
            if len(waypoints) == 1:
                self.arm.start(JointMove(self.arm.q_cmd, waypoints[0], speed, accel))
            else:
                self.arm.start(PathMove([("movej", w, speed, accel) for w in waypoints]))

    def _backend_move_linear(self, poses: FloatArray, speed: float, accel: float) -> None:
        with self._lock:
            if len(poses) == 1:
                self.arm.start(LinearMove(self.arm, poses[0], speed, accel))
            else:
                from normpos_grasp.geometry.transforms import pose_to_ur

                self.arm.start(PathMove([("movel", pose_to_ur(p), speed, accel) for p in poses]))

    def _backend_busy(self) -> bool:
        with self._lock:
            return self.arm.moving

    def _backend_servo_begin(self) -> None:
        pass

    def _backend_servo(self, q: FloatArray, period_s: float) -> None:
        with self._lock:
            motion = self.arm.motion
            if isinstance(motion, ServoControl):
                motion.retarget(q, period_s)
            else:
                self.arm.start(ServoControl(q, period_s))

    def _backend_servo_end(self) -> None:
        with self._lock:
            if isinstance(self.arm.motion, ServoControl):
                self.arm.stop(self.options.stop_decel)

    def _backend_stop(self, decel: float) -> None:
        """Decelerate and wait until the arm rests (as ur_rtde's stopJ(a, asynchronous=False)), at most 5 s."""
        with self._lock:
            if self.arm.moving:
                self.arm.stop(decel)
        deadline = time.monotonic() + 5.0
        while time.monotonic() < deadline:
            with self._lock:
                if not self.arm.moving:
                    return
            time.sleep(0.002)

    def _backend_protective_stop(self) -> None:
        with self._lock:
            self._enter_pstop()

    def _backend_link_lost(self) -> None:
        # the simulated controller is reachable by the same path; a real one would get a dashboard stop
        with self._lock:
            self._program = False
            if self.arm.moving:
                self.arm.stop(PROTECTIVE_STOP_DECEL)

    def _backend_set_output(self, index: int, level: bool, tool: bool) -> None:
        bit = index + (16 if tool else 0)
        with self._lock:
            self._digital_out = (self._digital_out | (1 << bit)) if level else (self._digital_out & ~(1 << bit))

    def _backend_reset_faults(self) -> None:
        with self._lock:
            self._program = self._safety_mode == 1
