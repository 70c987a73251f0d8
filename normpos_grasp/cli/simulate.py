"""`normpos-grasp simulate`: offline grasp simulation of a cell over synthetic bin scenes, judged by physics."""

from __future__ import annotations

import argparse
import json
import time
from typing import Any


def register(subparsers: Any) -> None:
    parser = subparsers.add_parser(
        "simulate",
        help="simulate bin clearing offline: real pipeline on rendered noisy frames, grasps checked in physics",
        description="For each synthetic scene, render the cell's bin through the sensor model, run segmentation, "
        "measurement, template fitting and pick planning on the noisy frame, validate the chosen grasp in MuJoCo "
        "against the true part poses, and repeat until the bin is cleared. Writes picks.csv, summary.json, "
        "timing.json and PNG plots to --out.",
    )
    parser.add_argument("--cell", required=True, help="cell YAML (needs a bin and a camera pose)")
    parser.add_argument("--scenes", type=int, default=10, help="number of scenes")
    parser.add_argument("--sensor", default="d435", help="sensor model preset (d435, d455, zed2, zivid, ideal)")
    parser.add_argument("--seed", type=int, default=0, help="batch seed (scenes are seeded from it)")
    parser.add_argument("--out", required=True, help="output folder")
    parser.add_argument("--parts", default="default", help="'default' or comma-separated part names")
    parser.add_argument("--count", type=int, default=8, help="parts per scene")
    parser.add_argument(
        "--segmenter",
        default="model",
        choices=("model", "gt", "depth"),
        help="model: the bundled RGB-D model (the product's pipeline); gt: the rendering's visible masks "
        "(ideal segmenter); depth: model-free depth segmenter",
    )
    parser.add_argument("--gripper", default="", help="physics gripper override (2f85, 2f140, suction)")
    parser.add_argument("--resolution", default="640x480", help="image size WxH in pixels")
    parser.add_argument("--renderer", default="auto", choices=("auto", "mujoco", "raycast"))
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--workers", type=int, default=1, help="local worker processes")
    group.add_argument(
        "--ray",
        default=None,
        metavar="ADDRESS",
        help="run scenes as Ray tasks: 'auto', 'local' (start one here) or a cluster address",
    )
    parser.add_argument(
        "--retries",
        type=int,
        default=1,
        help="fresh captures (everything fitted anew) before a 'no feasible grasp' ends a scene",
    )
    parser.add_argument(
        "--no-relaxed-plan",
        action="store_true",
        help="no second planning pass with relaxed margins when the planner finds no feasible grasp",
    )
    parser.add_argument(
        "--no-reuse-fits",
        action="store_true",
        help="fit every instance of every frame (default: keep the fits of instances the change detection finds "
        "unchanged since the previous frame)",
    )
    parser.add_argument(
        "--no-pick-unmatched",
        action="store_true",
        help="leave objects whose template fit was rejected as clutter (default: pick them by their measured box)",
    )
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from normpos_grasp.sim.cameras import parse_resolution
    from normpos_grasp.simulate.batch import run_batch, timing_summary, write_results
    from normpos_grasp.simulate.episode import SimulationConfig

    parts = () if args.parts == "default" else tuple(p.strip() for p in args.parts.split(",") if p.strip())
    config = SimulationConfig(
        cell_path=str(args.cell),
        sensor=args.sensor,
        seed=args.seed,
        parts=parts,
        parts_per_scene=args.count,
        segmenter=args.segmenter,
        renderer=args.renderer,
        gripper=args.gripper,
        resolution=parse_resolution(args.resolution),
        perception_retries=args.retries,
        reuse_fits=not args.no_reuse_fits,
        relaxed_plan=not args.no_relaxed_plan,
        pick_unmatched=not args.no_pick_unmatched,
    )
    bar = tqdm(total=args.scenes, unit="scene", disable=args.no_progress)

    def progress(done: int, total: int) -> None:
        bar.n = done
        bar.refresh()

    t0 = time.perf_counter()
    try:
        result = run_batch(config, args.scenes, workers=args.workers, ray_address=args.ray, progress=progress)
    finally:
        bar.close()
    wall = time.perf_counter() - t0
    timing = timing_summary(result, wall)
    summary = write_results(result, args.out, timing)
    print(
        json.dumps(
            {k: summary[k] for k in ("picks_attempted", "picks_succeeded", "success_rate", "failures_by_cause")},
            indent=1,
        )
    )
    print(
        f"{timing['picks']} picks in {wall:.1f} s ({timing['picks_per_minute']:.1f} picks/min); results in {args.out}"
    )
    return 0
