"""`normpos-grasp execute plan.json --robot HOST [--execute]`: check a plan and (only with --execute) run it.

Exit codes: 0 executed (or checked in a dry run); 1 the grip was not detected after closing (the pick stopped at the
grasp); 2 bad input, an unsafe plan, a controller that is not the plan's robot, or a driver fault (one line on
stderr, the arm stopped); 130 SIGINT (Ctrl-C), 143 SIGTERM: the arm is stopped (stopJ) before disconnecting.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

from normpos_grasp.cell.gripper_driver import GripperDriverSpec, RobotiqDriverSpec
from normpos_grasp.cli.args import float_in
from normpos_grasp.errors import InputError
from normpos_grasp.execution import (
    DriverOptions,
    ExecuteOptions,
    GripperIO,
    SafetyLimits,
    SimDriver,
    SupervisedRtdeDriver,
    execute_plan,
    exit_code,
    load_plan,
    parse_plan,
    stop_signals,
)
from normpos_grasp.execution.gripper_config import gripper_io, tool_driver
from normpos_grasp.execution.interrupts import signal_name

EXIT_CODES = (
    "exit codes: 0 done (or dry run checked), 1 grip not detected (pick stopped), 2 bad input / unsafe plan / "
    "controller mismatch / driver fault, 130 SIGINT and 143 SIGTERM (the arm is stopped first)"
)


def register(subparsers: Any) -> None:
    parser = subparsers.add_parser(
        "execute",
        help="check a plan.json against the safety limits and run it on a UR arm (dry run unless --execute)",
        description="Checks every waypoint and trajectory sample against joint limits, speed/acceleration caps and "
        "the workspace box before anything is sent. Without --execute nothing is sent. With --execute the controller's "
        "robot model (dashboard `get robot model`, and --robot-serial where given) must be the plan's. SIGINT and "
        "SIGTERM stop the arm (stopJ) before the client disconnects.",
        epilog=EXIT_CODES,
    )
    parser.add_argument("plan", help="plan.json written by `normpos-grasp plan`")
    parser.add_argument("--robot", required=True, help="controller address (e.g. 192.168.1.10, 127.0.0.1), or 'sim'")
    parser.add_argument("--execute", action="store_true", help="send the plan (default: dry run)")
    parser.add_argument(
        "--cell",
        default=None,
        help="cell YAML or packaged cell name: the judge of the plan (workspace, mounted tool, caps); default: the "
        "cell the plan records it was made in",
    )
    parser.add_argument(
        "--speed-fraction",
        type=float_in(0.01, 1.0),
        default=None,
        help="fraction of the rated joint speeds allowed (default 1); with a cell it tightens the cell's caps, "
        "never loosens them",
    )
    parser.add_argument(
        "--max-joint-accel",
        type=float_in(0.01, 40.0, "rad/s^2"),
        default=None,
        help="joint acceleration cap, rad/s^2 (default 4, at most 40, ur_rtde's bound); with a cell it tightens the "
        "cell's cap, never loosens it",
    )
    parser.add_argument(
        "--robot-serial", default=None, help="refuse a controller whose `get serial number` is not this one"
    )
    parser.add_argument(
        "--workspace",
        type=float_in(-100.0, 100.0, "m"),
        nargs=6,
        default=None,
        metavar=("XMIN", "YMIN", "ZMIN", "XMAX", "YMAX", "ZMAX"),
        help="TCP box in the robot base frame, m",
    )
    parser.add_argument(
        "--close-output",
        type=int,
        default=None,
        help="digital output that closes the gripper (0-7 standard, 8-15 configurable; default 0), for a cell "
        "without a gripper.driver section",
    )
    parser.add_argument(
        "--open-output", type=int, default=None, help="digital output that opens it (-1: none; default 1)"
    )
    parser.add_argument(
        "--grip-input", type=int, default=None, help="grip-detect digital input bit 0-17 (-1: none, the default)"
    )
    parser.add_argument("--json", action="store_true", help="print the report as JSON")
    parser.set_defaults(handler=run)


def _limits(
    args: argparse.Namespace, plan: dict[str, Any], robot: str
) -> tuple[SafetyLimits, str | None, GripperDriverSpec | None]:
    """The limits that judge the plan: its cell's (--cell, else the cell the plan records), or a bare arm's with an
    explicit --workspace box; no cell and no box is refused (the arm would have no workspace at all). Also returns
    the controller serial number the cell names (None: not checked) and the cell's `gripper.driver` (None: none)."""
    from normpos_grasp.cell import resolve_cell

    raw = plan.get("cell")
    recorded: dict[str, Any] = raw if isinstance(raw, dict) else {}
    if args.cell:
        cell = resolve_cell(args.cell)
    elif recorded.get("path"):
        path = Path(str(recorded["path"]))
        if not path.is_file():
            raise InputError(
                f"the plan was made in cell {recorded.get('name', '?')!r} ({path}), which is not here: pass --cell"
            )
        cell = resolve_cell(path)
        if recorded.get("sha256") and cell.source_sha256 != recorded["sha256"]:
            raise InputError(f"cell file {path} changed since the plan was made: re-plan, or pass --cell to judge it")
    elif args.workspace is None:
        raise InputError(
            "no cell to judge the plan against: pass --cell CELL.yaml (or --workspace XMIN YMIN ZMIN XMAX YMAX ZMAX "
            "for an arm outside any cell)"
        )
    else:
        cell = None
    if cell is not None:
        cell = _plan_tool_cell(args, plan, cell)
        if cell.robot_model != robot:
            raise InputError(f"plan is for {robot!r} but cell {cell.name!r} has a {cell.robot_model!r}")
        limits = SafetyLimits.from_cell(cell, max_tool_accel=cell.motion.tcp_acceleration_m_s2)
        if args.workspace is not None:
            raise InputError("--workspace is for an arm outside any cell; the cell's workspace judges this plan")
        return _tightened(limits, args), cell.robot_serial, cell.gripper_driver
    ws = args.workspace
    bare = SafetyLimits.for_model(
        robot,
        workspace_min=ws[:3],
        workspace_max=ws[3:],
        speed_fraction=1.0 if args.speed_fraction is None else args.speed_fraction,
        max_joint_accel=4.0 if args.max_joint_accel is None else args.max_joint_accel,
    )
    return bare, None, None


