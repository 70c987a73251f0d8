"""Signals of long runs (`simulate`, `synth`): SIGINT and SIGTERM as an exception, and the start-up of worker
processes. Kept free of heavy imports: a spawned worker imports this module before any task, so it arms the
parent-death signal within milliseconds of its start instead of after the seconds that importing the pipeline
takes.
"""

from __future__ import annotations

import contextlib
import os
import signal
import threading
from collections.abc import Iterator
from types import FrameType


class Interrupted(KeyboardInterrupt):
    """SIGINT or SIGTERM arrived (see `signals_raise`). signum: the signal; finished / total: the units of work
    (scenes) finished and in all, where the raiser knows them."""

    def __init__(self, signum: int, finished: int = 0, total: int = 0) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = int(signum)
        self.finished = finished
        self.total = total

    @property
    def exit_code(self) -> int:
        """128 + signal number (130 for SIGINT, 143 for SIGTERM)."""
        return 128 + self.signum


@contextlib.contextmanager
def signals_raise() -> Iterator[None]:
    """While the block runs (main thread only), SIGINT and SIGTERM raise `Interrupted`; previous handlers are
    restored on exit."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    fired: list[int] = []

    def handler(signum: int, _frame: FrameType | None) -> None:
        if fired:  # a second signal must not cut the cleanup of the first one short
            return
        fired.append(signum)
        raise Interrupted(signum)

    saved = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    for s in saved:
        signal.signal(s, handler)
    try:
        yield
    finally:
        for s, previous in saved.items():
            signal.signal(s, previous)


@contextlib.contextmanager
def signals_ignored() -> Iterator[None]:
    """Ignore SIGINT and SIGTERM in the block (main thread only): cleanup that must not be cut short."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    saved = {s: signal.signal(s, signal.SIG_IGN) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for s, previous in saved.items():
            signal.signal(s, previous)


@contextlib.contextmanager
def signals_deferred() -> Iterator[None]:
    """Block SIGINT and SIGTERM in the block (delivered when it ends): workers spawned here start with both
    blocked (the mask survives fork and exec) until `init_worker` ignores Ctrl-C, so a terminal's Ctrl-C,
    which reaches the whole process group, never interrupts a worker's start-up, and no signal cuts the parent
    between starting a worker and recording it."""
    if threading.current_thread() is not threading.main_thread() or not hasattr(signal, "pthread_sigmask"):
        yield
        return
    old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, signal.SIGTERM})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


def init_worker(parent_pid: int) -> None:  # pragma: no cover - runs in the worker processes
    """Ctrl-C is the parent's to handle (it ends the workers); SIGTERM ends the worker (both signals were blocked
    until here, see `signals_deferred`); the worker gets SIGKILL when the parent dies (Linux
    PR_SET_PDEATHSIG), or exits now when the parent is already gone."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    if hasattr(signal, "pthread_sigmask"):  # the parent spawns workers with both blocked
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT, signal.SIGTERM})
    with contextlib.suppress(OSError, AttributeError):
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG = 1
    if os.getppid() != parent_pid:  # the parent died before the death signal was armed
        os._exit(1)
