"""`normpos-grasp plan SCENE --cell CELL.yaml --im-id N --out plan.json [--library DIR ...] [--segmenter ...]`:
segment -> measure -> fit -> plan one pick for a frame of a BOP scene; writes plan.json (docs/grasping.md).

Exit codes: 0 a plan was found, 1 no feasible grasp (plan.json still written, with rejection counts), 2 bad input.
plan.json is written atomically (temporary name, then moved into place); an existing one is refused unless
--overwrite.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

from normpos_grasp.atomic import atomic_write_text
from normpos_grasp.cli.args import (
    add_library_args,
    add_segmenter_args,
    check_out_file,
    int_in,
    library_from_args,
    library_paths,
    seg_model_from_args,
)
from normpos_grasp.errors import InputError, NormposError, TemplateError


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "plan",
        help="choose an object and a grasp in one frame and plan the pick-and-place motion (plan.json)",
        description="Segment a BOP frame, measure norm-positions, fit templates and plan a collision-free pick.",
    )
    p.add_argument("scene", type=Path, help="BOP scene folder (scene_camera.json, rgb/, depth/)")
    p.add_argument("--cell", required=True, help="cell YAML (docs/cells.md) or a packaged cell name")
    p.add_argument("--im-id", type=int_in(0, 10**9), required=True, help="image id of the frame")
    p.add_argument("--out", type=Path, required=True, help="plan.json to write (refused when it exists)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out")
    add_library_args(p, "the cell's `templates`, else the built-in parts")
    add_segmenter_args(p, "gt")
    p.add_argument("--pick-unmatched", action="store_true", help="also pick objects no template matched (as boxes)")
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from normpos_grasp.cell import resolve_cell
    from normpos_grasp.cli.measure import scene_segmenter
    from normpos_grasp.io.bop import BopScene, is_scene_dir
    from normpos_grasp.measure.measure import MeasureOptions, measure_instances
    from normpos_grasp.planning import PlanOptions, plan_pick
    from normpos_grasp.templates.fit import FitContext, fit_best

    t0 = time.perf_counter()
    out = check_out_file(args.out, getattr(args, "overwrite", False))
    cell = resolve_cell(args.cell)
    if not is_scene_dir(args.scene):
        raise InputError(f"{args.scene} is not a BOP scene folder (expected scene_camera.json, rgb/ and depth/)")
    scene = BopScene(args.scene)
    scene.check_frame(args.im_id)
    frame = scene.load_frame(args.im_id)
    if cell.world_from_camera is not None:  # the cell's calibrated extrinsics win over the dataset's
        frame = replace(frame, camera=replace(frame.camera, world_from_camera=cell.world_from_camera))
    if frame.camera.world_from_camera is None:
        raise InputError("the frame's camera has no world_from_camera: give camera.world_from_camera in the cell file")
    library = library_from_args(args, None if library_paths(args) else cell.templates_path)
    bop_dirs = [Path(p) for p in library_paths(args) if (Path(p) / "models_info.json").is_file()]
    models_dir = bop_dirs[0] if bop_dirs else None
    seg_model = seg_model_from_args(args, None if library_paths(args) else cell.templates_path)
    segmenter = scene_segmenter(args.segmenter, scene, seg_model, models_dir, library.labels, library).segmenter
    t1 = time.perf_counter()
    instances = segmenter.segment(frame)
    t2 = time.perf_counter()
    normpositions = measure_instances(frame, instances, MeasureOptions())
    world_nps = [n for n in normpositions if n.frame == "world"]
    if len(world_nps) != len(normpositions):
        raise InputError("norm-positions were measured in the camera frame; the camera needs world_from_camera")
    t3 = time.perf_counter()
    context = FitContext(frame.camera, frame.depth_m)
    fits = []
    for n in world_nps:
        try:
            fit = fit_best(n, library, camera=context)
        except TemplateError:
            raise
        except NormposError as exc:
            print(f"instance {n.instance_id}: fit failed ({exc}); its points stay in the world as clutter")
            continue
        fits.append(replace(fit, instance_id=n.instance_id))
        status = "accepted" if fit.accepted else f"rejected ({fit.reason})"
        print(f"instance {n.instance_id} '{n.label}': {fit.template.name} {status}, score {fit.score:.3f}")
    t4 = time.perf_counter()
    plan = plan_pick(fits, world_nps, cell, PlanOptions(pick_unmatched=args.pick_unmatched))
    doc = plan.to_json()
    doc["timing_ms"] = {
        "segment": round((t2 - t1) * 1e3, 3),
        "measure": round((t3 - t2) * 1e3, 3),
        "fit": round((t4 - t3) * 1e3, 3),
        **{f"plan_{k}": v for k, v in doc["timing_ms"].items()},
        "total": round((time.perf_counter() - t0) * 1e3, 3),
    }
    doc["source"] = {
        "scene": str(args.scene),
        "im_id": int(args.im_id),
        "cell": str(args.cell),
        "segmenter": args.segmenter,
    }
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out, json.dumps(doc, indent=1))
    cands = doc["candidates"]
    reasons = ", ".join(f"{k} {v}" for k, v in sorted(cands["rejected_by_reason"].items(), key=lambda kv: -kv[1]))
    print(
        f"{doc['status']}: {cands['feasible']} feasible of {cands['evaluated']} evaluated "
        f"({cands['total']} candidates); rejected: {reasons or 'none'}"
    )
    if plan.chosen is not None:
        print(
            f"target instance {doc['target']['instance']} ({doc['target']['template']}), grasp {doc['grasp']['id']} "
            f"[{doc['grasp']['scheme']}], trajectory {doc['trajectory']['duration_s']:.2f} s -> {args.out}"
        )
        return 0
    print(f"no feasible grasp -> {args.out}")
    return 1
