"""The child process of `SupervisedRtdeDriver`: an `RtdeDriver` (the ur_rtde client) serving its backend calls.

Started as `python -m normpos_grasp.execution.rtde_child FD` in a session of its own; FD is one end of a socket pair.
The first message is (host, limits, gripper, options, (servo_lookahead_s, servo_gain)); then each request
(seq, name, args) gets (seq, "ok", value) or (seq, "err", exception type name, message). SIGINT/SIGTERM are
ignored (the caller stops the arm through this process); if the caller vanishes, the arm is stopped and the process
ends. The log and ur_rtde's console output go to the file named by NORMPOS_GRASP_RTDE_LOG (default: nowhere).
"""

from __future__ import annotations

import logging
import os
import signal
import sys
import time
from multiprocessing.connection import Connection

from normpos_grasp.errors import DriverFault

from .driver import DriverOptions, GripperIO
from .rtde_driver import RtdeDriver
from .safety import SafetyLimits

log = logging.getLogger("normpos_grasp.execution.rtde_child")


def serve(
    conn: Connection,
    host: str,
    limits: SafetyLimits,
    gripper: GripperIO,
    options: DriverOptions,
    servo: tuple[float, float],
) -> None:  # pragma: no cover - runs in the child process (exercised by the emulator tests)
    """Serve RtdeDriver backend calls: (seq, name, args) -> (seq, "ok", value) | (seq, "err", type name, message)."""
    logging.basicConfig(level=logging.INFO, format=f"%(asctime)s rtde-child[{os.getpid()}] %(levelname)s %(message)s")
    drv = RtdeDriver(host, limits, gripper, options, servo[0], servo[1], verify_controller=False)
    while True:
        try:
            if not conn.poll(0.2):
                continue
            seq, name, args = conn.recv()
        except (EOFError, OSError):
            # the caller is gone (killed, crashed): stop the arm and end
            log.error("caller gone: stopping the arm and exiting")
            try:
                if drv._backend_connected():
                    drv._backend_stop(options.halt_decel)
                drv._backend_disconnect()
            except Exception as exc:
                log.error("stop after the caller vanished failed: %s", exc)
            os._exit(0)
        if name == "exit":
            conn.send((seq, "ok", None))
            os._exit(0)
        try:
            if name == "servo_end":
                drv._fault = DriverFault("faulted in the caller") if args[0] else None
                drv._backend_servo_end()
                value = None
            elif name == "reset_faults":
                drv._fault = None
                drv._backend_reset_faults()
                value = None
            elif name == "state":
                st = drv._backend_state()  # the stream's age is taken here, where it is read (see the caller)
                value = (st, drv._backend_connected(), time.monotonic() - st.received_at)
            else:
                value = getattr(drv, "_backend_" + name)(*args)
            conn.send((seq, "ok", value))
        except Exception as exc:
            conn.send((seq, "err", type(exc).__name__, str(exc)))


def main(argv: list[str]) -> None:  # pragma: no cover - runs in the child process
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    conn = Connection(int(argv[1]))
    host, limits, gripper, options, servo = conn.recv()
    serve(conn, host, limits, gripper, options, servo)


if __name__ == "__main__":  # pragma: no cover
    main(sys.argv)
