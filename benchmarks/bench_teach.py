"""Teach benchmark: new parts from CAD to validated picks, on CPU.

1. Teach: each part of --parts (built by tests/teach_parts.py with trimesh: flanged bushing, T-profile, hex nut,
   thin bracket; none ships with the project) is written as an STL in millimetres and taught into a fresh library
   with the default options (`normpos-grasp teach`'s defaults: 4 min budget, 2F-85); wall time per part.
2. Perception: --scenes bins of the packaged cell 'ur5e_bin_parallel' (seeds --seed.., none used by teach),
   --count parts each drawn from the new parts and the eight built-in ones (the new parts weighted to half the
   draws), D435 noise, 640x480, through pipeline.perceive with the GT masks, the bundled model (its masks
   class-agnostic: the library has labels it lacks, perception.factory.for_library) and the depth segmenter. Per
   new part: eligible objects (>= 400 visible px, visible fraction >= 0.3; bench_pipeline's protocol); segmentation
   recall (eligible new-part objects matched one-to-one by an instance mask at IoU >= 0.5) and precision (of the
   instances whose mask overlaps a new part most, those matched to it at IoU >= 0.5); pose recall (the matched
   instance's accepted fit is the right template with ADD(-S) < 0.1 d) and wrong accepted fits (a new-part
   template accepted on another object, or another template on a new part, or ADD(-S) >= 0.1 d); and the pose
   recall of the eligible built-in objects in the same bins.
3. Picks: `normpos-grasp simulate --library LIB --library builtin` on --sim-scenes bins of --sim-count parts drawn
   from the new parts (GT segmenter, the physics judge), share of picks held.

    nice -n 10 .venv/bin/python benchmarks/bench_teach.py [--parts t_profile,flanged_bushing] [--scenes 6]
        [--count 8] [--sim-scenes 3] [--sim-count 4] [--seed 9300] [--segmenters gt,model,depth] [--taught DIR]

--taught DIR skips step 1 and uses a library `teach` wrote before (its parts are the new parts); --sim-scenes 0
skips step 3; --model PATH runs 'model' with that ONNX file (a model taught the new parts by `train-segmenter
--library`, whose learned classes are weak hints: perception.factory.for_library).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT / "benchmarks"))

import teach_parts  # noqa: E402
from bench_pipeline import MIN_VISIB_FRACT, MIN_VISIBLE_PX, _world, match, pose_errors  # noqa: E402


def load() -> str:
    return "load average " + " ".join(f"{x:.1f}" for x in os.getloadavg())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--parts", default="t_profile,flanged_bushing", help=f"comma list of {sorted(teach_parts.PARTS)}")
    ap.add_argument("--scenes", type=int, default=6)
    ap.add_argument("--count", type=int, default=8)
    ap.add_argument("--sim-scenes", type=int, default=3)
    ap.add_argument("--sim-count", type=int, default=4)
    ap.add_argument("--seed", type=int, default=9300)
    ap.add_argument("--segmenters", default="gt,model,depth")
    ap.add_argument("--taught", type=Path, default=None, help="a taught library to use instead of step 1")
    ap.add_argument("--model", type=Path, default=None, help="the segmentation model for 'model' (default: bundled)")
    args = ap.parse_args()

    from normpos_grasp.cell import resolve_cell
    from normpos_grasp.pipeline import make_segmenter, perceive
    from normpos_grasp.sim.cell_scene import cell_camera, compose_cell_scene
    from normpos_grasp.sim.dataset import render_frame
    from normpos_grasp.sim.render import make_renderer
    from normpos_grasp.sim.sensor import sensor_preset
    from normpos_grasp.teach import TeachOptions, teach
    from normpos_grasp.templates.library import resolve_library
    from normpos_grasp.templates.prepared import prepare

    names = [n.strip() for n in args.parts.split(",") if n.strip()]
    work = Path(tempfile.mkdtemp(prefix="bench_teach_"))
    lib = work / "lib"
    if args.taught is not None:
        lib = args.taught
        taught = sorted(p.name for p in lib.iterdir() if (p / "template.yaml").is_file())
        names = [n for n in names if n in taught] + [n for n in taught if n not in names]  # --parts order first
        print(f"1. teach: skipped, the parts {names} taught before in {lib}")
    else:
        print(f"1. teach ({load()} at start)")
    for name in names if args.taught is None else ():
        path = teach_parts.write_part(name, work / "cad")
        t0, c0 = time.perf_counter(), time.process_time()
        (part,) = teach([path], lib, TeachOptions())
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        t = part.template
        rates = sorted(part.success.values(), reverse=True)
        steps = ", ".join(f"{k} {v:.1f}" for k, v in part.timings.items())
        print(
            f"  {name}: {wall:.1f} s wall, {cpu:.1f} s CPU ({steps}); symmetry "
            f"{part.symmetry.summary}; {len(part.resting)} resting poses (top {part.resting[0].probability:.0%}); "
            f"{len(part.success)} grasps validated, {sum(r >= 0.99 for r in rates)} at 100 %, {len(part.dropped)} "
            f"dropped; {len(t.grasps)} stored; {load()}"
        )

    library = list(resolve_library([str(lib), "builtin"]))
    builtin = [t.name for t in library if t.name not in names]
    draw = tuple(names * max(1, len(builtin) // len(names)) + builtin)  # the new parts: about half the draws
    cell = resolve_cell("ur5e_bin_parallel")
    camera = cell_camera(cell, "d435", (640, 480))
    sensor = sensor_preset("d435")
    diam = {t.name: prepare(t).diameter for t in library}
    kinds = [k.strip() for k in args.segmenters.split(",") if k.strip()]
    labels = {t.label for t in library}
    segs = {
        k: (None if k == "gt" else make_segmenter(k, args.model if k == "model" else None, labels=labels))
        for k in kinds
    }
    keys = ("eligible", "correct", "wrong", "accepted", "seg_found", "seg_inst", "seg_ok", "b_eligible", "b_correct")
    tally = {k: dict.fromkeys(keys, 0) for k in kinds}
    t0 = time.perf_counter()
    for i in range(args.scenes):
        layout = compose_cell_scene(cell, args.count, args.seed + i, library, draw)
        renderer = make_renderer(layout, camera.width, camera.height)
        try:
            sf = render_frame(layout, renderer, camera, sensor, np.random.default_rng(args.seed + i), scene_id=i)
        finally:
            renderer.close()
        templates = sf.layout.templates
        visible = sf.rendering.masks_visible.reshape(len(templates), -1).sum(axis=1)
        eligible = (visible >= MIN_VISIBLE_PX) & (sf.visib_fractions >= MIN_VISIB_FRACT)
        for kind, seg in segs.items():
            result = perceive(sf.frame, seg, library, instances=sf.instances if seg is None else None)
            matched, best = match([n.mask for n in result.instances], sf.rendering.instance_ids, visible)
            fits = {n.instance_id: f for n, f in zip(result.normpositions, result.fits, strict=True)}
            tl = tally[kind]
            tl["eligible"] += sum(int(eligible[k]) for k, t in enumerate(templates) if t.name in names)
            tl["seg_found"] += sum(int(eligible[k] and templates[k].name in names) for k in matched.values())
            for j in range(len(result.instances)):
                if best[j][0] >= 0 and templates[best[j][0]].name in names:
                    tl["seg_inst"] += 1
                    tl["seg_ok"] += int(j in matched)
            tl["b_eligible"] += sum(int(eligible[k]) for k, t in enumerate(templates) if t.name not in names)
            for j, inst in enumerate(result.instances):
                fit = fits.get(inst.instance_id)
                part = matched.get(j, best[j][0])
                truth = templates[part].name if part >= 0 else ""
                built_in = j in matched and eligible[part] and truth not in names
                if built_in and fit is not None and fit.accepted and fit.template.name == truth:
                    est = _world(fit.frame_from_object, fit.frame, sf.frame.camera)
                    good = pose_errors(templates[part], est, sf.world_from_object[part])[2] < 0.1 * diam[truth]
                    tl["b_correct"] += int(good)
                if fit is None or not fit.accepted or (truth not in names and fit.template.name not in names):
                    continue
                tl["accepted"] += 1
                ok = part >= 0 and fit.template.name == truth
                if ok:
                    est = _world(fit.frame_from_object, fit.frame, sf.frame.camera)
                    ok = pose_errors(templates[part], est, sf.world_from_object[part])[2] < 0.1 * diam[truth]
                tl["wrong"] += int(not ok)
                if ok and j in matched and eligible[part]:
                    tl["correct"] += 1
    print(
        f"2. perception: {args.scenes} bins x {args.count} parts (new parts {names} about half), seeds "
        f"{args.seed}..{args.seed + args.scenes - 1}, D435 640x480, {time.perf_counter() - t0:.0f} s; {load()}"
    )
    for kind, tl in tally.items():
        recall = tl["correct"] / max(tl["eligible"], 1)
        seg = ""
        if kind != "gt":
            seg = (
                f"segmentation recall {tl['seg_found'] / max(tl['eligible'], 1):.3f} ({tl['seg_found']}/"
                f"{tl['eligible']}), precision {tl['seg_ok'] / max(tl['seg_inst'], 1):.3f} ({tl['seg_ok']}/"
                f"{tl['seg_inst']}) at IoU 0.5; "
            )
        print(
            f"  {kind}: {seg}new-part pose ADD(-S) recall {recall:.3f} ({tl['correct']}/{tl['eligible']} eligible), "
            f"wrong accepted {tl['wrong']} of {tl['accepted']} accepted fits involving a new part; built-in parts' "
            f"pose recall {tl['b_correct'] / max(tl['b_eligible'], 1):.3f} ({tl['b_correct']}/{tl['b_eligible']})"
        )
    if args.sim_scenes <= 0:
        print(f"(library in {lib})")
        return

    out = work / "sim"
    t0 = time.perf_counter()
    cmd = [sys.executable, "-m", "normpos_grasp.cli.main", "simulate", "--cell", "ur5e_bin_parallel", "--library",
           str(lib), "--library", "builtin", "--parts", ",".join(names), "--count", str(args.sim_count), "--scenes",
           str(args.sim_scenes), "--segmenter", "gt", "--seed", str(args.seed), "--out", str(out)]  # fmt: skip
    subprocess.run(cmd, check=True, capture_output=True)
    summary = json.loads((out / "summary.json").read_text())
    print(
        f"3. simulate --library: {summary['picks_succeeded']}/{summary['picks_attempted']} picks held "
        f"({summary['success_rate']:.1%}), {summary['parts_left_in_bin']} of {summary['parts_total']} parts left, "
        f"failures {summary['failures_by_cause']}, {time.perf_counter() - t0:.0f} s; {load()}"
    )
    print(f"by part: {summary.get('by_part')}")
    print(f"(library kept in {lib})")


if __name__ == "__main__":
    main()
