"""`normpos-grasp emulate-ur`: run a loopback UR controller that the unmodified ur_rtde clients can drive."""

from __future__ import annotations

import argparse
import logging
import signal
import sys
from typing import Any

from normpos_grasp.cli.args import float_in
from normpos_grasp.errors import InputError
from normpos_grasp.sim.ur_emulator import EmulatorOptions, UREmulator


def register(subparsers: Any) -> None:
    parser = subparsers.add_parser(
        "emulate-ur",
        help="run a loopback UR controller (RTDE 30004, dashboard 29999, script 30003)",
        description="Serve RTDE, dashboard and script ports on a loopback address so that ur_rtde's receive, "
        "control and IO interfaces run moves on a simulated arm at 500 Hz. Faults: dashboard lines "
        "'emu protective_stop', 'emu estop', 'emu drop', 'emu stall S', 'emu state'.",
    )
    parser.add_argument("--model", default="ur5e", help="UR model (ur3e, ur5e, ur10e, ur16e, ur20, ur30)")
    parser.add_argument("--host", default="127.0.0.1", help="loopback address to bind (127.0.0.x)")
    parser.add_argument(
        "--unlock-delay", type=float_in(0.0, 3600.0, "s"), default=5.0, help="seconds before a protective stop unlocks"
    )
    parser.add_argument(
        "--q-home", type=float_in(-6.2832, 6.2832, "rad"), nargs=6, default=None, help="initial joints (rad)"
    )
    parser.add_argument("--serial", default="20265500001", help="serial number the dashboard reports")
    parser.add_argument(
        "--rt-priority", type=int, default=0, help="SCHED_FIFO priority of the 500 Hz loop (0: normal scheduling)"
    )
    parser.add_argument(
        "--robotiq-model",
        default="2F-85",
        help="gripper behind the Robotiq URCap socket: 2F-85, 2F-140, or 'none' (a controller without the URCap)",
    )
    parser.add_argument("--robotiq-port", type=int, default=63352, help="TCP port of the Robotiq socket (1-65535)")
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    options = EmulatorOptions(
        model=args.model,
        host=args.host,
        unlock_delay_s=args.unlock_delay,
        rt_priority=args.rt_priority,
        serial=args.serial,
        robotiq_model="" if args.robotiq_model.lower() == "none" else args.robotiq_model,
        robotiq_port=args.robotiq_port,
    )
    if not 1 <= args.robotiq_port <= 65535:
        raise InputError(f"--robotiq-port must be a TCP port 1-65535, got {args.robotiq_port}")
    if args.q_home is not None:
        options.q_home = tuple(args.q_home)

    def _term(signum: int, frame: object) -> None:
        raise KeyboardInterrupt

    # SIGINT and SIGTERM end the emulator whatever it inherited: an ignored SIGINT (SIG_IGN survives exec, and
    # Python then keeps ignoring it) or a blocked mask would leave it running until its parent kills it
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, _term)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT, signal.SIGTERM})
    emulator = UREmulator(options).start()
    logging.getLogger("normpos_grasp").setLevel(min(logging.getLogger().level, logging.INFO))
    gripper = f", Robotiq {options.robotiq_model} {options.robotiq_port}" if options.robotiq_model else ""
    print(
        f"emulate-ur: {args.model} listening on {args.host} (RTDE 30004, dashboard 29999, script 30003{gripper})",
        flush=True,
    )
    try:
        emulator.serve_forever()
    except KeyboardInterrupt:
        pass
    finally:
        emulator.stop()
        print("emulate-ur: stopped", file=sys.stderr, flush=True)
    return 0
