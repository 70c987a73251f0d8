"""Wall time of `normpos-grasp demo` and per-stage medians over its picks.

    .venv/bin/python benchmarks/bench_demo.py [--parts 4] [--max-picks 8] [--repeats 10] [--seed 0] [--no-emulator]

Prints, per repeat (seed, seed + 1, ...), the demo's wall time, the driver used, the picks, pushes and why it
stopped; then the parts held over all bins, bins cleared, slips; then the median of every stage
(capture, segment, measure, fit, plan, execute, check; milliseconds per pick) over all picks of all repeats, and
the median wall time. The issue's goal: the default demo under 60 s on the reference machine.
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
from collections import defaultdict

from normpos_grasp.demo import DemoOptions, run_demo


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--parts", type=int, default=DemoOptions.parts)
    parser.add_argument("--max-picks", type=int, default=DemoOptions.max_picks)
    parser.add_argument("--repeats", type=int, default=1)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--segmenter", default=DemoOptions.segmenter)
    parser.add_argument("--no-emulator", action="store_true")
    parser.add_argument("--host", default="127.0.0.97", help="emulator loopback address")
    args = parser.parse_args()
    stages: dict[str, list[float]] = defaultdict(list)
    walls = []
    held = dropped = cleared = slips = pushes = 0
    for r in range(args.repeats):
        options = DemoOptions(
            seed=args.seed + r,
            parts=args.parts,
            max_picks=args.max_picks,
            segmenter=args.segmenter,
            use_emulator=not args.no_emulator,
            emulator_host=args.host,
        )
        with tempfile.TemporaryDirectory() as out:
            t0 = time.perf_counter()
            result = run_demo(out, options)
            wall = time.perf_counter() - t0
        walls.append(wall)
        statuses = ", ".join(rec.status for rec in result.records)
        summary = result.summary
        held += summary["picks_succeeded"]
        dropped += args.parts
        cleared += int(summary["parts_left_in_bin"] == 0)
        slips += sum(1 for rec in result.records if rec.check == "slip")
        pushes += len(summary.get("pushes", []))
        print(
            f"repeat {r + 1} (seed {args.seed + r}): {wall:.1f} s wall, driver {result.driver}, segmenter "
            f"{result.segmenter}, {summary['picks_succeeded']}/{summary['picks_attempted']} picked, "
            f"{summary['parts_left_in_bin']} left, {len(summary.get('pushes', []))} push(es) [{statuses}]; "
            f"{summary['stop']}"
        )
        for rec in result.records:
            for stage, ms in rec.timings_ms.items():
                stages[stage].append(ms)
    print(
        f"demo: {args.parts} parts, max {args.max_picks} picks, {args.repeats} repeat(s), load {os.getloadavg()[0]:.1f}"
    )
    print(
        f"parts held {held} / {dropped} in the bins = {100.0 * held / max(dropped, 1):.1f} %; bins cleared "
        f"{cleared} / {args.repeats}; slips {slips}; pushes {pushes}"
    )
    print(f"wall time: median {statistics.median(walls):.1f} s (min {min(walls):.1f}, max {max(walls):.1f})")
    for stage, values in stages.items():
        print(f"  {stage:>8s}: median {statistics.median(values):8.1f} ms per pick over {len(values)} picks")


if __name__ == "__main__":
    main()