def _tightened(limits: SafetyLimits, args: argparse.Namespace) -> SafetyLimits:
    """The cell's limits with --speed-fraction (of the rated joint speeds) and --max-joint-accel as further caps:
    each takes the smaller value per joint, so a flag given for a first run on a real arm is never ignored and
    never raises a cap. A plan timed for the cell's own caps then fails the check: re-plan in a slower cell."""
    import numpy as np

    from normpos_grasp.kinematics.ur_params import ur_params

    speed, accel = limits.max_joint_speed, limits.max_joint_accel
    if args.speed_fraction is not None:
        rated = np.asarray(ur_params(limits.model).velocity_limit, dtype=np.float64)
        speed = np.minimum(speed, rated * args.speed_fraction)
    if args.max_joint_accel is not None:
        accel = np.minimum(accel, args.max_joint_accel)
    return replace(limits, max_joint_speed=speed, max_joint_accel=accel)


def _plan_tool_cell(args: argparse.Namespace, plan: dict[str, Any], cell: Any) -> Any:
    """The cell with the tool the plan was made with (a dual-tool cell: the one its `tool.name` names, whose TCP and
    driver then judge and drive it; the plan's TCP is still checked against it); a real controller is refused for a
    dual-tool cell, since it cannot switch between the tools."""
    if len(cell.tools) == 1:
        return cell
    recorded = plan.get("tool")
    tool, _ = cell.tool_named(str(recorded.get("name", "")) if isinstance(recorded, dict) else "")
    if args.execute and args.robot != "sim":
        cell.refuse_dual_tool(f"the controller at {args.robot}")
    return cell.with_tool(tool)


