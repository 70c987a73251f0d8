"""Fault and interrupt campaign (issue 18): the CLI (and a library script for moveL) as a subprocess, the real
ur_rtde client (in SupervisedRtdeDriver's child), the loopback controller in its own process.

Cases: SIGINT / SIGTERM during moveJ, moveL and the servoJ stream; a ur10e plan on a ur5e controller; a gripper
output out of range (--close-output 99); the controller killed (SIGKILL) mid-moveJ; every RTDE link dropped
mid-moveJ (`emu drop`); a permanent stall mid-moveJ (`emu stall 60`). Per run the campaign
(normpos_grasp.sim.ur_emulator.campaign) measures on the controller the first stop command's arrival and the arm at
rest (`emu since`, time.monotonic() of the controller process: one clock with this process on Linux), the motion
commands after the stop (or during a refused run), the joint state over RTDE for 0.6 s after a signal, and the
process's exit code, stderr lines and exit time.

Columns: aborts / hangs of the calling process; exit codes seen (expected); stop cmd, at rest (controller), still
(RTDE: |qd| < 1e-3 rad/s and q constant after): median/worst ms after the fault; exit: fault -> process gone, ms;
moved: max joint travel after the signal (rad); cmds: motion commands after the stop (refusals: during the run);
1-line: runs with exactly one error line and no traceback; bad: runs with any problem.

    .venv/bin/python benchmarks/bench_faults.py [--runs 5] [--cases sigint_movej,...] [--host 127.0.0.61] [--json F]
        [--rt-priority 10]
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

from normpos_grasp.errors import DriverTimeout
from normpos_grasp.sim.ur_emulator.campaign import CASES, Campaign, summarize


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--cases", default=",".join(CASES))
    ap.add_argument("--host", default="127.0.0.61")
    ap.add_argument("--json", type=Path, default=None, help="write every run's record here")
    ap.add_argument("--rt-priority", type=int, default=0, help="SCHED_FIFO priority of the emulator's loop (0: none)")
    ap.add_argument("--controllers", default="emulator,reference", help="comma-separated: emulator, reference")
    args = ap.parse_args()
    cases = [c for c in args.cases.split(",") if c]
    controllers = [c for c in args.controllers.split(",") if c]
    results = []
    t0 = time.monotonic()
    load0 = os.getloadavg()
    for ci, controller in enumerate(controllers):
        host = args.host if ci == 0 else _next_host(args.host, ci)
        with (
            tempfile.TemporaryDirectory() as tmp,
            Campaign(host, Path(tmp), rt_priority=args.rt_priority, controller=controller) as campaign,
        ):
            for _ in range(args.runs):
                for case in cases:
                    try:
                        r = campaign.run(case)
                    except (DriverTimeout, OSError) as exc:  # the harness could not set the case up (a slow start-up
                        # or the controller's dashboard not answering the harness's own query): counted, not measured
                        print(f"  {controller:9s} {case:18s} not run: {exc}", flush=True)
                        continue
                    results.append(r)
                    if args.json is not None:  # every run as it ends (a long campaign may be cut short)
                        with args.json.with_suffix(".jsonl").open("a") as out:
                            out.write(json.dumps(r.to_dict(), default=str) + "\n")
                    flag = "ok" if not r.problems() else "; ".join(r.problems())
                    rest = "-" if r.rest_s is None else f"{r.rest_s * 1000:.0f} ms"
                    line = f"exit {r.exit_code}  rest {rest}  overruns {r.emu_overruns}  {flag}"
                    print(f"  {controller:9s} {case:18s} {line}", flush=True)
    load1 = os.getloadavg()
    print(
        f"\n{len(results)} runs in {time.monotonic() - t0:.0f} s; load average {load0[0]:.1f} at the start, "
        f"{load1[0]:.1f} at the end ({os.cpu_count()} cores)"
    )
    head = (
        f"{'case':18s} {'runs':>4s} {'abort':>5s} {'hang':>4s} {'exit (exp)':>12s} {'stop cmd':>9s} {'at rest':>9s} "
        f"{'still':>9s} {'exit ms':>11s} {'moved':>6s} {'cmds':>4s} {'1-line':>6s} {'bad':>3s}"
    )
    for controller in controllers:
        table = summarize([r for r in results if r.controller == controller])
        print(f"\ncontroller: {controller}")
        print(head)
        for case, row in table.items():
            codes = ",".join(str(c) for c in row["exit_codes"]) + f" ({row['expected_exit']})"
            print(
                f"{case:18s} {row['runs']:4d} {row['aborts']:5d} {row['hangs']:4d} {codes:>12s} "
                f"{row['stop_cmd_ms']:>9s} {row['rest_ms']:>9s} {row['rtde_still_ms']:>9s} {row['exit_ms']:>11s} "
                f"{row['moved_rad_max']:6.3f} {row['cmds_after_stop']:4d} "
                f"{row['one_error_line'] - row['tracebacks']:6d} {row['problem_runs']:3d}"
            )
    if args.json is not None:
        args.json.write_text(json.dumps([r.to_dict() for r in results], indent=1, default=str))


def _next_host(host: str, k: int) -> str:
    """Another loopback address for the k-th controller (the ports are fixed: one controller per address)."""
    parts = host.split(".")
    parts[-1] = str((int(parts[-1]) + k) % 254 + 1)
    return ".".join(parts)


if __name__ == "__main__":
    main()
