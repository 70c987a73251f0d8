"""Template preparation paid by a fresh process's first fit: computed (no stored preparation) vs loaded (stored).

For the built-in part library and the example templates (copied to a temporary folder), each repeat starts a
fresh Python process that loads the templates, imports the fit's modules (timed apart: any fit pays them) and
times `prepared.prepare` of each template, in order: first with the disk cache off (`NORMPOS_GRASP_CACHE_DIR=off`: what
every process paid before), then, after one process has stored the preparations, loading them. Printed: median
seconds per template over the repeats, the worst template, and the machine load (os.getloadavg) before and after.

    .venv/bin/python benchmarks/bench_template_prep.py --repeats 5
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

CHILD = r"""
import json, sys, time
from pathlib import Path
from normpos_grasp.sim.parts import default_part_library
from normpos_grasp.templates.library import load_library
from normpos_grasp.templates.prepared import prepare
templates = list(default_part_library()) + list(load_library(Path(sys.argv[1])))
t0 = time.perf_counter()
import normpos_grasp.templates.fit  # what a fit imports anyway (numba kernels): timed apart
out = {"(imports)": time.perf_counter() - t0}
for t in templates:
    t0 = time.perf_counter()
    prepare(t)
    out[t.name] = time.perf_counter() - t0
print(json.dumps(out))
"""


def run_child(examples: Path, cache: str) -> dict[str, float]:
    env = dict(os.environ, NORMPOS_GRASP_CACHE_DIR=cache)
    done = subprocess.run(
        [sys.executable, "-c", CHILD, str(examples)], env=env, capture_output=True, text=True, check=True, cwd=ROOT
    )
    return json.loads(done.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    load0 = os.getloadavg()
    with tempfile.TemporaryDirectory() as tmp:
        examples = Path(tmp) / "templates"
        shutil.copytree(
            ROOT / "normpos_grasp" / "examples" / "templates", examples, ignore=shutil.ignore_patterns(".prepared")
        )
        cache = Path(tmp) / "cache"
        runs: dict[str, list[dict[str, float]]] = {"computed": [], "loaded": []}
        for _ in range(args.repeats):
            runs["computed"].append(run_child(examples, "off"))
        store = run_child(examples, str(cache))  # computes and stores every preparation once
        for _ in range(args.repeats):
            runs["loaded"].append(run_child(examples, str(cache)))
        stored = sorted(cache.glob("*.npz")) + sorted(examples.glob("*/.prepared/*.npz"))
        size_mb = sum(p.stat().st_size for p in stored) / 1e6
    load1 = os.getloadavg()
    imports = {k: float(np.median([r.pop("(imports)") for r in v])) for k, v in runs.items()}
    store.pop("(imports)")
    names = list(store)
    print(
        f"bench_template_prep: {len(names)} templates (built-in library + examples), {args.repeats} fresh processes "
        f"each; load average {load0[0]:.2f} / {load0[1]:.2f} before, {load1[0]:.2f} / {load1[1]:.2f} after"
    )
    print(f"  stored preparations: {len(stored)} files, {size_mb:.1f} MB; first store {sum(store.values()):.2f} s")
    print(f"  fit module imports (not preparation): {imports['computed']:.2f} s / {imports['loaded']:.2f} s")
    print(f"  {'template':12} {'computed s':>11} {'loaded s':>9}")
    med = {k: {n: float(np.median([r[n] for r in v])) for n in names} for k, v in runs.items()}
    for n in names:
        print(f"  {n:12} {med['computed'][n]:11.3f} {med['loaded'][n]:9.3f}")
    for k in ("computed", "loaded"):
        vals = np.array([med[k][n] for n in names])
        print(
            f"  {k:8}: median per template {np.median(vals):.3f} s, worst {vals.max():.3f} s "
            f"({names[int(vals.argmax())]}), all {vals.sum():.2f} s"
        )


if __name__ == "__main__":
    main()