def _flag_wiring(args: argparse.Namespace) -> GripperIO:
    """The gripper outputs the command line gives (defaults 0, 1, none); validated before anything else, so bad
    I/O indices are refused first and never reach a moving arm."""
    open_output = 1 if args.open_output is None else args.open_output
    grip_input = -1 if args.grip_input is None else args.grip_input
    return GripperIO(
        close_output=0 if args.close_output is None else args.close_output,
        open_output=None if open_output < 0 else open_output,
        grip_detect_input=None if grip_input < 0 else grip_input,
    )


def _gripper_wiring(args: argparse.Namespace, spec: GripperDriverSpec | None, flag_wiring: GripperIO) -> GripperIO:
    """The arm's gripper outputs: the cell's `gripper.driver` (a wiring flag next to it is refused), else the
    command line's."""
    given = (
        ("--close-output", args.close_output),
        ("--open-output", args.open_output),
        ("--grip-input", args.grip_input),
    )
    flags = [flag for flag, value in given if value is not None]
    if spec is None:
        return flag_wiring
    if flags:
        raise InputError(
            f"the cell configures the gripper (gripper.driver, type {spec.kind}); {flags[0]} would contradict it: "
            "drop the flag or the cell's driver section"
        )
    return gripper_io(spec) or GripperIO()


def run(args: argparse.Namespace) -> int:
    flag_wiring = _flag_wiring(args)
    plan = load_plan(args.plan)
    parsed = parse_plan(plan)
    limits, cell_serial, gripper_spec = _limits(args, plan, parsed.robot)
    gripper = _gripper_wiring(args, gripper_spec, flag_wiring)
    serial = args.robot_serial or cell_serial
    if not args.execute:
        report = execute_plan(None, plan, limits, dry_run=True)
    else:
        if not args.robot:
            raise InputError("--robot is empty")
        if args.robot == "sim":
            if isinstance(gripper_spec, RobotiqDriverSpec):
                raise InputError(
                    "the simulated driver has no Robotiq URCap socket: execute on the loopback controller "
                    "(`normpos-grasp emulate-ur`, --robot 127.0.0.1) or on the arm"
                )
            driver: SupervisedRtdeDriver | SimDriver = SimDriver(limits, gripper, q_home=parsed.q[0])
        else:
            driver = SupervisedRtdeDriver(args.robot, limits, gripper, DriverOptions(), expected_serial=serial)
        tool = tool_driver(gripper_spec, driver, args.robot)
        with stop_signals():
            try:
                try:
                    driver.connect()
                    if tool is not None:
                        tool.connect()  # a Robotiq activates here, before the arm moves
                    report = execute_plan(driver, plan, limits, dry_run=False, options=ExecuteOptions(), gripper=tool)
                finally:
                    if tool is not None:
                        tool.disconnect()
                    driver.disconnect()  # stops the arm first if it still moves
                    if isinstance(driver, SimDriver):
                        driver.shutdown()
            except KeyboardInterrupt as exc:
                code = exit_code(exc)
                print(
                    f"normpos-grasp execute: interrupted by {signal_name(exc)}: arm stopped, nothing further sent "
                    f"(exit {code})",
                    file=sys.stderr,
                    flush=True,
                )
                return code
    if args.json:
        print(json.dumps(report.to_dict(), indent=1))
    else:
        for m in report.messages:
            print(f"execute: {m}")
        for s in report.steps:
            print(f"execute: {s.name:>12s} {s.kind:<14s} {s.duration_s:7.2f} s  error {s.error_rad:.2e} rad")
        if report.status == "executed":
            print(f"execute: done, final joint error {report.final_error_rad:.2e} rad")
        elif report.status == "grip_failed":
            print("execute: grip not detected: pick stopped at the grasp, arm at rest (exit 1)")
        else:
            print("execute: plan checked (dry run); add --execute to send it")
    return 1 if report.status == "grip_failed" else 0
