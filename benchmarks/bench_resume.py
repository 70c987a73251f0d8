"""Interrupted `simulate` runs resumed (issue 20): do they finish with the files of an uninterrupted run, and does any
process outlive an interrupted run?

    .venv/bin/python benchmarks/bench_resume.py [--trials 10] [--scenes 20] [--count 1] [--parts cube]
        [--resolution 160x120] [--segmenter gt] [--seed 0] [--workers 1,2] [--out DIR]

One uninterrupted reference run (with the first of --workers), then per trial: the same command (workers
alternating over --workers), sent SIGINT or SIGTERM (alternating) at a random moment: once k scene files exist
(k uniform in 0 .. scenes-1), after a delay uniform in one reference scene time (four for k = 0, which covers the
start-up); then run again with --resume (the first resume interrupted the same way with --interrupt-resumes) to
the end. A trial counts as identical when picks.csv, summary.json and the three plots equal the reference's
byte for byte. Orphans: every child and grandchild of the CLI seen while it ran (a /proc scan every 20 ms) that is
still alive (not a zombie) 5 s after the CLI exited. Prints one line per trial and a summary; --json writes both.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
COMPARED = ("picks.csv", "summary.json", "success_by_part.png", "success_by_depth.png", "success_by_occlusion.png")


def _stat(pid: int) -> tuple[str, int] | None:
    """(state, parent pid) of a live process, None when gone or a zombie."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    state, ppid = text[text.rindex(")") + 2 :].split()[:2]
    return None if state in ("Z", "X") else (state, int(ppid))


class Watch:
    """Records every descendant of `pid` while it runs (a /proc scan every `period_s`)."""

    def __init__(self, pid: int, period_s: float = 0.02) -> None:
        self.pid, self.period_s = pid, period_s
        self.seen: set[int] = set()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            tree = {self.pid}
            parents: dict[int, int] = {}
            for entry in os.scandir("/proc"):
                if entry.name.isdigit():
                    st = _stat(int(entry.name))
                    if st is not None:
                        parents[int(entry.name)] = st[1]
            grew = True
            while grew:
                grew = False
                for child, parent in parents.items():
                    if parent in tree and child not in tree:
                        tree.add(child)
                        grew = True
            self.seen |= tree - {self.pid}
            self._stop.wait(self.period_s)

    def stop(self) -> set[int]:
        self._stop.set()
        self._thread.join()
        return self.seen


def _scene_files(out: Path) -> int:
    try:
        return sum(1 for e in os.scandir(out / "scenes") if e.name.endswith(".json") and not e.name.startswith("."))
    except OSError:
        return 0


