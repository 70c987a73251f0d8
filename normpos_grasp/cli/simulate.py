"""`normpos-grasp simulate`: offline grasp simulation of a cell over synthetic bin scenes, judged by physics.

The run folder --out receives manifest.json (the run's parameters) first, scenes/scene_NNNNNN.json as each
scene finishes, and picks.csv, the plots, timing.json and summary.json (last: the run is complete) at the end.
SIGINT / SIGTERM end the worker processes, keep the finished scenes and exit 130 / 143; `--resume` runs the
remaining scenes of such a run (refused when the parameters differ) and gives the same picks.csv, summary.json
and plots as an uninterrupted run. An --out that holds files is refused unless --overwrite or --resume.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import time
from pathlib import Path
from typing import Any

from normpos_grasp.cli.args import (
    OVERWRITE_HELP,
    add_library_args,
    check_out_dir,
    int_in,
    library_from_args,
    library_paths,
    part_names,
)
from normpos_grasp.sim.sensor import SENSOR_PRESETS

#: bounds of the numeric options (a larger value is refused with this range)
MAX_SCENES = 100_000
MAX_COUNT = 100
MAX_WORKERS = 256
MAX_RETRIES = 10
MIN_SIDE, MAX_SIDE = 16, 4096


def register(subparsers: Any) -> None:
    parser = subparsers.add_parser(
        "simulate",
        help="simulate bin clearing offline: real pipeline on rendered noisy frames, grasps checked in physics",
        description="For each synthetic scene, render the cell's bin through the sensor model, run segmentation, "
        "measurement, template fitting and pick planning on the noisy frame, validate the chosen grasp in MuJoCo "
        "against the true part poses, and repeat until the bin is cleared. Writes manifest.json, one file per "
        "finished scene under scenes/, and at the end picks.csv, timing.json, PNG plots and summary.json to "
        "--out. An interrupted run (Ctrl-C, SIGTERM) keeps its finished scenes: continue it with --resume.",
    )
    parser.add_argument("--cell", required=True, help="cell YAML or packaged cell name (needs a bin and a camera pose)")
    parser.add_argument("--scenes", type=int_in(1, MAX_SCENES), default=10, help=f"number of scenes, 1..{MAX_SCENES}")
    parser.add_argument("--sensor", default="d435", choices=sorted(SENSOR_PRESETS), help="sensor model preset")
    parser.add_argument("--seed", type=int_in(0, 2**32 - 1), default=0, help="batch seed (scenes are seeded from it)")
    parser.add_argument("--out", required=True, help="output folder (must be empty or absent, see --overwrite)")
    parser.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    parser.add_argument(
        "--resume",
        action="store_true",
        help="continue the interrupted run in --out: its finished scenes are kept, the others run (the other "
        "options must be those of the first command; --workers / --ray may differ; with --overwrite too, a "
        "folder without a run is replaced)",
    )
    add_library_args(parser)
    parser.add_argument("--parts", default="default", help="'default' or comma-separated part names")
    parser.add_argument("--count", type=int_in(1, MAX_COUNT), default=8, help=f"parts per scene, 1..{MAX_COUNT}")
    parser.add_argument(
        "--segmenter",
        default="model",
        choices=("model", "gt", "depth"),
        help="model: the bundled RGB-D model (the product's pipeline); gt: the rendering's visible masks "
        "(ideal segmenter); depth: model-free depth segmenter",
    )
    parser.add_argument("--gripper", default="", help="physics gripper override (2f85, 2f140, suction)")
    parser.add_argument(
        "--resolution", default="640x480", help=f"image size WxH in pixels, each side {MIN_SIDE}..{MAX_SIDE}"
    )
    parser.add_argument("--renderer", default="auto", choices=("auto", "mujoco", "raycast"))
    group = parser.add_mutually_exclusive_group()
    group.add_argument(
        "--workers", type=int_in(1, MAX_WORKERS), default=1, help=f"local worker processes, 1..{MAX_WORKERS}"
    )
    group.add_argument(
        "--ray",
        default=None,
        metavar="ADDRESS",
        help="run scenes as Ray tasks: 'auto', 'local' (start one here) or a cluster address",
    )
    parser.add_argument(
        "--retries",
        type=int_in(0, MAX_RETRIES),
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
    parser.add_argument(
        "--no-drags",
        action="store_true",
        help="only push parts when no grasp is feasible (default: also drag parts out from walls and corners)",
    )
    parser.add_argument(
        "--no-uncovered",
        action="store_true",
        help="plan with what was segmented only (default: surfaces no instance covers are obstacles too, "
        "measure.uncovered)",
    )
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from normpos_grasp.simulate.signals import Interrupted, signals_raise

    try:
        with signals_raise():  # from here on SIGTERM, like Ctrl-C, ends the run with one line
            return _run(args)
    except Interrupted as exc:
        done = f" with {exc.finished} of {exc.total} scenes finished (kept in {Path(args.out) / 'scenes'})"
        print(
            f"normpos-grasp simulate: interrupted by {signal.Signals(exc.signum).name}{done if exc.total else ''}; "
            "run the same command with --resume to continue",
            file=sys.stderr,
        )
        return exc.exit_code


def _run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from normpos_grasp.cell.config import resolve_cell
    from normpos_grasp.errors import InputError, SimulationError
    from normpos_grasp.sim.cameras import parse_resolution
    from normpos_grasp.simulate.batch import (
        BatchResult,
        RunFolder,
        format_breakdown,
        run_batch,
        run_parameters,
        timing_summary,
        write_results,
    )
    from normpos_grasp.simulate.episode import SimulationConfig, gripper_spec

    resolution = parse_resolution(args.resolution)
    if not all(MIN_SIDE <= side <= MAX_SIDE for side in resolution):
        raise InputError(f"--resolution: each side must lie in {MIN_SIDE}..{MAX_SIDE} pixels, got {args.resolution}")
    parts = part_names(args.parts)
    cell = resolve_cell(args.cell)  # the input is read and checked before anything is written
    libraries = tuple(p if p == "builtin" else str(Path(p).resolve()) for p in library_paths(args))
    library = library_from_args(args)  # an unknown part or a bad library is refused before anything is written
    if parts:
        library.subset(parts)
    config = SimulationConfig(
        library=libraries,
        cell_path=str(cell.source),
        sensor=args.sensor,
        seed=args.seed,
        parts=parts,
        parts_per_scene=args.count,
        segmenter=args.segmenter,
        renderer=args.renderer,
        gripper=args.gripper,
        resolution=resolution,
        perception_retries=args.retries,
        reuse_fits=not args.no_reuse_fits,
        relaxed_plan=not args.no_relaxed_plan,
        pick_unmatched=not args.no_pick_unmatched,
        drags=not args.no_drags,
        uncovered=not args.no_uncovered,
    )
    if cell.bin is None or (cell.world_from_camera is None and cell.wrist_camera is None):
        raise InputError(
            f"--cell {args.cell}: simulate needs a cell with a bin and a camera pose "
            f"({'no bin' if cell.bin is None else 'no camera pose'})"
        )
    gripper_spec(cell, args.gripper)  # an unknown --gripper is refused here, not in the workers
    params = run_parameters(config, args.scenes)
    out = Path(args.out)
    folder = RunFolder(out)
    done = {}
    if args.resume and folder.started:
        folder.check_resume(params)
        if folder.complete:
            print(f"the run in {out} is already complete (summary.json); nothing to resume")
            return 0
        done = folder.load_scenes(args.scenes)
    else:
        if args.resume and not args.overwrite and out.is_dir() and any(out.iterdir()):
            raise InputError(f"--resume: {out} holds files but no simulate run (no manifest.json)")
        check_out_dir(out, args.overwrite)
        folder.clear()
        folder.start(params)
    bar = tqdm(total=args.scenes, initial=len(done), unit="scene", disable=args.no_progress)

    def progress(finished: int, _total: int) -> None:
        bar.n = finished
        bar.refresh()

    t0 = time.perf_counter()
    try:
        run_batch(
            config,
            args.scenes,
            workers=args.workers,
            ray_address=args.ray,
            progress=progress,
            done=done,
            on_scene=folder.write_scene,
        )
    finally:
        bar.close()
    wall = time.perf_counter() - t0
    scenes = folder.load_scenes(args.scenes)  # the written files are the results: one path, resumed or not
    if len(scenes) != args.scenes:
        missing = sorted(set(range(args.scenes)) - set(scenes))[:5]
        raise SimulationError(f"{folder.scenes_dir}: scenes {missing} missing after the run; run with --resume")
    result = BatchResult(config, tuple(scenes[i] for i in range(args.scenes)))
    timing = timing_summary(result, wall, resumed=tuple(done))
    summary = write_results(result, out, timing)
    print(
        json.dumps(
            {k: summary[k] for k in ("picks_attempted", "picks_succeeded", "success_rate", "failures_by_cause")},
            indent=1,
        )
    )
    from normpos_grasp.simulate.trace import format_cause_table

    print(format_cause_table(summary["causes"]))
    print(format_breakdown(summary))
    print(
        f"{timing['picks']} picks in {wall:.1f} s ({timing['picks_per_minute']:.1f} picks/min"
        + (f"; {len(done)} scenes resumed" if done else "")
        + f"); results in {out}"
    )
    return 0
