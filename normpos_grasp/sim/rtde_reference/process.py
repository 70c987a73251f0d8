"""`ReferenceControllerProcess`: the reference controller in a child process, ready when its dashboard answers."""

from __future__ import annotations

import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

from normpos_grasp.errors import ConnectionLost, InputError
from normpos_grasp.hosts import is_ipv4_loopback_literal

from .controller import DASHBOARD_PORT


def ask(host: str, line: str, timeout_s: float = 2.0) -> str:
    """One dashboard line and its reply (after the welcome line)."""
    with socket.create_connection((host, DASHBOARD_PORT), timeout=timeout_s) as sock:
        f = sock.makefile("rwb", buffering=0)
        f.readline()
        f.write(line.encode() + b"\n")
        return f.readline().decode(errors="replace").strip()


class ReferenceControllerProcess:
    """Start (`start()`), query (`emu(...)`, `dashboard(...)`) and stop (`stop()`) a reference controller.

    host: 127.x.y.z. model: UR model. ready_timeout_s: how long start() waits for the dashboard. log_path: its log.
    rt_priority: SCHED_FIFO priority of its cycle (0: none)."""

    def __init__(
        self,
        host: str,
        model: str = "ur5e",
        ready_timeout_s: float = 30.0,
        log_path: str | Path | None = None,
        rt_priority: int = 0,
    ) -> None:
        if not is_ipv4_loopback_literal(host):
            raise InputError(f"the reference controller binds loopback addresses 127.x.y.z only, got {host!r}")
        self.host, self.model = host, model
        self.ready_timeout_s = ready_timeout_s
        self.log_path = Path(log_path) if log_path else None
        self.rt_priority = rt_priority
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self) -> ReferenceControllerProcess:
        cmd = [sys.executable, "-m", "normpos_grasp.sim.rtde_reference", "--host", self.host, "--model", self.model]
        if self.rt_priority > 0:
            cmd += ["--rt-priority", str(self.rt_priority)]
        out = open(self.log_path, "ab") if self.log_path else subprocess.DEVNULL  # noqa: SIM115 - kept by the child
        try:
            self.proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=out, stderr=out)
        finally:
            if self.log_path:
                out.close()  # type: ignore[union-attr]
        deadline = time.monotonic() + self.ready_timeout_s
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                code = self.proc.returncode
                raise ConnectionLost(f"the reference controller exited with {code} (log {self.log_path})")
            try:
                if f"pid={self.proc.pid} " in ask(self.host, "emu state", 0.5):
                    return self
            except OSError:
                pass
            time.sleep(0.05)
        self.stop()
        raise ConnectionLost(f"the reference controller on {self.host} did not answer within {self.ready_timeout_s} s")

    def emu(self, *verb: str) -> str:
        return ask(self.host, "emu " + " ".join(verb))

    def dashboard(self, line: str) -> str:
        return ask(self.host, line)

    def stop(self, timeout_s: float = 10.0) -> None:
        proc, self.proc = self.proc, None
        if proc is None or proc.poll() is not None:
            return
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=5.0)

    def __enter__(self) -> ReferenceControllerProcess:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
