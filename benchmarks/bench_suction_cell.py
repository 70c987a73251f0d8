"""Suction cell on suction-friendly parts (issue 17): which parts the rule calls friendly, and how a run held them.

    .venv/bin/python benchmarks/bench_suction_cell.py [--cell ur5e_bin_suction] [--run OUT ...]

Prints, for every built-in part, the rule of `grasp.quality.suction_friendliness` with the cell's own cup: friendly
or why not, the sealing patches found, the share of its resting poses with a patch facing up, the cup's payload,
and the `--parts` list of the friendly ones for `normpos-grasp simulate`. With --run (a `simulate` output folder,
repeatable): the picks held, all and per part, and over the friendly parts' picks. A 'no feasible grasp' that ended
a scene has no part: it counts in the all-parts figure only, and the scenes it ended with a friendly part still in
the bin are counted apart. Prints the machine load.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import time
from collections import Counter
from dataclasses import replace
from pathlib import Path

from normpos_grasp.cell.config import resolve_cell
from normpos_grasp.grasp.quality import QualityOptions, suction_friendliness
from normpos_grasp.sim.parts import default_part_library


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cell", default="ur5e_bin_suction")
    parser.add_argument("--run", action="append", default=[], help="a simulate output folder (repeatable)")
    parser.add_argument("--min-share", type=float, default=0.0, help="also require this resting share (0: off)")
    args = parser.parse_args()
    cell = resolve_cell(args.cell)
    if cell.tool.kind != "suction" or cell.tool.cup_diameter_m <= 0.0:
        raise SystemExit(f"cell {cell.name!r} has no suction cup")
    opts = replace(QualityOptions(), cup_diameter_m=float(cell.tool.cup_diameter_m))
    print(f"cell {cell.name}: cup {opts.cup_diameter_m * 1e3:.0f} mm (+{opts.seal_margin_m * 1e3:.0f} mm a side)")
    head = ("mass kg", "friendly", "reason", "patches", "rest up", "payload")
    print(f"{'part':10s} " + " ".join(f"{h:>8s}" for h in head))
    friendly = []
    t0 = time.perf_counter()
    for t in default_part_library():
        v = suction_friendliness(t.mesh, float(t.mass_kg), opts, min_share=args.min_share)
        print(
            f"{t.name:10s} {t.mass_kg:8.3f} {'yes' if v.friendly else 'no':>8s} {v.reason:>8s} {len(v.patches):8d} "
            f"{v.share:8.2f} {v.payload_kg:8.2f}"
        )
        if v.friendly:
            friendly.append(t.name)
    print(f"rule in {time.perf_counter() - t0:.1f} s; friendly parts: --parts {','.join(friendly)}")
    for run in args.run:
        _report(Path(run), set(friendly))
    print(f"load {' '.join(f'{x:.1f}' for x in os.getloadavg())}")


def _report(run: Path, friendly: set[str]) -> None:
    rows = list(csv.DictReader((run / "picks.csv").open(encoding="utf-8")))
    held = sum(int(r["success"]) for r in rows)
    print(f"\n{run}: {held} / {len(rows)} = {100.0 * held / max(len(rows), 1):.1f} % held (all picks)")
    per_part: Counter[tuple[str, bool]] = Counter((r["part"], r["success"] == "1") for r in rows if r["part"])
    for part in sorted({p for p, _ in per_part}):
        ok, bad = per_part[(part, True)], per_part[(part, False)]
        print(f"  {part:10s} {ok:3d} / {ok + bad:3d} held{'  (friendly)' if part in friendly else ''}")
    f_ok = sum(n for (p, s), n in per_part.items() if p in friendly and s)
    f_all = sum(n for (p, _), n in per_part.items() if p in friendly)
    print(f"  friendly parts' picks: {f_ok} / {f_all} = {100.0 * f_ok / max(f_all, 1):.1f} % held")
    ended, left = 0, Counter()
    for path in sorted((run / "scenes").glob("scene_*.json")):
        scene = json.loads(path.read_text(encoding="utf-8"))
        mine = [p for p in scene.get("left", []) if str(p.get("part", "")) in friendly]
        ended += bool(mine)
        left.update(f"{p['part']} ({p.get('stage', '')} {p.get('detail', '')})" for p in mine)
    causes = Counter(r["cause"] for r in rows if r["cause"])
    print(f"  failed picks by cause: {dict(causes)}; scenes that ended with a friendly part left: {ended}")
    for what, n in left.most_common():
        print(f"    left: {n:3d} x {what}")


if __name__ == "__main__":
    main()
