"""SIGINT and SIGTERM as exceptions in the main thread, for every long-running command (standard library only).

One helper for the commands that drive an arm (`execute`, `run`: the exception leaves a motion call through its
exception path, which stops the arm before the client disconnects) and for the long batch runs (`simulate`,
`synth`: finished work is kept and the run can be resumed). Inside `signals_raise()` the first SIGINT raises
`Interrupted` and the first SIGTERM raises `Terminated` (an `Interrupted` and a `TerminationRequested`); both are
KeyboardInterrupts, so a bare `except Exception` never swallows them. Later signals are logged and ignored, so a
repeated Ctrl-C cannot cut the stop or the clean-up short. Exit codes: 128 + signal number, 130 for SIGINT and
143 for SIGTERM, as shells report them (`exit_code`).

Kept free of heavy imports: a spawned worker imports this before any task (see `init_worker`).
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import threading
from collections.abc import Iterator
from types import FrameType

from normpos_grasp.errors import TerminationRequested

log = logging.getLogger(__name__)

EXIT_SIGINT = 128 + int(signal.SIGINT)  # 130
EXIT_SIGTERM = 128 + int(signal.SIGTERM)  # 143


class Interrupted(KeyboardInterrupt):
    """SIGINT or SIGTERM arrived. signum: the signal; finished / total: the units of work (scenes) finished and in
    all, where the raiser knows them."""

    def __init__(self, signum: int, finished: int = 0, total: int = 0) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = int(signum)
        self.finished = finished
        self.total = total

    @property
    def exit_code(self) -> int:
        """128 + signal number (130 for SIGINT, 143 for SIGTERM)."""
        return 128 + self.signum


class Terminated(Interrupted, TerminationRequested):
    """SIGTERM arrived (a process supervisor's stop): an `Interrupted` that is also a `TerminationRequested`."""

    def __init__(self, signum: int = int(signal.SIGTERM), finished: int = 0, total: int = 0) -> None:
        super().__init__(signum, finished, total)


def interrupted(signum: int, finished: int = 0, total: int = 0) -> Interrupted:
    """The exception for `signum`: `Terminated` for SIGTERM, else `Interrupted`."""
    cls = Terminated if signum == signal.SIGTERM else Interrupted
    return cls(signum, finished, total)


def exit_code(exc: KeyboardInterrupt) -> int:
    """130 for SIGINT / Ctrl-C (a plain KeyboardInterrupt too), 143 for SIGTERM."""
    if isinstance(exc, Interrupted):
        return exc.exit_code
    return EXIT_SIGTERM if isinstance(exc, TerminationRequested) else EXIT_SIGINT


def signal_name(exc: KeyboardInterrupt) -> str:
    """'SIGTERM' or 'SIGINT' for an interrupt raised by `signals_raise` (or a plain KeyboardInterrupt)."""
    return "SIGTERM" if exit_code(exc) == EXIT_SIGTERM else "SIGINT"


@contextlib.contextmanager
def signals_raise(warn_repeats: bool = False) -> Iterator[list[int]]:
    """While the block runs (main thread only), the first SIGINT / SIGTERM raises `Interrupted` / `Terminated` in
    the main thread; later ones are ignored (logged as a warning with `warn_repeats`, else at debug level). Yields
    the list of signals received; the previous handlers are restored on exit. Outside the main thread it does
    nothing (Python delivers signals to the main thread only)."""
    received: list[int] = []
    if threading.current_thread() is not threading.main_thread():
        yield received
        return

    def handler(signum: int, _frame: FrameType | None) -> None:
        received.append(signum)
        if len(received) > 1:  # a second signal must not cut the stop or clean-up of the first one short
            level = logging.WARNING if warn_repeats else logging.DEBUG
            log.log(level, "signal %d ignored: the stop for signal %d is in progress", signum, received[0])
            return
        if _critical.depth > 0:  # raised when the critical section ends (see `uninterrupted`)
            _critical.pending = signum
            return
        raise interrupted(signum)

    saved = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    for s in saved:
        signal.signal(s, handler)
    try:
        yield received
    finally:
        for s, previous in saved.items():
            signal.signal(s, previous)


class _Critical:
    depth = 0
    pending: int | None = None


_critical = _Critical()


@contextlib.contextmanager
def uninterrupted() -> Iterator[None]:
    """Inside `signals_raise`, hold the exception of a signal that arrives in the block until the block ends: for
    a few lines that must not be cut in two (writing or reading one message on a pipe: an exception between its
    header and its body would leave the stream out of step). Main thread only; nests."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    _critical.depth += 1
    try:
        yield
    finally:
        _critical.depth -= 1
        if _critical.depth == 0 and _critical.pending is not None:
            signum, _critical.pending = _critical.pending, None
            raise interrupted(signum)


@contextlib.contextmanager
def signals_ignored() -> Iterator[None]:
    """Ignore SIGINT and SIGTERM in the block (main thread only): clean-up that must not be cut short."""
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
    """Start-up hook of a worker process: Ctrl-C is the parent's to handle (it ends the workers); SIGTERM ends the
    worker (both signals were blocked until here, see `signals_deferred`); the worker gets SIGKILL when the parent
    dies (Linux PR_SET_PDEATHSIG), or exits now when the parent is already gone."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    if hasattr(signal, "pthread_sigmask"):  # the parent spawns workers with both blocked
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT, signal.SIGTERM})
    with contextlib.suppress(OSError, AttributeError):
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG = 1
    if os.getppid() != parent_pid:  # the parent died before the death signal was armed
        os._exit(1)
