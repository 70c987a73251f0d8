"""Surfaces the segmenter missed (`measure.uncovered.uncovered_points`): false points on empty bins, recall of a part
whose mask is dropped, CPU per frame.

Bins of the packaged cell `ur5e_bin_parallel` (`loop.SyntheticBinSource`, D435 noise, 640x480):
- empty bins (`--empty` frames, seeds 9000...): uncovered points, and what the planner keeps of them (3 points within
  1 cm, `planning.plan._drop_outliers`); want 0;
- full bins (`--bins` frames of `--parts` parts, seeds 9100...) with their true masks: want 0; then each part's mask
  dropped in turn: the share of its pixels (at the stride) that come back, per part;
- CPU per frame (median of 20 calls, 10 masks), with the load printed.

    .venv/bin/python benchmarks/bench_uncovered.py [--empty 6] [--bins 4] [--parts 8]
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from normpos_grasp.cell import load_cell
from normpos_grasp.loop import SyntheticBinSource
from normpos_grasp.measure.uncovered import UncoveredOptions, uncovered_points
from normpos_grasp.planning.plan import _drop_outliers
from normpos_grasp.sim.parts import default_part_library

CELL = "examples/cells/ur5e_bin_parallel.yaml"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--empty", type=int, default=6)
    ap.add_argument("--bins", type=int, default=4)
    ap.add_argument("--parts", type=int, default=8)
    args = ap.parse_args()
    cell = load_cell(CELL)
    library = default_part_library()
    opts = UncoveredOptions()
    print("# bench_uncovered")
    print(f"options: {opts}")
    print(f"load average before: {' / '.join(f'{v:.2f}' for v in os.getloadavg())}")
    empty = []
    for k in range(args.empty):
        frame = SyntheticBinSource(cell, count=0, seed=9000 + k, validate_physics=False).capture()
        pts = uncovered_points(frame, [], cell.bins, opts)
        empty.append((len(pts), len(_drop_outliers(pts, cell.voxel_m, 3))))
    print(
        f"empty bins: {args.empty} frames, uncovered points per frame {[e[0] for e in empty]}, kept as clutter "
        f"{[e[1] for e in empty]}"
    )
    recall: dict[str, list[float]] = {}
    full = []
    timing: list[float] = []
    for k in range(args.bins):
        source = SyntheticBinSource(cell, count=args.parts, seed=9100 + k, validate_physics=False, library=library)
        frame = source.capture()
        instances = source.ground_truth_segmenter().segment(frame)
        masks = [i.mask for i in instances]
        full.append(len(uncovered_points(frame, masks, cell.bins, opts)))
        for j, missed in enumerate(instances):
            pts = uncovered_points(frame, masks[:j] + masks[j + 1 :], cell.bins, opts)
            s = opts.stride_px
            recall.setdefault(missed.label, []).append(len(pts) / max(int(missed.mask[::s, ::s].sum()), 1))
        for _ in range(20 if k == 0 else 0):
            t0 = time.process_time()
            uncovered_points(frame, masks, cell.bins, opts)
            timing.append(time.process_time() - t0)
    print(f"full bins with their true masks: {args.bins} frames, uncovered points per frame {full}")
    print("a part's mask dropped: share of its pixels that come back (per occurrence)")
    for label, values in sorted(recall.items()):
        print(f"  {label:10s} median {np.median(values):.2f}, min {min(values):.2f} over {len(values)}")
    print(f"CPU per frame ({args.parts} masks): {np.median(timing) * 1e3:.1f} ms median of {len(timing)}")
    print(f"load average after: {' / '.join(f'{v:.2f}' for v in os.getloadavg())}")


if __name__ == "__main__":
    main()
