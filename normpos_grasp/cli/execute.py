"""`normpos-grasp execute plan.json --robot HOST [--execute]`: check a plan and (only with --execute) run it."""

from __future__ import annotations

import argparse
import json
from typing import Any

from normpos_grasp.errors import InputError
from normpos_grasp.execution import (
    DriverOptions,
    ExecuteOptions,
    GripperIO,
    RtdeDriver,
    SafetyLimits,
    SimDriver,
    execute_plan,
    load_plan,
    parse_plan,
)


def register(subparsers: Any) -> None:
    parser = subparsers.add_parser(
        "execute",
        help="check a plan.json against the safety limits and run it on a UR arm (dry run unless --execute)",
        description="Checks every waypoint and trajectory sample against joint limits, speed/acceleration caps and "
        "the workspace box before anything is sent. Without --execute nothing is sent.",
    )
    parser.add_argument("plan", help="plan.json written by `normpos-grasp plan`")
    parser.add_argument("--robot", required=True, help="controller address (e.g. 192.168.1.10, 127.0.0.1), or 'sim'")
    parser.add_argument("--execute", action="store_true", help="send the plan (default: dry run)")
    parser.add_argument("--cell", default=None, help="cell YAML: take speed/acceleration caps and workspace from it")
    parser.add_argument("--speed-fraction", type=float, default=1.0, help="fraction of rated joint speeds allowed")
    parser.add_argument("--max-joint-accel", type=float, default=4.0, help="joint acceleration cap, rad/s^2")
    parser.add_argument(
        "--workspace",
        type=float,
        nargs=6,
        default=None,
        metavar=("XMIN", "YMIN", "ZMIN", "XMAX", "YMAX", "ZMAX"),
        help="TCP box in the robot base frame, m",
    )
    parser.add_argument("--close-output", type=int, default=0, help="digital output that closes the gripper")
    parser.add_argument("--open-output", type=int, default=1, help="digital output that opens it (-1: none)")
    parser.add_argument("--grip-input", type=int, default=-1, help="grip-detect digital input (-1: none)")
    parser.add_argument("--json", action="store_true", help="print the report as JSON")
    parser.set_defaults(handler=run)


def _limits(args: argparse.Namespace, robot: str) -> SafetyLimits:
    if args.cell:
        from normpos_grasp.cell import load_cell

        return SafetyLimits.from_cell(load_cell(args.cell))
    ws = args.workspace
    return SafetyLimits.for_model(
        robot,
        workspace_min=None if ws is None else ws[:3],
        workspace_max=None if ws is None else ws[3:],
        speed_fraction=args.speed_fraction,
        max_joint_accel=args.max_joint_accel,
    )


def run(args: argparse.Namespace) -> int:
    plan = load_plan(args.plan)
    parsed = parse_plan(plan)
    limits = _limits(args, parsed.robot)
    gripper = GripperIO(
        close_output=args.close_output,
        open_output=None if args.open_output < 0 else args.open_output,
        grip_detect_input=None if args.grip_input < 0 else args.grip_input,
    )
    if not args.execute:
        report = execute_plan(None, plan, limits, dry_run=True)
    else:
        if args.robot == "sim":
            driver: RtdeDriver | SimDriver = SimDriver(limits, gripper, q_home=parsed.q[0])
        elif args.robot:
            driver = RtdeDriver(args.robot, limits, gripper, DriverOptions())
        else:
            raise InputError("--robot is empty")
        driver.connect()
        try:
            report = execute_plan(driver, plan, limits, dry_run=False, options=ExecuteOptions())
        finally:
            driver.disconnect()
            if isinstance(driver, SimDriver):
                driver.shutdown()
    if args.json:
        print(json.dumps(report.to_dict(), indent=1))
    else:
        for m in report.messages:
            print(f"execute: {m}")
        for s in report.steps:
            print(f"execute: {s.name:>12s} {s.kind:<14s} {s.duration_s:7.2f} s  error {s.error_rad:.2e} rad")
        if report.status == "executed":
            print(f"execute: done, final joint error {report.final_error_rad:.2e} rad")
        else:
            print("execute: plan checked (dry run); add --execute to send it")
    return 0
