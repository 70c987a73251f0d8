"""Replay bundles (issue 22 item 4): size and save time per cycle, replay time, and how many replays reproduce the
plan byte for byte.

Bins: `loop.SyntheticBinSource` in the packaged ur5e_bin_parallel cell (`--parts` parts, seeds `--seed`,
`--seed` + 1, ...; true masks, D435 noise, no physics check), `--picks` dry-run turns each with a
`replay.BundleRecorder`. Then every bundle is replayed in this process (`replay.replay_bundle`: load + verify +
perceive + plan + compare), and again with one part's depth moved by `--shift-mm` (must be detected). With `--cli`
the first bundle is also replayed by `normpos-grasp replay` in a fresh process (wall time includes start-up).

    nice -n 10 .venv/bin/python benchmarks/bench_replay.py [--bins 3] [--parts 4] [--picks 2] [--seed 7100] [--cli]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from normpos_grasp.cell import resolve_cell
from normpos_grasp.loop import SyntheticBinSource, run_cell_loop
from normpos_grasp.pipeline import PipelineOptions
from normpos_grasp.replay import BundleRecorder, load_bundle, replay_bundle
from normpos_grasp.replay.bundle import library_record, write_bundle
from normpos_grasp.sim.parts import default_part_library


def _load() -> str:
    return " / ".join(f"{v:.2f}" for v in os.getloadavg())


def _size(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bins", type=int, default=3)
    ap.add_argument("--parts", type=int, default=4)
    ap.add_argument("--picks", type=int, default=2)
    ap.add_argument("--seed", type=int, default=7100)
    ap.add_argument("--shift-mm", type=float, default=2.0, help="depth shift of one part for the detection check")
    ap.add_argument("--cli", action="store_true", help="also replay the first bundle with the CLI in a new process")
    args = ap.parse_args()
    print(f"load average before: {_load()} ({os.cpu_count()} cores)")
    cell = resolve_cell("ur5e_bin_parallel")
    library = default_part_library()
    with tempfile.TemporaryDirectory(prefix="bench_replay_") as tmp:
        saved: list[Path] = []
        save_s: list[float] = []
        save_cpu: list[float] = []
        for k in range(args.bins):
            source = SyntheticBinSource(cell, args.parts, args.seed + k, validate_physics=False)
            segmenter = source.ground_truth_segmenter()
            with BundleRecorder(Path(tmp) / f"bin{k}", segmenter) as recorder:
                records = run_cell_loop(cell, source, segmenter, library, None, max_picks=args.picks, bundles=recorder)
            saved += recorder.saved
            save_s += recorder.save_times_s
            for r in records:  # the same bundle written again, for its CPU time (the loop above timed wall only)
                c0 = time.process_time()
                write_bundle(Path(tmp) / f"again{k}-{r.index}", r, cell, library, PipelineOptions(),
                             segmenter=recorder.segmenter, library=library_record(library))  # fmt: skip
                save_cpu.append(time.process_time() - c0)
        sizes = np.array([_size(p) for p in saved], dtype=np.float64)
        parts: dict[str, list[int]] = {}
        for p in saved:
            per: dict[str, int] = {}
            for f in p.rglob("*"):
                if f.is_file():
                    key = f.relative_to(p).parts[0]
                    per[key] = per.get(key, 0) + f.stat().st_size
            for key, n in per.items():
                parts.setdefault(key, []).append(n)
        print(f"{len(saved)} bundles from {args.bins} bins of {args.parts} parts ({args.picks} turns each)")
        print(
            f"bundle size: median {np.median(sizes) / 1e6:.2f} MB (min {sizes.min() / 1e6:.2f}, "
            f"max {sizes.max() / 1e6:.2f}); save time per cycle: median {np.median(save_s) * 1e3:.0f} ms wall "
            f"(max {max(save_s) * 1e3:.0f} ms), {np.median(save_cpu) * 1e3:.0f} ms CPU"
        )
        share = ", ".join(
            f"{k} {np.median(v) / 1e3:.0f} kB" for k, v in sorted(parts.items(), key=lambda kv: -sum(kv[1]))
        )
        print(f"  per part (median per bundle, summed over its files): {share}")
        replay_s: list[float] = []
        replay_cpu: list[float] = []
        identical = detected = 0
        for p in saved:
            t0, c0 = time.perf_counter(), time.process_time()
            report = replay_bundle(p)
            replay_s.append(time.perf_counter() - t0)
            replay_cpu.append(time.process_time() - c0)
            identical += report.identical
            b = load_bundle(p)
            fitted = {f["instance_id"] for f in b.fits if f["accepted"]}
            inst = next((i for i in b.instances if i.instance_id in fitted), b.instances[0])
            depth = b.frame.depth_m.copy()
            depth[inst.mask & (depth > 0)] += args.shift_mm * 1e-3
            detected += not replay_bundle(b, frame=replace(b.frame, depth_m=depth)).identical
        print(
            f"replay (load, verify, perceive, plan, compare): median {np.median(replay_s):.2f} s wall "
            f"(max {max(replay_s):.2f} s), {np.median(replay_cpu):.2f} s CPU (2 fit threads); "
            f"byte-identical plans {identical} of {len(saved)}; "
            f"one part's depth +{args.shift_mm:g} mm detected {detected} of {len(saved)}"
        )
        if args.cli:
            t0 = time.perf_counter()
            done = subprocess.run(
                [sys.executable, "-m", "normpos_grasp.cli.main", "replay", str(saved[0])],
                capture_output=True,
                text=True,
            )
            last = (done.stdout.strip().splitlines() or [""])[-1]
            print(
                f"CLI replay in a fresh process: exit {done.returncode} ({last}), {time.perf_counter() - t0:.1f} s wall"
            )
            if done.returncode not in (0, 1):
                print(done.stderr.strip()[-2000:])
    print(f"load average after: {_load()}")


if __name__ == "__main__":
    main()
