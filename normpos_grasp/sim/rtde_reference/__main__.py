"""`python -m normpos_grasp.sim.rtde_reference --host 127.0.0.9 --model ur5e`: serve until SIGINT/SIGTERM."""

from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
import threading

from normpos_grasp.errors import NormposError

from .controller import ReferenceController, Settings


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m normpos_grasp.sim.rtde_reference", description=__doc__)
    ap.add_argument("--host", default="127.0.0.1")
    ap.add_argument("--model", default="ur5e")
    ap.add_argument("--serial", default=Settings.serial)
    ap.add_argument("--unlock-delay", type=float, default=5.0, help="s before a protective stop may be unlocked")
    ap.add_argument("--rt-priority", type=int, default=0, help="SCHED_FIFO priority of the 500 Hz cycle (0: none)")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s reference %(levelname)s %(message)s")
    sys.setswitchinterval(0.0002)  # socket threads must not hold the 2 ms cycle off for Python's default 5 ms
    done = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: done.set())
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT, signal.SIGTERM})  # a mask inherited from the parent
    if args.rt_priority > 1:
        # every thread of this process (socket servers, script runner) real-time one step below the cycle, as on a
        # controller's own computer: a server thread holding a lock or the GIL must not be starved by the host's
        # other work and hold the 500 Hz cycle (and its state stream) off with it; threads inherit this policy
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(args.rt_priority - 1))
        except (OSError, AttributeError) as exc:
            logging.getLogger(__name__).warning("no real-time scheduling for the server threads (%s)", exc)
    try:
        ctl = ReferenceController(
            Settings(args.model, args.host, args.serial, args.unlock_delay, rt_priority=args.rt_priority)
        ).start()
    except NormposError as exc:
        sys.stderr.write(f"reference controller: {exc}\n")
        return 2
    done.wait()
    ctl.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
