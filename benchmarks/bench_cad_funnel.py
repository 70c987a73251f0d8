"""The cad detector's hypothesis funnel on bench_cad's held-out piles: where the right pose is lost.

For every target (visible fraction >= 0.3) and every stage of `CadDetector.detect` (raw vote peaks, clustered
hypotheses, the pre-score's survivors, the ICP pull-in, the hypotheses verified, the poses accepted by the greedy
selection, those dropped by the judgement against the whole scene, the poses returned), whether a pose of the right
template lies within ADD(-S) < 0.1 d of the ground truth (symmetry-aware; `CadDetector.trace`). Printed: the number
of targets with a right pose at each stage, per part and overall, with the CPU time per frame and the load average;
then every returned pose judged (right template and ADD(-S) < 0.1 d of a part of that template): precision overall
and against score (bench_verify.precision_table), and the dropped poses: how many were right.

    .venv/bin/python benchmarks/bench_cad_funnel.py [--frames 3] [--count 10] [--seed 2] [--mode none]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_cad import bin_roi
from bench_verify import precision_table
from heldout_parts import heldout_library

from normpos_grasp.geometry.transforms import invert_pose
from normpos_grasp.perception.cad_detector import CadDetector
from normpos_grasp.records.template import Template
from normpos_grasp.templates.prepared import prepare

STAGES = ("votes", "clusters", "prescore", "pull_in", "verified", "accepted", "dropped", "returned")


def right_any(template: Template, poses: np.ndarray, gt: np.ndarray) -> bool:
    """Whether any of the (K, 4, 4) poses is within ADD(-S) < 0.1 d of `gt` (min over the symmetries)."""
    if len(poses) == 0:
        return False
    prep = prepare(template)
    lim = 0.1 * prep.diameter
    c_gt = gt[:3, :3] @ prep.centroid + gt[:3, 3]
    c = poses[:, :3, :3] @ prep.centroid + poses[:, :3, 3]
    # ADD >= the centroid's displacement (the norm of a mean is at most the mean of the norms): an exact pre-filter
    cand = poses[np.linalg.norm(c - c_gt, axis=1) < lim]
    if len(cand) == 0:
        return False
    sub = prep.samples[:: max(1, len(prep.samples) // 120)]
    syms = template.symmetry.transforms(continuous_steps=72 if len(template.symmetry.continuous) == 1 else 12)
    pe = np.einsum("kij,pj->kpi", cand[:, :3, :3], sub) + cand[:, None, :3, 3]
    for s in syms:
        g = gt @ s
        pg = sub @ g[:3, :3].T + g[:3, 3]
        if np.min(np.mean(np.linalg.norm(pe - pg[None], axis=2), axis=1)) < lim:
            return True
    return False


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=3)
    ap.add_argument("--count", type=int, default=10)
    ap.add_argument("--seed", type=int, default=2)
    ap.add_argument("--mode", default="none", help="none or model (the bundled model's masks as hints)")
    args = ap.parse_args()

    from normpos_grasp.perception.factory import make_segmenter
    from normpos_grasp.sim.cameras import CameraOptions
    from normpos_grasp.sim.dataset import generate_frame
    from normpos_grasp.sim.scene import SceneOptions

    library = heldout_library()
    det = CadDetector(library)
    hint_seg = make_segmenter(args.mode) if args.mode != "none" else None
    found: dict[str, dict[str, int]] = defaultdict(lambda: defaultdict(int))
    walls, cpus, loads = [], [], []
    scored: list[tuple[float, bool]] = []
    n_dropped = n_dropped_right = 0
    for f in range(args.frames):
        so = SceneOptions(count=args.count, seed=args.seed * 1000 + f, clutter=0.5)
        sf = generate_frame(
            so, "d435", CameraOptions(distance_m=(0.5, 0.9)), seed=args.seed * 7919 + f, library=library
        )
        det.roi = bin_roi(so)
        det.trace = []
        hints = hint_seg.segment(sf.frame) if hint_seg is not None else None
        t0, c0 = time.perf_counter(), time.process_time()
        res = det.detect(sf.frame, hint_instances=hints)
        walls.append(time.perf_counter() - t0)
        cpus.append(time.process_time() - c0)
        loads.append(os.getloadavg()[0])
        cfw = invert_pose(np.asarray(sf.frame.camera.world_from_camera))
        by: dict[tuple[str, str], list[np.ndarray]] = defaultdict(list)
        for stage, name, poses in det.trace:
            by[(stage, name)].append(poses)
        for fit in res.fits:
            by[("returned", fit.template.name)].append(cfw @ np.asarray(fit.frame_from_object)[None])
        templates = sf.layout.templates
        gts = {
            t.name: [cfw @ sf.world_from_object[k] for k, u in enumerate(templates) if u.name == t.name]
            for t in library
        }
        for fit in res.fits:
            pose = cfw @ np.asarray(fit.frame_from_object)[None]
            scored.append((fit.score, any(right_any(fit.template, pose, g) for g in gts[fit.template.name])))
        by_name = {t.name: t for t in library}
        for stage, name, poses in det.trace:
            if stage == "dropped":
                n_dropped += 1
                n_dropped_right += int(any(right_any(by_name[name], poses, g) for g in gts[name]))
        for k, t in enumerate(templates):
            if sf.visib_fractions[k] < 0.3:
                continue
            gt = cfw @ sf.world_from_object[k]
            found[t.name]["targets"] += 1
            for stage in STAGES:
                ps = by.get((stage, t.name), [])
                if ps and right_any(t, np.concatenate(ps), gt):
                    found[t.name][stage] += 1
    print(
        f"funnel, mode '{args.mode}', {args.frames} frames of {args.count} parts, seed {args.seed}: wall per frame "
        f"median {np.median(walls):.1f} s (CPU {np.median(cpus):.1f} s), load average {np.median(loads):.1f}"
    )
    print(f"  {'part':13s} targets " + " ".join(f"{s:>9s}" for s in STAGES))
    tot: dict[str, int] = defaultdict(int)
    for name in sorted(found):
        row = found[name]
        for key, v in row.items():
            tot[key] += v
        print(f"  {name:13s} {row['targets']:7d} " + " ".join(f"{row[s]:9d}" for s in STAGES))
    print(f"  {'all':13s} {tot['targets']:7d} " + " ".join(f"{tot[s]:9d}" for s in STAGES))
    n_right = sum(ok for _, ok in scored)
    print(
        f"returned poses: {len(scored)}, right {n_right}, precision {n_right / max(len(scored), 1):.3f}; dropped by "
        f"the judgement against the scene: {n_dropped}, of them right {n_dropped_right}"
    )
    precision_table(scored, f"mode '{args.mode}', returned poses")


if __name__ == "__main__":
    main()
