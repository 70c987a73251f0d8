"""Operator stops for processes that drive an arm: SIGINT and SIGTERM become exceptions in the main thread.

Inside `stop_signals()` (the package's one signal helper, `normpos_grasp.interrupts.signals_raise`, with repeated
signals logged as warnings) SIGINT raises `Interrupted` (a KeyboardInterrupt) and SIGTERM raises `Terminated` (a
`TerminationRequested`) at the point the main thread is executing, so a motion call in progress is left through its
exception path, which stops the arm (`GuardedDriver` issues stopJ, see `DriverOptions.halt_decel_for`) before the
caller disconnects. Only the first signal raises; later ones are ignored, so a repeated Ctrl-C cannot cut the stop
short. Exit codes (`exit_code`): 130 for SIGINT, 143 for SIGTERM (128 + signal number, as shells report).
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

from normpos_grasp.interrupts import EXIT_SIGINT, EXIT_SIGTERM, exit_code, signal_name, signals_raise

__all__ = ["EXIT_SIGINT", "EXIT_SIGTERM", "exit_code", "signal_name", "stop_signals"]


@contextlib.contextmanager
def stop_signals() -> Iterator[list[int]]:
    """While active, SIGINT/SIGTERM raise (once) in the main thread; yields the list of signals received."""
    with signals_raise(warn_repeats=True) as received:
        yield received
