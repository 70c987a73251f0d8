"""The RTDE state trace of a replay bundle: a passive recorder in its own process, on its own RTDE connection.

`python -m normpos_grasp.replay.rtde_trace HOST PERIOD_S` connects ur_rtde's `RTDEReceiveInterface` to the
controller at HOST (output recipe at 2 / PERIOD_S Hz, at most 500) and prints one JSON line every PERIOD_S seconds:
monotonic_s (CLOCK_MONOTONIC, shared by every process of the machine), controller_time_s, q (rad), qd (rad/s),
tcp_xyz_m (base frame), robot_mode, safety_mode, safety_status_bits, runtime_state, program_running, digital_out,
digital_in. It never talks to the arm driver and sends nothing to the controller but the recipe, so it cannot slow
the driver's servo stream down (polling `driver.state()` from another thread shares the driver's lock and its
child process, and stalled the stream on a loaded machine). It ends when its stdin closes (the parent ended), on
SIGTERM, or after printing one `{"error": ...}` line when the controller cannot be reached.
"""

from __future__ import annotations

import contextlib
import json
import os
import select
import sys
import threading
import time
from typing import IO, Any


class RtdeTrace:
    """Runs the recorder process for `host` and collects its samples; `take()` hands over those since the last."""

    def __init__(self, host: str, period_s: float) -> None:
        import subprocess

        self.host = host
        self.t0 = time.monotonic()
        self.note = ""
        self._samples: list[dict[str, Any]] = []
        self._lock = threading.Lock()
        self._proc = subprocess.Popen(
            [sys.executable, "-m", "normpos_grasp.replay.rtde_trace", host, repr(float(period_s))],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
            start_new_session=True,  # Ctrl-C goes to the caller, which ends this process when it closes
        )
        self._reader = threading.Thread(target=self._read, args=(self._proc.stdout,), daemon=True, name="rtde-trace")
        self._reader.start()

    def _read(self, stream: IO[bytes] | None) -> None:
        if stream is None:
            return
        for line in stream:
            try:
                sample = json.loads(line)
            except ValueError:
                continue
            with self._lock:
                if "error" in sample:
                    self.note = f"RTDE trace: {sample['error']}"
                    continue
                sample["t_s"] = round(float(sample.pop("monotonic_s")) - self.t0, 4)
                self._samples.append(sample)

    def take(self) -> tuple[list[dict[str, Any]], str]:
        """(samples since the last call, note on a failure)."""
        with self._lock:
            samples, self._samples = self._samples, []
            return samples, self.note

    def close(self) -> None:
        """End the recorder process (idempotent)."""
        proc = self._proc
        if proc.poll() is None:
            if proc.stdin is not None:
                proc.stdin.close()
            try:
                proc.wait(timeout=2.0)
            except Exception:
                proc.kill()
                proc.wait(timeout=2.0)
        self._reader.join(timeout=2.0)


def _sample(r: Any) -> dict[str, Any]:
    status = int(r.getRobotStatus())
    return {
        "monotonic_s": time.monotonic(),
        "controller_time_s": float(r.getTimestamp()),
        "q": [float(v) for v in r.getActualQ()],
        "qd": [float(v) for v in r.getActualQd()],
        "tcp_xyz_m": [float(v) for v in list(r.getActualTCPPose())[:3]],
        "robot_mode": int(r.getRobotMode()),
        "safety_mode": int(r.getSafetyMode()),
        "safety_status_bits": int(r.getSafetyStatusBits()),
        "runtime_state": int(r.getRuntimeState()),
        "program_running": bool(status & 2),
        "digital_out": int(r.getActualDigitalOutputBits()),
        "digital_in": int(r.getActualDigitalInputBits()),
    }


def main(argv: list[str]) -> int:
    """Record `argv` = [HOST, PERIOD_S] until stdin closes; see the module docstring."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent decides when the trace ends
    host, period = argv[0], float(argv[1])
    out = sys.stdout
    try:
        import rtde_receive

        r = rtde_receive.RTDEReceiveInterface(host, min(500.0, 2.0 / period))
    except Exception as exc:  # any failure to connect ends the trace with its reason
        print(json.dumps({"error": f"cannot connect to {host}: {type(exc).__name__}: {exc}"}), file=out, flush=True)
        return 1
    try:
        while True:
            ready, _, _ = select.select([sys.stdin], [], [], period)
            if ready and not os.read(sys.stdin.fileno(), 4096):
                return 0  # the parent closed the pipe (or ended)
            try:
                print(json.dumps(_sample(r)), file=out, flush=True)
            except (RuntimeError, OSError, BrokenPipeError) as exc:
                print(json.dumps({"error": f"{type(exc).__name__}: {exc}"}), file=out, flush=True)
                return 1
    finally:
        with contextlib.suppress(RuntimeError):
            r.disconnect()


if __name__ == "__main__":  # pragma: no cover - the recorder process
    sys.exit(main(sys.argv[1:]))
