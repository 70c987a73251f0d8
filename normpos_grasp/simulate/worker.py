"""Start-up of scene worker processes, kept free of heavy imports: it runs before the worker imports the simulation.

A spawned worker unpickles its initializer before any task; with this module it arms the parent-death signal
within milliseconds of its start instead of after the seconds that importing the pipeline takes.
"""

from __future__ import annotations

import contextlib
import os
import signal


def init_worker(parent_pid: int) -> None:  # pragma: no cover - runs in the worker processes
    """Ctrl-C is the parent's to handle (it ends the workers); SIGTERM ends the worker; the worker gets SIGKILL
    when the parent dies (Linux PR_SET_PDEATHSIG), or exits now when the parent is already gone."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    with contextlib.suppress(OSError, AttributeError):
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG = 1
    if os.getppid() != parent_pid:  # the parent died before the death signal was armed
        os._exit(1)
