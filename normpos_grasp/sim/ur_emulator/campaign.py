"""Fault and interrupt campaign: the CLI (or the library) in a subprocess against the loopback controller.

Each case starts `normpos-grasp execute ... --execute` (or, for moveL, a short library script: the CLI has no
linear moves) as a subprocess against an `EmulatorProcess`, waits until the arm moves, injects the fault (SIGINT,
SIGTERM, SIGKILL of the controller, a dropped link, a stall) and measures on the controller: when the first stop
command arrived (`emu since`), when the arm came to rest, how many motion commands arrived after the stop, and, for
the signal cases, the joint state over RTDE (ur_rtde's RTDEReceiveInterface, 500 Hz) for 0.6 s after the fault.
Refusal cases (model mismatch, bad gripper output) check that nothing moved and no motion command arrived.
All times are time.monotonic(), which on Linux is one clock for every process.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from normpos_grasp.errors import DriverTimeout, InputError

from .process import EmulatorProcess, dashboard_request

CONTROLLERS = ("emulator", "reference")

CASES = (
    "sigint_movej",
    "sigterm_movej",
    "sigint_movel",
    "sigterm_movel",
    "sigint_stream",
    "sigterm_stream",
    "sigint_run",
    "sigterm_run",
    "model_mismatch",
    "bad_io",
    "protective_stop",
    "estop",
    "killed_controller",
    "link_drop",
    "short_stall",
    "stall",
)
EXPECTED_EXIT = {"sigint": 130, "sigterm": 143}
SHORT_STALL_S = 2.0  # s: a stall that ends by itself (the driver must have stopped the arm long before)
PERMANENT_STALL_S = 1e6  # s: never ends while the CLI runs (cleared by the campaign afterwards)
RUN_CELL = "ur5e_bin_parallel"  # the packaged cell `normpos-grasp run` picks in (a ur5e at the emulator's home)
_RUN_ARGS = ("run", "--cell", RUN_CELL, "--source", "synthetic:3", "--execute", "--max-picks", "1")
# s after the arm starts moving that a signal is sent: at cruise speed. moveJ of 1.2 rad at 0.8 rad/s, 1.2 rad/s^2
# (execute's defaults) cruises from 0.67 s to 1.5 s; moveL of 0.2 m at 0.2 m/s, 1 m/s^2 from 0.2 s to 1.0 s; the
# 3 s cosine stream of 1.2 rad runs at 0.5-0.63 rad/s from 1.0 s to 2.0 s.
_INTO_MOVE_S = {"movej": 0.9, "movel": 0.5, "stream": 1.2, "run": 0.4}

_MOVEL_SCRIPT = """
import sys
import numpy as np
from normpos_grasp.errors import NormposError
from normpos_grasp.execution import SafetyLimits, SupervisedRtdeDriver, exit_code, stop_signals
host, dz = sys.argv[1], float(sys.argv[2])
drv = SupervisedRtdeDriver(host, SafetyLimits.for_model("ur5e"))
with stop_signals():
    try:
        try:
            drv.connect()
            pose = drv.state().base_from_tcp.copy()
            pose[2, 3] += dz
            print("MOVEL", flush=True)
            drv.move_linear(pose, 0.2, 1.0)
        finally:
            drv.disconnect()
    except KeyboardInterrupt as exc:
        print(f"normpos-grasp moveL: interrupted, arm stopped (exit {exit_code(exc)})", file=sys.stderr, flush=True)
        sys.exit(exit_code(exc))
    except NormposError as exc:  # a fault the driver raised (and stopped the arm for): one line, as the CLI does
        print(f"normpos-grasp moveL: {exc}", file=sys.stderr, flush=True)
        sys.exit(2)
