"""`normpos-grasp demo`: the whole product on embedded defaults, with a report folder to look at."""

from __future__ import annotations

import argparse
from typing import Any

from normpos_grasp.cell.config import BUILTIN_CELLS
from normpos_grasp.cli.args import add_library_args, int_in, library_from_args, library_paths, part_names
from normpos_grasp.demo import DemoOptions, run_demo
from normpos_grasp.loop import PickRecord


def register(sub: Any) -> None:
    parser = sub.add_parser(
        "demo",
        help="synthesise a bin, measure, fit, plan and pick on the loopback UR controller; write a report",
        description="Synthesise a bin scene in a packaged cell, then capture, segment, measure, fit, plan and execute "
        "picks on the loopback UR controller (real ur_rtde client) until the bin is empty or nothing is reachable.",
    )
    parser.add_argument("--out", default="demo_out", help="report folder (default: demo_out)")
    parser.add_argument("--cell", default="ur5e_bin_parallel", help=f"cell YAML or one of: {', '.join(BUILTIN_CELLS)}")
    parser.add_argument("--seed", type=int, default=0, help="scene seed")
    parser.add_argument("--parts", type=int_in(1, 50), default=4, help="parts dropped into the bin, 1..50")
    parser.add_argument("--part-names", default="", help="comma-separated part names to drop (default: all)")
    add_library_args(parser)
    parser.add_argument("--max-picks", type=int_in(1, 1000), default=8, help="most picks to attempt, 1..1000")
    parser.add_argument(
        "--segmenter",
        choices=("model", "depth", "gt"),
        default="model",
        help="model: the bundled ONNX model (depth if it is missing); depth: model-free; gt: the synthetic truth masks",
    )
    parser.add_argument("--no-emulator", action="store_true", help="use the simulated driver instead of the emulator")
    parser.add_argument("--emulator-host", default="127.0.0.1", help="loopback address for the emulator (127.x.y.z)")
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    options = DemoOptions(
        cell=args.cell,
        seed=args.seed,
        parts=args.parts,
        max_picks=args.max_picks,
        segmenter=args.segmenter,
        use_emulator=not args.no_emulator,
        emulator_host=args.emulator_host,
        part_names=part_names(args.part_names, "--part-names"),
        library=library_paths(args),
    )
    library = library_from_args(args)  # a bad library or an unknown part is refused before the demo starts
    if options.part_names:
        library.subset(options.part_names)
    bar = tqdm(total=None, desc="demo", unit=" step", leave=False)

    def on_step(message: str) -> None:
        bar.set_description(message)
        bar.update(1)

    def on_pick(record: PickRecord) -> None:
        plan = record.plan_json or {}
        target = (plan.get("target") or {}).get("template", "-")
        bar.write(f"pick {record.index + 1}: {record.status} ({record.check}), target {target}")
        if record.fault:
            bar.write(f"  fault: {record.fault}")

    try:
        result = run_demo(args.out, options, on_step, on_pick)
    finally:
        bar.close()
    summary = result.summary
    print(f"driver: {result.driver} - {result.driver_note}")
    print(f"segmenter: {result.segmenter}")
    rows = summary["picks"]
    if rows:
        keys = list(rows[0])
        widths = {k: max(len(k), *(len(str(r.get(k, ""))) for r in rows)) for k in keys}
        print("  ".join(k.ljust(widths[k]) for k in keys))
        for r in rows:
            print("  ".join(str(r.get(k, "")).ljust(widths[k]) for k in keys))
    print(
        f"picked {summary['picks_succeeded']} of {summary['picks_attempted']} attempted; "
        f"{summary['parts_left_in_bin']} parts left; {summary['wall_time_s']} s"
    )
    for k, push in enumerate(summary.get("pushes", [])):
        print(f"push {k + 1} after pick {push['after_pick']}: {push['outcome']}, push {push['push_m']} m")
    print(f"stopped: {summary['stop']}")
    print(f"report: {result.files['report']}  (3D twin: {result.files['scene']})")
    faults = [r.fault for r in result.records if r.status in ("driver_fault", "unsafe_plan")]
    if faults:
        print(f"the loop stopped on a fault: {faults[-1]}")
        return 1
    return 0
