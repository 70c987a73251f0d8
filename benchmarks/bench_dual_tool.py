"""Dual-tool cell against the parallel cell (issue 17 item 2): the same scenes, picked with a 2F-85 alone and with a
2F-85 and a suction cup on one flange, the tool chosen per part.

    .venv/bin/python benchmarks/bench_dual_tool.py [--scenes 10] [--seed 0] [--workers 2] [--out /tmp/dual]
    .venv/bin/python benchmarks/bench_dual_tool.py --runs DUAL_OUT PARALLEL_OUT   # read finished runs only

Runs `normpos-grasp simulate --cell C --scenes N --seed S --workers W --segmenter model` for C = ur5e_bin_dual and
ur5e_bin_parallel (unless --runs names two finished output folders) and prints for each: picks held / attempted,
bins cleared, failures by cause, and per part class the picks made with each tool (scheme) and how many held.
Prints the machine load and the wall time of each run. The issue's target for the dual cell: >= 98 % held,
>= 97 % of bins cleared.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

CELLS = ("ur5e_bin_dual", "ur5e_bin_parallel")


def _run(cell: str, out: Path, args: argparse.Namespace) -> float:
    cmd = [
        sys.executable, "-m", "normpos_grasp.cli.main", "simulate", "--cell", cell, "--scenes", str(args.scenes),
        "--seed", str(args.seed), "--workers", str(args.workers), "--segmenter", "model", "--out", str(out),
        "--overwrite",
    ]  # fmt: skip
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    return time.perf_counter() - t0


def report(out: Path) -> None:
    """Print one run's figures: held, bins cleared, causes, the tool per part class."""
    summary = json.loads((out / "summary.json").read_text())
    held, tried = summary["picks_succeeded"], summary["picks_attempted"]
    cleared, scenes = summary["scenes_cleared"], summary["scenes"]
    print(f"{summary['cell']}: {held} / {tried} = {100 * held / max(tried, 1):.1f} % held, {cleared} / {scenes} bins "
          f"cleared, {summary['parts_left_in_bin']} parts left, {summary['nudges']} nudges")  # fmt: skip
    causes = {k: v for k, v in summary["failures_by_cause"].items() if v}
    print("  failures: " + (", ".join(f"{k} {v}" for k, v in sorted(causes.items(), key=lambda kv: -kv[1])) or "none"))
    with (out / "picks.csv").open() as f:
        rows = list(csv.DictReader(f))
    used: Counter[tuple[str, str]] = Counter()
    ok: Counter[tuple[str, str]] = Counter()
    for r in rows:
        if r["part"] and r["scheme"]:
            used[(r["part"], r["scheme"])] += 1
            ok[(r["part"], r["scheme"])] += int(r["success"] == "1")
    print(f"  {'part':<10s} {'jaws held/picks':>16s} {'cup held/picks':>15s}")
    for part in sorted({p for p, _ in used}):
        cells = [f"{ok[(part, s)]} / {used[(part, s)]}" for s in ("parallel", "suction")]
        print(f"  {part:<10s} {cells[0]:>16s} {cells[1]:>15s}")
    for r in rows:
        if r["success"] != "1":
            print(f"  scene {r['scene']} pick {r['pick']}: {r['cause']} {r['part'] or '-'} ({r['scheme'] or '-'}): "
                  f"{r['reason'][:110]}")  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", type=int, default=10)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--out", type=Path, default=Path("/tmp/bench_dual_tool"))
    parser.add_argument("--runs", type=Path, nargs=2, metavar=("DUAL_OUT", "PARALLEL_OUT"))
    args = parser.parse_args()
    outs = list(args.runs) if args.runs else [args.out / c for c in CELLS]
    for cell, out in zip(CELLS, outs, strict=True):
        if not args.runs:
            load = os.getloadavg()[0]
            wall = _run(cell, out, args)
            print(f"{cell}: {wall:.0f} s wall (load {load:.1f} before, {os.getloadavg()[0]:.1f} after)")
        report(out)
    print(f"load average now: {' '.join(f'{v:.2f}' for v in os.getloadavg())}")


if __name__ == "__main__":
    main()