"""


@dataclass
class CaseResult:
    """One run of one case. Times in s after the fault; None where not measured (e.g. the controller was killed)."""

    case: str
    exit_code: int | None  # None: the process hung and was killed by the campaign
    expected_exit: int
    aborted: bool  # the process died of a signal (SIGABRT, SIGSEGV, ...)
    hung: bool
    stderr: list[str] = field(default_factory=list)
    exit_after_fault_s: float | None = None
    stop_cmd_s: float | None = None  # first stop command at the controller
    stop_cmd: str = "-"
    rest_s: float | None = None  # the controller's arm at rest
    rtde_still_s: float | None = None  # RTDE trace: first sample with |qd| < 1e-3 rad/s that stays still
    moved_after_fault_rad: float | None = None
    drift_after_still_rad: float | None = None
    motion_after_stop: int | None = None
    motion_cmds_in_run: int | None = None
    send_gap_s: float = 0.0  # time.monotonic() before -> after sending the signal (campaign process scheduling)
    emu_overruns: int = 0  # emulator control cycles late by > 20 ms during the run (a starved loop)
    # the arm must rest within this of the fault (a stall is seen only after DriverOptions.stale_state_s)
    stop_budget_s: float = 0.1
    controller: str = "emulator"

    @property
    def error_lines(self) -> list[str]:
        return [line for line in self.stderr if line.startswith("normpos-grasp")]

    @property
    def traceback(self) -> bool:
        return any("Traceback" in line for line in self.stderr)

    def problems(self) -> list[str]:
        """What falls short: wrong exit code, abort, hang, traceback, several error lines, motion after the stop,
        or an arm not at rest within `stop_budget_s` of the fault (measured on the controller)."""
        stop_budget_s = self.stop_budget_s
        out = []
        if self.hung:
            out.append("hang")
        if self.aborted:
            out.append(f"abort (signal {-(self.exit_code or 0)})")
        if self.exit_code != self.expected_exit:
            out.append(f"exit {self.exit_code} (expected {self.expected_exit})")
        if self.traceback:  # its last line names the exception
            out.append(f"traceback ({self.stderr[-1].strip()[:160]})")
        if len(self.error_lines) != 1:
            out.append(f"{len(self.error_lines)} error lines")
        if self.motion_after_stop:
            out.append(f"{self.motion_after_stop} motion commands after the stop")
        if self.motion_cmds_in_run:
            out.append(f"{self.motion_cmds_in_run} motion commands (expected none)")
        if self.rest_s is not None and self.rest_s > stop_budget_s + self.send_gap_s:
            out.append(f"at rest {self.rest_s * 1000:.0f} ms after the fault")
        return out

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["problems"] = self.problems()
        return d


class _Trace:
    """Joint state over RTDE (ur_rtde RTDEReceiveInterface) in this process."""

    def __init__(self, host: str) -> None:
        import rtde_receive

        self.r = rtde_receive.RTDEReceiveInterface(host)

    def record(self, seconds: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        ts, qs, qds = [], [], []
        end = time.monotonic() + seconds
        last = None
        while time.monotonic() < end:
            stamp = self.r.getTimestamp()
            if stamp != last:
                last = stamp
                ts.append(time.monotonic())
                qs.append(self.r.getActualQ())
                qds.append(self.r.getActualQd())
            time.sleep(0.0005)
        return np.array(ts), np.array(qs), np.array(qds)

    def moving(self) -> bool:
        return float(np.max(np.abs(self.r.getActualQd()))) > 0.05

    def close(self) -> None:
        self.r.disconnect()


def _emu_state(host: str) -> dict[str, str]:
    # the harness's own query, not a measured figure: a loaded machine may take more than the usual 2 s to answer
    reply = dashboard_request(host, "emu state", timeout_s=10.0)
    return dict(part.split("=", 1) for part in reply.split()[2:] if "=" in part)


def _since(host: str, t: float) -> dict[str, str]:
    reply = dashboard_request(host, f"emu since {t:.6f}")
    return dict(part.split("=", 1) for part in reply.split()[2:] if "=" in part)


def _q(state: dict[str, str]) -> np.ndarray:
    return np.array([float(v) for v in state["q"].strip("[]").split(",")])


BARE_ARM_WORKSPACE = ("-2", "-2", "-2", "2", "2", "2")  # m, base frame: the campaign's arm stands in no cell


def write_plan(path: Path, robot: str, q0: np.ndarray, q1: np.ndarray, duration_s: float | None) -> Path:
    """A two-waypoint plan.json (start, end); with `duration_s`, a cosine-profile trajectory of samples every 10 ms."""
    plan: dict[str, Any] = {
        "status": "ok",
        "robot": robot,
        "world_from_base": np.eye(4).tolist(),
        "joint_waypoints": [{"name": "start", "q": q0.tolist()}, {"name": "end", "q": q1.tolist()}],
        "tool": {"flange_from_tcp": np.eye(4).tolist()},
    }
    if duration_s is not None:
        t = np.linspace(0.0, duration_s, int(round(duration_s / 0.01)) + 1)
        s = (1.0 - np.cos(np.pi * t / duration_s)) / 2.0
        q = q0 + np.outer(s, q1 - q0)
        plan["trajectory"] = {"samples": [{"t": float(a), "q": b.tolist()} for a, b in zip(t, q, strict=True)]}
    path.write_text(json.dumps(plan))
    return path


class Campaign:
    """Runs cases against an emulator on `host` (restarted where a case kills it). Use as a context manager.

    controller: "emulator" (this package's loopback controller) or "reference" (normpos_grasp.sim.rtde_reference,
    written independently from the protocol notes). stale_state_s: the CLI driver's DriverOptions.stale_state_s (a
    stall is seen only after it). exit_timeout_s: a process still running this long after the fault counts as a
    hang (and is killed). rt_priority: SCHED_FIFO priority of the controller's 500 Hz loop (0: normal scheduling;
    on a loaded machine a starved loop makes the emulated servo catch up in jumps, see `emu_overruns`)."""

    def __init__(
        self,
        host: str,
        workdir: Path,
        model: str = "ur5e",
        exit_timeout_s: float = 45.0,
        stale_state_s: float = 0.15,
        rt_priority: int = 0,
        controller: str = "emulator",
    ) -> None:
        if controller not in CONTROLLERS:
            raise InputError(f"unknown controller {controller!r}; one of {', '.join(CONTROLLERS)}")
        self.controller = controller
        self.stale_state_s = stale_state_s
        self.rt_priority = rt_priority
        self.host = host
        self.workdir = Path(workdir)
        self.workdir.mkdir(parents=True, exist_ok=True)
        self.model = model
        self.exit_timeout_s = exit_timeout_s
        self.emu: Any = None  # EmulatorProcess or ReferenceControllerProcess (start, stop, emu, proc)
        self.runs = 0

    def __enter__(self) -> Campaign:
        self._ensure_emulator()
        return self

    def __exit__(self, *exc: object) -> None:
        if self.emu is not None:
            self.emu.stop()
            self.emu = None

    def _ensure_emulator(self) -> Any:
        if self.emu is None or self.emu.proc is None or self.emu.proc.poll() is not None:
            extra = ("--rt-priority", str(self.rt_priority)) if self.rt_priority > 0 else ()
            log_path = self.workdir / f"{self.controller}.log"
            if self.controller == "reference":
                from normpos_grasp.sim.rtde_reference import ReferenceControllerProcess

                self.emu = ReferenceControllerProcess(
                    self.host, self.model, ready_timeout_s=60.0, log_path=log_path, rt_priority=self.rt_priority
                ).start()
            else:
                self.emu = EmulatorProcess(
                    self.host, self.model, ready_timeout_s=60.0, log_path=log_path, extra_args=extra
                ).start()
            self.emu.emu("unlock_delay", "0.5")
        return self.emu

    # ------------------------------------------------------------------ helpers
    def _cli(self, *args: str) -> list[str]:
        if args and args[0] == "execute":  # bare-arm plans (no cell): the box execute requires, 2 m about the base
            args = (*args, "--workspace", *BARE_ARM_WORKSPACE)
        return [sys.executable, "-m", "normpos_grasp.cli.main", *args]

    def _start(self, cmd: list[str]) -> subprocess.Popen[str]:
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)

    def _finish(self, proc: subprocess.Popen[str], t_fault: float | None, result: CaseResult) -> None:
        try:
            _out, err = proc.communicate(timeout=self.exit_timeout_s)
        except subprocess.TimeoutExpired:
            result.hung = True
            proc.kill()
            _out, err = proc.communicate(timeout=10.0)
        t_end = time.monotonic()
        result.exit_code = None if result.hung else proc.returncode
        result.aborted = bool(not result.hung and proc.returncode is not None and proc.returncode < 0)
        result.stderr = [line for line in (err or "").splitlines() if line.strip()]
        if t_fault is not None:
            result.exit_after_fault_s = t_end - t_fault

    def _wait_moving(self, proc: subprocess.Popen[str], timeout_s: float = 120.0, hold_s: float = 0.0) -> None:
        """Return once the arm has moved without a pause for `hold_s` (a short move that ends before is skipped).
        The process is killed when it does not get there (a run left behind would drive the next case's arm).
        The timeout includes the CLI's start-up (imports, the client's child process): tens of s on a loaded
        machine."""
        try:
            self._wait_moving_or_raise(proc, timeout_s, hold_s)
        except DriverTimeout as exc:
            if proc.poll() is None:
                proc.kill()
            _out, err = proc.communicate(timeout=10.0)
            said = [line for line in (err or "").splitlines() if line.strip()][-3:]
            raise DriverTimeout(f"{exc}; its stderr: {' | '.join(said) or '(nothing)'}") from exc
        except BaseException:
            if proc.poll() is None:
                proc.kill()
            proc.communicate(timeout=10.0)
            raise

    def _wait_moving_or_raise(self, proc: subprocess.Popen[str], timeout_s: float, hold_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        since = None
        while time.monotonic() < deadline:
            if proc.poll() is not None:
                raise DriverTimeout(f"the process ended (exit {proc.returncode}) before the arm moved")
            if _emu_state(self.host)["moving"] == "True":
                since = time.monotonic() if since is None else since
                if time.monotonic() - since >= hold_s:
                    return
            else:
                since = None
            time.sleep(0.01)
        raise DriverTimeout(f"the arm did not start moving within {timeout_s} s")

    def _rest_q(self) -> np.ndarray:
        """The controller's joints once it is at rest and ready (protective stops unlocked, e-stops released and the
        arm powered on again)."""
        deadline = time.monotonic() + 10.0
        while time.monotonic() < deadline:
            st = _emu_state(self.host)
            if st["moving"] == "False":
                if st["safety_mode"] == "7":
                    dashboard_request(self.host, "emu release_estop")
                    continue
                if st["safety_mode"] != "1":
                    dashboard_request(self.host, "unlock protective stop")
                    time.sleep(0.1)
                    continue
                if st["robot_mode"] != "7":
                    dashboard_request(self.host, "power on")
                    dashboard_request(self.host, "brake release")
                    time.sleep(0.05)
                    continue
                return _q(st)
            time.sleep(0.05)
        raise DriverTimeout("the emulated arm did not come to rest")

    def _controller_stop(self, t_fault: float, result: CaseResult) -> None:
        info = _since(self.host, t_fault)
        stop_t, rest_t = float(info["stop_t"]), float(info["rest_t"])
        result.stop_cmd = info["stop"]
        result.stop_cmd_s = stop_t - t_fault if stop_t > 0 else None
        result.rest_s = rest_t - t_fault if rest_t > 0 else None
        result.motion_after_stop = int(info["motion_after_stop"])

    # ------------------------------------------------------------------ cases
    def run(self, case: str) -> CaseResult:
        if case not in CASES:
            raise InputError(f"unknown case {case!r}; cases: {', '.join(CASES)}")
        self.runs += 1
        self._ensure_emulator()
        if case.startswith(("sigint", "sigterm")):
            return self._signal_case(case)
        if case in ("model_mismatch", "bad_io"):
            return self._refusal_case(case)
        return self._fault_case(case)

    def _plan_for(self, kind: str, robot: str | None = None) -> tuple[Path, np.ndarray]:
        q0 = self._rest_q()
        q1 = q0.copy()
        q1[0] += -1.2 if q0[0] > 0.0 else 1.2  # toward zero and across it: stays inside the joint limits
        path = self.workdir / f"plan_{self.runs}.json"
        return write_plan(path, robot or self.model, q0, q1, 3.0 if kind == "stream" else None), q0

    def _signal_case(self, case: str) -> CaseResult:
        sig_name, kind = case.split("_", 1)
        sig = signal.SIGINT if sig_name == "sigint" else signal.SIGTERM
        result = CaseResult(case, None, EXPECTED_EXIT[sig_name], False, False, controller=self.controller)
        overruns0 = int(_emu_state(self.host)["overruns"])
        trace = _Trace(self.host)
        try:
            if kind == "movel":
                q0 = self._rest_q()
                dz = -0.2 if _tcp_z(self.host) > 0.45 else 0.2
                proc = self._start([sys.executable, "-c", _MOVEL_SCRIPT, self.host, str(dz)])
                assert proc.stdout is not None
                for line in proc.stdout:
                    if line.startswith("MOVEL"):
                        break
            elif kind == "run":  # the cell loop: synthetic bin, ground-truth masks, one pick
                q0 = self._rest_q()
                proc = self._start(self._cli(*_RUN_ARGS, "--robot", self.host))
            else:
                plan, q0 = self._plan_for(kind)
                proc = self._start(self._cli("execute", str(plan), "--robot", self.host, "--execute"))
            if kind == "run":  # a loop motion (the move home, then the pick's moves) running for 0.4 s
                self._wait_moving(proc, hold_s=_INTO_MOVE_S[kind])
            else:
                self._wait_moving(proc)
                time.sleep(_INTO_MOVE_S[kind])  # at cruise speed
            q_fault = np.asarray(trace.r.getActualQ())
            t_fault = time.monotonic()
            proc.send_signal(sig)
            result.send_gap_s = time.monotonic() - t_fault  # a loaded machine may deschedule this process here
            ts, qs, qds = trace.record(0.6)
            self._finish(proc, t_fault, result)
        finally:
            trace.close()
        self._controller_stop(t_fault, result)
        result.emu_overruns = int(_emu_state(self.host)["overruns"]) - overruns0
        if len(ts):
            result.moved_after_fault_rad = float(np.max(np.abs(qs - q_fault)))
            speed = np.max(np.abs(qds), axis=1)
            for i in range(len(ts)):
                if speed[i] < 1e-3 and float(np.max(np.abs(qs[i:] - qs[i]))) < 1e-4:
                    result.rtde_still_s = float(ts[i] - t_fault)
                    result.drift_after_still_rad = float(np.max(np.abs(qs[i:] - qs[i])))
                    break
        _ = q0
        return result

    def _refusal_case(self, case: str) -> CaseResult:
        result = CaseResult(case, None, 2, False, False, controller=self.controller)
        before = int(_emu_state(self.host)["motion_cmds"])
        q_before = self._rest_q()
        if case == "model_mismatch":
            other = "ur10e" if self.model != "ur10e" else "ur5e"
            plan, _ = self._plan_for("movej", robot=other)
            cmd = self._cli("execute", str(plan), "--robot", self.host, "--execute")
        else:
            plan, _ = self._plan_for("movej")
            cmd = self._cli("execute", str(plan), "--robot", self.host, "--execute", "--close-output", "99")
        t0 = time.monotonic()
        proc = self._start(cmd)
        self._finish(proc, t0, result)
        time.sleep(0.1)
        after = _emu_state(self.host)
        result.motion_cmds_in_run = int(after["motion_cmds"]) - before
        result.moved_after_fault_rad = float(np.max(np.abs(_q(after) - q_before)))
        return result

    def _fault_case(self, case: str) -> CaseResult:
        result = CaseResult(case, None, 2, False, False, controller=self.controller)
        if case in ("stall", "short_stall"):  # seen only after the stall watchdog (stale_state_s)
            result.stop_budget_s = self.stale_state_s + 0.1
        plan, _ = self._plan_for("movej")
        proc = self._start(self._cli("execute", str(plan), "--robot", self.host, "--execute"))
        try:
            self._wait_moving(proc)
        except BaseException:  # the case cannot start: end its client so the next case starts from a quiet arm
            proc.kill()
            proc.communicate(timeout=10.0)
            raise
        time.sleep(0.3)
        emu = self._ensure_emulator()
        t_fault = time.monotonic()
        if case == "killed_controller":
            assert emu.proc is not None
            emu.proc.kill()
            emu.proc.wait(timeout=10.0)
            emu.stop()
            self.emu = None
        elif case == "link_drop":
            emu.emu("drop")
        elif case == "protective_stop":
            emu.emu("protective_stop")
        elif case == "estop":
            emu.emu("estop")
        else:
            emu.emu("stall", str(SHORT_STALL_S if case == "short_stall" else PERMANENT_STALL_S))
        self._finish(proc, t_fault, result)
        if case == "stall":
            emu.emu("stall", "0")
        if case != "killed_controller":
            self._controller_stop(t_fault, result)
            after = _emu_state(self.host)
            result.moved_after_fault_rad = None if after["moving"] == "True" else result.moved_after_fault_rad
        return result


def _tcp_z(host: str) -> float:
    from normpos_grasp.kinematics.ur_params import dh_forward_kinematics, ur_params

    q = _q(_emu_state(host))
    return float(dh_forward_kinematics(ur_params("ur5e"), q)[2, 3])


def summarize(results: list[CaseResult]) -> dict[str, dict[str, Any]]:
    """Per case: runs, aborts, hangs, exit codes, stop figures (median and worst, ms), commands after the stop."""
    out: dict[str, dict[str, Any]] = {}
    for case in dict.fromkeys(r.case for r in results):
        rs = [r for r in results if r.case == case]

        def ms(values: list[float | None]) -> str:
            v = [x * 1000 for x in values if x is not None]
            return "-" if not v else f"{np.median(v):.0f}/{max(v):.0f}"

        out[case] = {
            "runs": len(rs),
            "aborts": sum(r.aborted for r in rs),
            "hangs": sum(r.hung for r in rs),
            "exit_codes": sorted({r.exit_code for r in rs}, key=lambda c: -1 if c is None else c),
            "expected_exit": rs[0].expected_exit,
            "stop_cmd_ms": ms([r.stop_cmd_s for r in rs]),
            "rest_ms": ms([r.rest_s for r in rs]),
            "rtde_still_ms": ms([r.rtde_still_s for r in rs]),
            "exit_ms": ms([r.exit_after_fault_s for r in rs]),
            "moved_rad_max": max((r.moved_after_fault_rad or 0.0) for r in rs),
            "cmds_after_stop": sum(r.motion_after_stop or 0 for r in rs) + sum(r.motion_cmds_in_run or 0 for r in rs),
            "one_error_line": sum(len(r.error_lines) == 1 for r in rs),
            "tracebacks": sum(r.traceback for r in rs),
            "problem_runs": sum(bool(r.problems()) for r in rs),
        }
    return out
