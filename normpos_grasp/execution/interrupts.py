"""Operator stops for processes that drive an arm: SIGINT and SIGTERM become exceptions in the main thread.

Inside `stop_signals()`, SIGINT raises KeyboardInterrupt and SIGTERM raises `TerminationRequested` (a
KeyboardInterrupt) at the point the main thread is executing, so a motion call in progress is left through its
exception path, which stops the arm (`GuardedDriver` issues stopJ with `DriverOptions.halt_decel`) before the caller
disconnects. Only the first signal raises; later ones are logged and ignored, so a repeated Ctrl-C cannot cut the
stop short. Exit codes (`exit_code`): 130 for SIGINT, 143 for SIGTERM (128 + signal number, as shells report).
"""

from __future__ import annotations

import contextlib
import logging
import signal
import threading
from collections.abc import Iterator
from types import FrameType

from normpos_grasp.errors import TerminationRequested

log = logging.getLogger(__name__)

EXIT_SIGINT = 128 + int(signal.SIGINT)  # 130
EXIT_SIGTERM = 128 + int(signal.SIGTERM)  # 143


def exit_code(exc: KeyboardInterrupt) -> int:
    """130 for an interrupt (SIGINT, Ctrl-C), 143 for a termination request (SIGTERM)."""
    return EXIT_SIGTERM if isinstance(exc, TerminationRequested) else EXIT_SIGINT


def signal_name(exc: KeyboardInterrupt) -> str:
    return "SIGTERM" if isinstance(exc, TerminationRequested) else "SIGINT"


@contextlib.contextmanager
def stop_signals() -> Iterator[list[int]]:
    """While active, SIGINT/SIGTERM raise (once) in the main thread; yields the list of signals received.

    Outside the main thread it does nothing (Python delivers signals to the main thread only)."""
    received: list[int] = []
    if threading.current_thread() is not threading.main_thread():
        yield received
        return

    def handler(signum: int, frame: FrameType | None) -> None:
        received.append(signum)
        if len(received) > 1:
            log.warning("signal %d ignored: the stop for signal %d is in progress", signum, received[0])
            return
        if signum == signal.SIGTERM:
            raise TerminationRequested("SIGTERM")
        raise KeyboardInterrupt("SIGINT")

    old = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield received
    finally:
        for s, h in old.items():
            signal.signal(s, h)
