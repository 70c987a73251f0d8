"""Leaned grasps (`grasp.lean`, `PlanOptions.leans`) on parts by a bin wall or in a corner of the example cell.

Each default part lies on the bin floor of `ur5e_bin_parallel`, turned by each yaw, at each gap from the +x wall,
the +y wall, or both (the corner). Every placement is planned alone with the leaned pass off and on; printed per
placement kind: placements, planned without, planned with, and those only the leaned pass planned (part, yaw, gap,
the chosen grasp id), the plan time of those, and the machine load.

    .venv/bin/python benchmarks/bench_lean.py [--gaps 0.003 0.01 0.02] [--yaws 0 0.4 1.5708]
"""

from __future__ import annotations

import argparse
import os
import time
from collections import Counter
from pathlib import Path

import numpy as np

from normpos_grasp.cell import load_cell
from normpos_grasp.geometry import make_pose, rotation_from_rotvec
from normpos_grasp.planning import PlanOptions, plan_pick
from normpos_grasp.records.template import TemplateFit
from normpos_grasp.sim.parts import default_part_library

ROOT = Path(__file__).resolve().parents[1]
FLOOR_Z = 0.01  # the example cell's inner bin floor; walls at x = 0.3 / 0.7, y = -0.15 / 0.15


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--gaps", type=float, nargs="+", default=[0.003, 0.01, 0.02], help="gaps to the wall, m")
    ap.add_argument("--yaws", type=float, nargs="+", default=[0.0, 0.4, np.pi / 2], help="yaws, rad")
    args = ap.parse_args()
    cell = load_cell(ROOT / "examples" / "cells" / "ur5e_bin_parallel.yaml")
    print(f"load before: {os.getloadavg()[0]:.2f}")
    counts: Counter[tuple[str, str]] = Counter()
    rescued = []
    ms = []
    for part in default_part_library():
        for yaw in args.yaws:
            rot = rotation_from_rotvec([0.0, 0.0, yaw])
            verts = np.asarray(part.mesh.vertices) @ rot.T
            lo, hi = verts.min(axis=0), verts.max(axis=0)
            for gap in args.gaps:
                for where in ("wall_x", "wall_y", "corner"):
                    x = 0.7 - hi[0] - gap if where != "wall_y" else 0.5
                    y = 0.15 - hi[1] - gap if where != "wall_x" else 0.0
                    pose = make_pose(rot, [x, y, FLOOR_Z - lo[2]])
                    fit = TemplateFit(part, pose, 1.0, 0.0, 1.0, 1.0, 0.0, True, instance_id=1)
                    off = plan_pick([fit], [], cell, PlanOptions(leans=None))
                    t0 = time.perf_counter()
                    on = plan_pick([fit], [], cell, PlanOptions())
                    dt = (time.perf_counter() - t0) * 1e3
                    counts[(where, "all")] += 1
                    counts[(where, "without")] += off.status == "ok"
                    counts[(where, "with")] += on.status == "ok"
                    if off.status != "ok" and on.status == "ok" and on.chosen is not None:
                        rescued.append((part.name, yaw, gap, where, on.chosen.candidate.grasp_id))
                        ms.append(dt)
    print("placement  placements  planned without leans  planned with leans")
    for where in ("wall_x", "wall_y", "corner"):
        print(
            f"{where:9s}  {counts[(where, 'all')]:10d}  {counts[(where, 'without')]:21d}  {counts[(where, 'with')]:18d}"
        )
    print("planned only with the leaned pass:")
    for name, yaw, gap, where, gid in rescued:
        print(f"  {name:9s} yaw {yaw:.2f} gap {gap * 1e3:4.1f} mm {where:7s} {gid}")
    if ms:
        print(f"plan time of those (leaned pass included): median {np.median(ms):.0f} ms, max {max(ms):.0f} ms")
    print(f"load after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
