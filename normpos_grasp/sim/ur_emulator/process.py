"""Run the loopback UR controller as a subprocess: start, wait until it serves, stop cleanly.

ur_rtde's Python constructors hold the GIL while they wait for data, so the emulator must not share a process
with the client. `EmulatorProcess` starts `python -m normpos_grasp.cli.main emulate-ur ...`, waits for its
dashboard to answer, and offers the `emu` fault-injection verbs over the dashboard port.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

from normpos_grasp.errors import ConnectionLost, DriverTimeout, InputError
from normpos_grasp.hosts import is_ipv4_loopback_literal

from .server import DASHBOARD_PORT

log = logging.getLogger(__name__)


def dashboard_request(host: str, line: str, timeout_s: float = 2.0, port: int = DASHBOARD_PORT) -> str:
    """Send one dashboard line to `host` and return the reply line (welcome line skipped)."""
    with socket.create_connection((host, port), timeout=timeout_s) as sock:
        f = sock.makefile("rwb", buffering=0)
        f.readline()
        f.write(line.encode() + b"\n")
        reply = f.readline()
        if not reply:
            raise ConnectionLost(f"dashboard at {host}:{port} closed without answering {line!r}")
        return reply.decode().strip()


def _die_with_parent() -> None:  # pragma: no cover - runs in the child between fork and exec
    """Linux: the emulator gets SIGTERM when the process that started it dies (no orphaned controllers)."""
    try:
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG = 1
    except OSError:
        pass


class EmulatorProcess:
    """A loopback UR controller in its own process. Use as a context manager.

    host: 127.0.0.x address (ports are fixed, so one emulator per address). model: UR model name.
    ready_timeout_s: how long to wait for the servers to answer. log_path: file for the emulator's log
    (default: inherited stderr). verbose: 0 warnings, 1 info, 2 debug (logs every uploaded script).
    """

    def __init__(
        self,
        host: str = "127.0.0.1",
        model: str = "ur5e",
        ready_timeout_s: float = 30.0,
        log_path: str | Path | None = None,
        extra_args: tuple[str, ...] = (),
        verbose: int = 1,
    ) -> None:
        if not is_ipv4_loopback_literal(host):
            raise InputError(f"the emulator binds only loopback addresses (127.x.y.z), got {host!r}")
        self.host = host
        self.model = model
        self.ready_timeout_s = ready_timeout_s
        self.log_path = Path(log_path) if log_path is not None else None
        self.extra_args = extra_args
        self.verbose = verbose
        self.proc: subprocess.Popen[bytes] | None = None
        self._log_file: object | None = None

    def start(self) -> EmulatorProcess:
        cmd = [
            sys.executable,
            "-m",
            "normpos_grasp.cli.main",
            *(["-v"] * self.verbose),
            "emulate-ur",
            "--model",
            self.model,
            "--host",
            self.host,
            *self.extra_args,
        ]
        out = open(self.log_path, "ab") if self.log_path is not None else None  # noqa: SIM115 - closed in stop()
        self._log_file = out
        env = dict(os.environ)
        self.proc = subprocess.Popen(
            cmd, stdout=out or subprocess.DEVNULL, stderr=out, env=env, preexec_fn=_die_with_parent
        )
        deadline = time.monotonic() + self.ready_timeout_s
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise ConnectionLost(
                    f"emulator exited with code {self.proc.returncode} before it was ready "
                    f"(command: {' '.join(cmd)}); see {self.log_path or 'its stderr'}"
                )
            try:
                reply = dashboard_request(self.host, "emu state", timeout_s=1.0)
            except OSError:
                time.sleep(0.1)
                continue
            if f"pid={self.proc.pid} " in reply:
                return self
            time.sleep(0.1)  # another process answers on this address: ours will fail to bind and exit
        self.stop()
        raise DriverTimeout(f"emulator on {self.host} not ready within {self.ready_timeout_s} s")

    def emu(self, *verb: str) -> str:
        """Send a fault-injection verb (`protective_stop`, `estop`, `drop`, `stall 3`, `state`, ...)."""
        return dashboard_request(self.host, "emu " + " ".join(verb))

    def dashboard(self, line: str) -> str:
        return dashboard_request(self.host, line)

    def stop(self, timeout_s: float = 10.0) -> None:
        proc = self.proc
        if proc is not None and proc.poll() is None:
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                log.warning("emulator on %s ignored SIGINT; killing it", self.host)
                proc.kill()
                proc.wait(timeout=timeout_s)
        self.proc = None
        if self._log_file is not None:
            with contextlib.suppress(OSError):
                self._log_file.close()  # type: ignore[attr-defined]
            self._log_file = None

    def __enter__(self) -> EmulatorProcess:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
