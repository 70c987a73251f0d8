"""Execution figures on the loopback UR controller with the real ur_rtde 1.6.5 client.

1. A planner plan (UR5e bin cell) executed through RtdeDriver: final joint error vs the plan (target <= 1e-3 rad).
2. The 500 Hz receive stream while the plan runs, as a separate RTDE client process sees it: period p50/p99/max
   (target p99 <= 3 ms), from packet arrival times (client clock) and from the controller timestamps.
3. Command round trip: getForwardKinematics (register handshake: command -> done -> clear), a digital output
   set through RTDEIOInterface until the receive stream shows it, and a zero-length moveJ.

Run: .venv/bin/python benchmarks/bench_execution.py [--repeats 3] [--host 127.0.0.60]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

STREAM_CLIENT = r"""
import socket, struct, sys, time, json
import os
host, seconds, prio = sys.argv[1], float(sys.argv[2]), int(sys.argv[3])
if prio:
    os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(prio))
s = socket.create_connection((host, 30004)); s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
def send(kind, payload=b""):
    s.sendall(struct.pack(">HB", len(payload) + 3, kind) + payload)
def recv():
    hdr = b""
    while len(hdr) < 3:
        chunk = s.recv(3 - len(hdr))
        if not chunk:
            raise SystemExit("stream closed")
        hdr += chunk
    size, kind = struct.unpack(">HB", hdr)
    body = b""
    while len(body) < size - 3:
        chunk = s.recv(size - 3 - len(body))
        if not chunk:
            raise SystemExit("stream closed")
        body += chunk
    return kind, body
send(ord("V"), struct.pack(">H", 2)); recv()
send(ord("O"), struct.pack(">d", 500.0) + b"timestamp,actual_q")
recv()
send(ord("S")); recv()
arrivals, stamps = [], []
end = time.monotonic() + seconds
while time.monotonic() < end:
    kind, body = recv()
    if kind == ord("U"):
        arrivals.append(time.perf_counter())
        stamps.append(struct.unpack(">d", body[1:9])[0])
s.close()
print(json.dumps({"arrivals": arrivals, "stamps": stamps}))
"""


def _pct(values: np.ndarray) -> str:
    v = np.asarray(values) * 1e3
    return f"p50 {np.percentile(v, 50):.3f} ms, p99 {np.percentile(v, 99):.3f} ms, max {v.max():.3f} ms (n={len(v)})"


def _plan() -> tuple[dict, object]:
    import trimesh

    from normpos_grasp.cell import load_cell
    from normpos_grasp.geometry import make_pose
    from normpos_grasp.planning import plan_pick
    from normpos_grasp.records.template import Template, TemplateFit

    cell = load_cell(ROOT / "examples" / "cells" / "ur5e_bin_parallel.yaml")
    part = Template("box", "box", trimesh.creation.box((0.06, 0.04, 0.03)), shape="box")
    fit = TemplateFit(part, make_pose(None, [0.5, 0.05, 0.025]), 1.0, 0.0, 1.0, 1.0, 0.0, True, instance_id=1)
    return plan_pick([fit], [], cell).to_json(), cell


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--host", default="127.0.0.60")
    ap.add_argument("--rtt-samples", type=int, default=200)
    ap.add_argument(
        "--rt-priority",
        type=int,
        default=0,
        help="SCHED_FIFO priority for the emulator loop and the stream client (0: normal scheduling)",
    )
    args = ap.parse_args()

    from normpos_grasp.execution import RtdeDriver, SafetyLimits, execute_plan
    from normpos_grasp.sim.ur_emulator import EmulatorProcess

    plan, cell = _plan()
    limits = SafetyLimits.from_cell(cell)
    print(f"plan: {len(plan['joint_waypoints'])} waypoints, trajectory {plan['trajectory']['duration_s']:.2f} s")
    extra = ("--rt-priority", str(args.rt_priority)) if args.rt_priority else ()
    print(f"real-time priority: {args.rt_priority or 'off'}; load average {os.getloadavg()}")
    with EmulatorProcess(args.host, "ur5e", log_path="/tmp/bench_execution_emulator.log", extra_args=extra) as emu:
        driver = RtdeDriver(args.host, limits)
        driver.connect()
        try:
            errors, durations, periods, stamp_periods = [], [], [], []
            for r in range(args.repeats):
                driver.move_joints([plan["joint_waypoints"][0]["q"]], 1.0, 1.0)
                seconds = plan["trajectory"]["duration_s"] + 4.0
                client = subprocess.Popen(
                    [sys.executable, "-c", STREAM_CLIENT, args.host, str(seconds), str(args.rt_priority)],
                    stdout=subprocess.PIPE,
                    text=True,
                )
                time.sleep(0.5)
                t0 = time.monotonic()
                report = execute_plan(driver, plan, limits, dry_run=False)
                durations.append(time.monotonic() - t0)
                errors.append(report.final_error_rad)
                out, _ = client.communicate(timeout=seconds + 30)
                data = json.loads(out)
                periods.append(np.diff(np.array(data["arrivals"])))
                stamp_periods.append(np.diff(np.array(data["stamps"])))
                print(
                    f"run {r}: executed in {durations[-1]:.2f} s, final joint error {errors[-1]:.2e} rad, "
                    f"stream {_pct(periods[-1])}"
                )
            allp = np.concatenate(periods)
            print(
                f"final joint error: median {np.median(errors):.2e} rad, max {np.max(errors):.2e} rad "
                f"(target <= 1e-3) over {args.repeats} runs"
            )
            print(f"receive stream period (client arrival clock) while the plan runs: {_pct(allp)}")
            print(f"receive stream period (controller timestamps): {_pct(np.concatenate(stamp_periods))}")
            print(f"stream p99 per run: {', '.join(f'{np.percentile(p, 99) * 1e3:.3f} ms' for p in periods)}")

            c = driver._c  # the ur_rtde control interface: round trips of single commands
            fk, io_rt, movej = [], [], []
            for _ in range(args.rtt_samples):
                t = time.perf_counter()
                c.getForwardKinematics()
                fk.append(time.perf_counter() - t)
            for i in range(args.rtt_samples // 4):
                t = time.perf_counter()
                driver._backend_set_output(4, bool(i % 2), False)
                io_rt.append(time.perf_counter() - t)
            q = driver.state().q.tolist()
            for _ in range(args.rtt_samples // 4):
                t = time.perf_counter()
                c.moveJ(q, 1.0, 1.0, False)
                movej.append(time.perf_counter() - t)
            print(f"round trip getForwardKinematics (command->done->clear): {_pct(np.array(fk))}")
            print(f"round trip digital output set -> seen in receive stream: {_pct(np.array(io_rt))}")
            print(f"round trip zero-length synchronous moveJ: {_pct(np.array(movej))}")
            print(emu.emu("state"))
        finally:
            driver.disconnect()
    return 0


if __name__ == "__main__":
    sys.exit(main())
