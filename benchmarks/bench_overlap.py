"""Overlapped cycles on the loopback controller: seconds per pick-and-place and projected picks per hour, with and
without `run_cell_loop(overlap=True)`.

The example cell (examples/cells/ur5e_bin_parallel.yaml, its caps) on `normpos-grasp emulate-ur` (a loopback UR
controller in its own process) through the real ur_rtde client (`RtdeDriver`); a `SyntheticBinSource` of `--parts`
physics-settled parts (seed `--seed`) perceived with the frame's true masks (everything after segmentation as
`run` does it); picks are not replayed in physics (`validate_physics=False`: every executed pick counts), so both
modes walk through the same bin. Per mode the arm first moves home; the cycle is the wall time between two
consecutive finished turns (capture, perception, planning, execution, check), the first turn left out (it has
nothing to overlap with); the median over turns gives the projected picks per hour (3600 / median). Also printed:
the median plan trajectory (arm motion) and the median perception + planning time. The driver's stall watchdogs are
relaxed (`--stale-state`, 0.5 s): the default 0.15 s trips when the emulator process is descheduled on a loaded host.

    nice -n 10 .venv/bin/python benchmarks/bench_overlap.py [--parts 6] [--seed 5200] [--host 127.0.0.19]
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from normpos_grasp.cell import load_cell
from normpos_grasp.execution import DriverOptions, RtdeDriver, SafetyLimits
from normpos_grasp.loop import PickRecord, SyntheticBinSource, run_cell_loop
from normpos_grasp.sim.parts import default_part_library
from normpos_grasp.sim.ur_emulator import EmulatorProcess

CELL = "examples/cells/ur5e_bin_parallel.yaml"


def run_mode(
    host: str, overlap: bool, parts: int, seed: int, options: DriverOptions
) -> tuple[list[PickRecord], list[float]]:
    cell = load_cell(CELL)
    library = default_part_library()
    limits = SafetyLimits.from_cell(cell)
    source = SyntheticBinSource(cell, count=parts, seed=seed, validate_physics=False, library=library)
    driver = RtdeDriver(host, limits, options=options)
    driver.connect()
    stamps: list[float] = []
    try:
        driver.move_joints(np.asarray(cell.home_q, dtype=np.float64)[None], 1.0, 1.0)
        stamps.append(time.monotonic())
        records = run_cell_loop(
            cell, source, source.ground_truth_segmenter(), library, driver, execute=True, max_picks=parts,
            overlap=overlap, on_pick=lambda r: stamps.append(time.monotonic()),
        )  # fmt: skip
    finally:
        driver.disconnect()
    return records, list(np.diff(stamps))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--parts", type=int, default=6)
    parser.add_argument("--seed", type=int, default=5200)
    parser.add_argument("--host", default="127.0.0.19")
    parser.add_argument(
        "--stale-state", type=float, default=0.5, help="driver stall watchdog, s (default 0.15 trips on a loaded host)"
    )
    args = parser.parse_args()
    options = DriverOptions(stale_state_s=args.stale_state, watchdog_s=max(0.2, args.stale_state))
    cell = load_cell(CELL)
    print("# bench_overlap")
    print(
        f"cell {CELL}: caps {cell.motion.joint_velocity[0]:g} rad/s, {cell.motion.joint_acceleration[0]:g} rad/s^2; "
        f"loopback controller on {args.host}; bin of {args.parts} parts, seed {args.seed}; driver stall watchdog "
        f"{options.stale_state_s:g} s, stream watchdog {options.watchdog_s:g} s"
    )
    print(f"load average before: {' / '.join(f'{v:.2f}' for v in os.getloadavg())}")
    rows = []
    with EmulatorProcess(args.host, "ur5e", log_path="/tmp/bench_overlap_emulator.log"):
        for overlap in (False, True):
            records, cycles = run_mode(args.host, overlap, args.parts, args.seed, options)
            statuses = [r.status for r in records]
            motion = [
                r.result.plan.trajectory.duration_s for r in records if r.result.plan and r.result.plan.trajectory
            ]
            perceive = [
                sum(v for k, v in r.timings_ms.items() if k not in ("execute", "check", "overlap_wait")) / 1e3
                for r in records
            ]
            prepared = sum("overlap_wait" in r.timings_ms for r in records)
            execute = [r.timings_ms.get("execute", 0.0) / 1e3 for r in records]
            wait = [r.timings_ms["overlap_wait"] / 1e3 for r in records if "overlap_wait" in r.timings_ms]
            steady = cycles[1:] if len(cycles) > 1 else cycles
            name = "overlap" if overlap else "sequential"
            print(f"{name}: statuses {statuses}; cycles s {[round(float(c), 2) for c in cycles]}")
            rows.append((name, len(records), prepared, steady, motion, perceive, execute, wait))
    print("\n## Cycle per pick-and-place on the loopback controller")
    print("| mode | turns | turns prepared during the place | median cycle s | picks/hour | median arm motion s | "
          "median capture+perception+plan s | median execution s | median wait for the worker s |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|---|")
    for name, n, prepared, steady, motion, perceive, execute, wait in rows:
        med = float(np.median(steady)) if steady else float("nan")
        print(
            f"| {name} | {n} | {prepared} | {med:.2f} | {3600.0 / med:.0f} | {np.median(motion):.2f} | "
            f"{np.median(perceive):.2f} | {np.median(execute):.2f} | {np.median(wait) if wait else float('nan'):.2f} |"
        )
    print(f"load average after: {' / '.join(f'{v:.2f}' for v in os.getloadavg())}")


if __name__ == "__main__":
    main()