def run_cli(
    args: list[str], out: Path, moment: tuple[int, float] | None, sig: int
) -> tuple[int, float, set[int], str, int]:
    """Run the CLI; moment (k, delay_s): send `sig` `delay_s` after the k-th scene file appeared (k = 0: after
    the start), None: never. Returns (exit code, wall s, the descendants seen, stderr, scene files at the
    signal or -1 when none was sent)."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(args, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    watch = Watch(proc.pid)
    sent = [-1]

    def interrupt(k: int, delay_s: float) -> None:
        while proc.poll() is None and _scene_files(out) < k:
            time.sleep(0.02)
        time.sleep(delay_s)
        if proc.poll() is None:
            sent[0] = _scene_files(out)
            proc.send_signal(sig)

    timer = None
    if moment is not None:
        timer = threading.Thread(target=interrupt, args=moment, daemon=True)
        timer.start()
    _, err = proc.communicate()
    if timer is not None:
        timer.join()
    seen = watch.stop()
    return proc.returncode, time.perf_counter() - t0, seen, err, sent[0]


def orphans(pids: set[int], wait_s: float = 5.0) -> list[int]:
    deadline = time.monotonic() + wait_s
    while time.monotonic() < deadline:
        alive = [p for p in pids if _stat(p) is not None]
        if not alive:
            return []
        time.sleep(0.1)
    return [p for p in pids if _stat(p) is not None]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--trials", type=int, default=10)
    ap.add_argument("--scenes", type=int, default=20)
    ap.add_argument("--count", type=int, default=1)
    ap.add_argument("--parts", default="cube")
    ap.add_argument("--resolution", default="160x120")
    ap.add_argument("--segmenter", default="gt")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workers", default="1,2", help="worker counts the trials alternate over")
    ap.add_argument("--interrupt-resumes", action="store_true", help="interrupt the first resume too")
    ap.add_argument("--rng", type=int, default=20, help="seed of the interrupt moments")
    ap.add_argument("--out", default=None, help="work folder (default: a temporary one, removed)")
    ap.add_argument("--json", default=None, help="write the figures here")
    a = ap.parse_args()
    work = Path(a.out) if a.out else Path(tempfile.mkdtemp(prefix="bench_resume_"))
    work.mkdir(parents=True, exist_ok=True)
    base = [sys.executable, "-m", "normpos_grasp.cli.main", "simulate", "--cell",
            str(ROOT / "examples" / "cells" / "ur5e_bin_parallel.yaml"), "--scenes", str(a.scenes), "--count",
            str(a.count), "--parts", a.parts, "--resolution", a.resolution, "--segmenter", a.segmenter, "--seed",
            str(a.seed), "--no-progress"]  # fmt: skip
    workers = [int(w) for w in a.workers.split(",")]
    rng = random.Random(a.rng)
    print(f"load average {os.getloadavg()[0]:.1f}, {os.cpu_count()} CPUs; config: {' '.join(base[4:])}", flush=True)
    ref = work / "reference"
    shutil.rmtree(ref, ignore_errors=True)
    code, ref_wall, seen, err, _ = run_cli([*base, "--out", str(ref), "--workers", str(workers[0])], ref, None, 0)
    if code != 0:
        print(f"reference run failed ({code}): {err.strip()}")
        return 1
    ref_orphans = orphans(seen)
    per_scene = ref_wall / a.scenes
    print(f"reference: {ref_wall:.1f} s, workers {workers[0]}, orphans {len(ref_orphans)}", flush=True)
    rows: list[dict[str, Any]] = []
    for trial in range(a.trials):
        out = work / f"trial_{trial:02d}"
        shutil.rmtree(out, ignore_errors=True)
        n_workers = workers[trial % len(workers)]
        sig = (signal.SIGINT, signal.SIGTERM)[trial % 2]
        cmd = [*base, "--out", str(out), "--workers", str(n_workers)]

        def moment() -> tuple[int, float]:
            k = rng.randrange(0, a.scenes)  # after k finished scenes, somewhere in the next one (or the start-up)
            return k, rng.uniform(0.0, (4.0 if k == 0 else 1.0) * per_scene)

        first = moment()
        code, wall, seen, err, at_scenes = run_cli(cmd, out, first, sig)
        codes, lost, sent_at = [code], orphans(seen), [at_scenes]
        stderr_lines = [len(err.strip().splitlines())]
        extra = [err.strip()] if stderr_lines[0] > 1 else []  # more than the one line: kept for the record
        resumes = 0
        while codes[-1] != 0 and resumes < 3:
            again = moment() if (a.interrupt_resumes and resumes == 0) else None
            code, w, seen, err, at_scenes = run_cli([*cmd, "--resume"], out, again, sig)
            wall += w
            codes.append(code)
            sent_at.append(at_scenes)
            lost += orphans(seen)
            stderr_lines.append(len(err.strip().splitlines()))
            if stderr_lines[-1] > 1:
                extra.append(err.strip())
            resumes += 1
        same = codes[-1] == 0 and all((out / n).read_bytes() == (ref / n).read_bytes() for n in COMPARED)
        row = {
            "trial": trial,
            "workers": n_workers,
            "signal": signal.Signals(sig).name,
            "after_scenes": first[0],
            "delay_s": round(first[1], 2),
            "scene_files_at_signal": sent_at,
            "codes": codes,
            "stderr_lines": stderr_lines,
            "stderr_extra": extra,
            "identical": same,
            "orphans": len(lost),
            "wall_s": round(wall, 1),
        }
        rows.append(row)
        print(json.dumps(row), flush=True)
    identical = sum(r["identical"] for r in rows)
    orphaned = sum(r["orphans"] for r in rows)
    interrupted = sum(1 for r in rows if r["codes"][0] != 0)
    print(
        f"{identical} of {len(rows)} interrupted-and-resumed runs identical to the uninterrupted one "
        f"({interrupted} were interrupted before they finished); {orphaned} orphaned processes; reference "
        f"{ref_wall:.1f} s; load average {os.getloadavg()[0]:.1f}"
    )
    if a.json:
        Path(a.json).write_text(json.dumps({"reference_wall_s": ref_wall, "trials": rows}, indent=1) + "\n")
    if not a.out:
        shutil.rmtree(work, ignore_errors=True)
    return 0 if identical == len(rows) and orphaned == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
