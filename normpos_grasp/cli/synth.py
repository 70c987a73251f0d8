"""`normpos-grasp synth`: write a synthetic BOP dataset (parts dropped into a bin, rendered with a sensor model)."""

from __future__ import annotations

import argparse
import time
from typing import Any

from normpos_grasp.sim.cameras import parse_resolution
from normpos_grasp.sim.scene import CONTAINERS, SceneOptions
from normpos_grasp.sim.sensor import SENSOR_PRESETS


def register(subparsers: Any) -> None:
    parser = subparsers.add_parser(
        "synth",
        help="generate a synthetic BOP dataset of parts in a bin",
        description="Drop parts into a bin/table/conveyor with MuJoCo physics, render RGB-D views through a "
        "sensor model and write a BOP dataset (models, rgb, depth, masks, GT poses, camera extrinsics).",
    )
    parser.add_argument("--out", required=True, help="output dataset folder")
    parser.add_argument("--scenes", type=int, default=1, help="number of scenes (physics drops)")
    parser.add_argument("--frames", type=int, default=1, help="camera views per scene")
    parser.add_argument("--sensor", default="d435", choices=sorted(SENSOR_PRESETS), help="sensor model preset")
    parser.add_argument("--resolution", default="640x480", help="image size WxH in pixels")
    parser.add_argument("--parts", default="default", help="'default' or comma-separated part names")
    parser.add_argument("--count", type=int, default=10, help="parts per scene")
    parser.add_argument("--container", default="bin", choices=CONTAINERS)
    parser.add_argument("--clutter", type=float, default=0.3, help="0 spread out .. 1 piled in the centre")
    parser.add_argument("--layers", type=int, default=2, help="drop layers (more = more stacking)")
    parser.add_argument("--renderer", default="auto", choices=("auto", "mujoco", "raycast"))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from normpos_grasp.sim.dataset import write_bop_dataset

    resolution = parse_resolution(args.resolution)
    parts = None if args.parts in ("", "default") else [p.strip() for p in args.parts.split(",") if p.strip()]
    scene = SceneOptions(count=args.count, container=args.container, clutter=args.clutter, stack_layers=args.layers)
    total = args.scenes * args.frames
    bar = tqdm(total=total, unit="frame", desc="synth", disable=args.no_progress)
    state = {"done": 0}

    def progress(done: int, _total: int) -> None:
        bar.update(done - state["done"])
        state["done"] = done

    start = time.perf_counter()
    try:
        split = write_bop_dataset(
            args.out,
            args.scenes,
            args.frames,
            sensor=args.sensor,
            resolution=resolution,
            parts=parts,
            seed=args.seed,
            progress=progress,
            scene_options=scene,
            backend=args.renderer,
        )
    finally:
        bar.close()
    elapsed = time.perf_counter() - start
    print(f"wrote {total} frames ({args.scenes} scenes) to {split} in {elapsed:.1f} s")
    return 0
