"""Grasps carried through a template's symmetries: the example `cube_40mm` (one annotated top pinch, one top
suction grasp, 24 rotations) in five-cube bins, with and without the symmetric expansion.

Per bin (five cubes dropped into the bin and settled with MuJoCo; ground-truth poses handed to `plan_pick` as
accepted fits: a fit may return any of the 24 equivalent poses, the drop gives a random one): the parts that offer a
top-down grasp (approach within 20 degrees of straight down), the plan's status and its feasible candidates. Also
printed: of the 24 poses of the cube's group, how many offer a top-down grasp.

    .venv/bin/python benchmarks/bench_symmetric_grasps.py --bins 6
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from normpos_grasp.grasp.candidates import CandidateOptions, candidates_for_object, symmetry_group
from normpos_grasp.planning import PlanOptions, plan_pick
from normpos_grasp.records.template import TemplateFit
from normpos_grasp.sim.scene import SceneOptions, compose_scene
from normpos_grasp.templates.library import load_library

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from bench_grasp import scene_cell  # noqa: E402

DOWN_COS = float(np.cos(np.deg2rad(20.0)))


def top_down(template, world_from_object, kind: str, opts: CandidateOptions) -> bool:  # type: ignore[no-untyped-def]
    """Whether any candidate of the part approaches within 20 degrees of straight down."""
    cands = candidates_for_object(0, template, world_from_object, kind, opts)
    return any(-c.world_from_tcp[2, 2] >= DOWN_COS for c in cands)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--bins", type=int, default=6)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--gripper", default="2f85")
    args = ap.parse_args()
    cube = load_library(ROOT / "examples" / "templates" / "cube_40mm").get("cube_40mm")
    group = symmetry_group(cube.symmetry)
    print(f"bench_symmetric_grasps: cube_40mm, {len(group)} symmetry rotations, load {os.getloadavg()[0]:.1f}")
    for symmetric in (False, True):
        opts = CandidateOptions(symmetric=symmetric)
        for kind in ("parallel", "suction"):
            n = sum(top_down(cube, np.eye(4) @ g, kind, opts) for g in group)
            print(f"  symmetric={symmetric!s:5} {kind:8}: top-down grasp in {n}/{len(group)} cube orientations")
    rows = {False: [0, 0, 0, 0, []], True: [0, 0, 0, 0, []]}  # parts, parts with top-down, bins, bins ok, times
    for b in range(args.bins):
        layout = compose_scene(SceneOptions(count=5, seed=args.seed + b, parts=("cube_40mm",)), [cube])
        cell = scene_cell(layout, args.gripper)
        fits = [
            TemplateFit(t, layout.world_from_object[k], 1.0, 0.0, 1.0, 1.0, 0.0, True, instance_id=k + 1)
            for k, t in enumerate(layout.templates)
        ]
        for symmetric in (False, True):
            popts = replace(PlanOptions(), candidates=CandidateOptions(symmetric=symmetric))
            row = rows[symmetric]
            row[0] += layout.n_parts
            row[1] += sum(top_down(f.template, f.world_from_object, cell.tool.kind, popts.candidates) for f in fits)
            t0 = time.perf_counter()
            plan = plan_pick(fits, [], cell, popts)
            row[4].append(time.perf_counter() - t0)
            row[2] += 1
            row[3] += plan.status == "ok"
            print(
                f"  bin {b} symmetric={symmetric!s:5}: {plan.status:10} feasible {plan.n_feasible:3} "
                f"of {len(plan.evaluations):3} candidates"
            )
    for symmetric, (parts, tops, bins, ok, times) in rows.items():
        print(
            f"symmetric={symmetric!s:5}: {tops}/{parts} parts offer a top-down grasp; {ok}/{bins} bins planned; "
            f"plan median {np.median(times) * 1e3:.0f} ms"
        )


if __name__ == "__main__":
    main()
