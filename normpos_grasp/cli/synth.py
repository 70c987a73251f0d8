"""`normpos-grasp synth`: write a synthetic BOP dataset (parts dropped into a bin, rendered with a sensor model).

The dataset is written into a staging folder `.<OUT name>.partial` next to OUT and moved to OUT only when every
scene is complete, so an interrupted or failed run leaves no dataset that readers could take as complete. Each
scene appears in the staging folder at once when finished; SIGINT / SIGTERM keep the finished scenes (exit 130 /
143, one line) and `--resume` continues from them with the same seeds (refused when the options differ), giving
the files of an uninterrupted run. An OUT that already holds files is refused; with --overwrite an earlier
synthetic dataset there is replaced (a folder that does not look like one is still refused).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import shutil
import signal
import sys
import time
from pathlib import Path
from typing import Any

from normpos_grasp.atomic import atomic_write_text
from normpos_grasp.cli.args import (
    OVERWRITE_HELP,
    add_library_args,
    float_in,
    int_in,
    library_from_args,
    library_paths,
    part_names,
)
from normpos_grasp.errors import InputError
from normpos_grasp.sim.cameras import parse_resolution
from normpos_grasp.sim.scene import CONTAINERS, SceneOptions
from normpos_grasp.sim.sensor import SENSOR_PRESETS
from normpos_grasp.simulate.signals import Interrupted, signals_ignored, signals_raise

#: bounds of the numeric options (a larger value is refused with this range)
MAX_SCENES = 10_000
MAX_FRAMES = 1_000
MAX_COUNT = 100
MAX_LAYERS = 10
MIN_SIDE, MAX_SIDE = 16, 4096
#: the options of a run, in its staging folder until the dataset is complete (what --resume checks)
RESUME_FILE = "synth-run.json"


def register(subparsers: Any) -> None:
    parser = subparsers.add_parser(
        "synth",
        help="generate a synthetic BOP dataset of parts in a bin",
        description="Drop parts into a bin/table/conveyor with MuJoCo physics, render RGB-D views through a "
        "sensor model and write a BOP dataset (models, rgb, depth, masks, GT poses, camera extrinsics).",
    )
    parser.add_argument("--out", required=True, help="output dataset folder (must be empty or absent)")
    parser.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP + " (an earlier synth dataset only)")
    parser.add_argument(
        "--resume",
        action="store_true",
        help="continue an interrupted run into the same --out: its finished scenes are kept (the other options "
        "must be those of the first command)",
    )
    parser.add_argument("--scenes", type=int_in(1, MAX_SCENES), default=1,
                        help=f"number of scenes (physics drops), 1..{MAX_SCENES}")  # fmt: skip
    parser.add_argument("--frames", type=int_in(1, MAX_FRAMES), default=1,
                        help=f"camera views per scene, 1..{MAX_FRAMES}")  # fmt: skip
    parser.add_argument("--sensor", default="d435", choices=sorted(SENSOR_PRESETS), help="sensor model preset")
    parser.add_argument("--resolution", default="640x480",
                        help=f"image size WxH in pixels, each side {MIN_SIDE}..{MAX_SIDE}")  # fmt: skip
    add_library_args(parser)
    parser.add_argument("--parts", default="default", help="'default' (every part of the library) or comma-separated "
                        "part names from it")  # fmt: skip
    parser.add_argument("--count", type=int_in(0, MAX_COUNT), default=10,
                        help=f"parts per scene, 0..{MAX_COUNT}")  # fmt: skip
    parser.add_argument("--container", default="bin", choices=CONTAINERS)
    parser.add_argument("--clutter", type=float_in(0.0, 1.0), default=0.3,
                        help="0 spread out .. 1 piled in the centre")  # fmt: skip
    parser.add_argument("--layers", type=int_in(1, MAX_LAYERS), default=2,
                        help=f"drop layers (more = more stacking), 1..{MAX_LAYERS}")  # fmt: skip
    parser.add_argument("--renderer", default="auto", choices=("auto", "mujoco", "raycast"))
    parser.add_argument("--seed", type=int_in(0, 2**32 - 1), default=0)
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from normpos_grasp.sim.dataset import write_bop_dataset

    resolution = parse_resolution(args.resolution)
    if not all(MIN_SIDE <= side <= MAX_SIDE for side in resolution):
        raise InputError(f"--resolution: each side must lie in {MIN_SIDE}..{MAX_SIDE} pixels, got {args.resolution}")
    parts = list(part_names(args.parts)) or None
    library = library_from_args(args)
    if parts is not None:
        library.subset(parts)  # an unknown name is refused (listing the library) before anything is written
    scene = SceneOptions(count=args.count, container=args.container, clutter=args.clutter, stack_layers=args.layers)
    out = Path(args.out)
    staging = out.parent / f".{out.name}.partial"
    params = {
        "scenes": args.scenes,
        "frames": args.frames,
        "sensor": args.sensor,
        "resolution": list(resolution),
        "parts": parts,
        "scene": {"count": args.count, "container": args.container, "clutter": args.clutter, "layers": args.layers},
        "renderer": args.renderer,
        "seed": args.seed,
    }
    if library_paths(args):  # recorded only when given, so runs without it keep their earlier record
        params["library"] = [p if p == "builtin" else str(Path(p).resolve()) for p in library_paths(args)]
    resume = args.resume and (staging / RESUME_FILE).is_file()
    if args.resume and not resume and (out / "parts.json").is_file() and not staging.exists():
        print(f"the dataset in {out} is already complete (parts.json); nothing to resume")
        return 0
    replace_old = _check_out(out, args.overwrite)
    if resume:
        _check_resume(staging, params)
    else:
        if staging.exists():  # left by an interrupted run: never complete, never read
            shutil.rmtree(staging)
        staging.mkdir(parents=True)
        atomic_write_text(staging / RESUME_FILE, json.dumps(params, indent=1) + "\n")
    total = args.scenes * args.frames
    bars: list[Any] = []  # the bar appears with the first finished frame: input errors print only their line
    state = {"done": 0}

    def progress(done: int, _total: int) -> None:
        if not bars:
            bars.append(tqdm(total=total, unit="frame", desc="synth", disable=args.no_progress))
        bars[0].update(done - state["done"])
        state["done"] = done

    start = time.perf_counter()
    try:
        with signals_raise():
            split = write_bop_dataset(
                staging,
                args.scenes,
                args.frames,
                sensor=args.sensor,
                resolution=resolution,
                parts=parts,
                library=list(library),
                seed=args.seed,
                progress=progress,
                scene_options=scene,
                backend=args.renderer,
                resume=resume,
            )
            with signals_ignored():  # the finished dataset is moved whole
                (staging / RESUME_FILE).unlink()
                _move_into_place(staging, out, replace_old)
    except Interrupted as exc:
        for bar in bars:
            bar.close()
        finished = sum(1 for p in (staging / "train").glob("[0-9]*") if p.is_dir()) if staging.is_dir() else 0
        print(
            f"normpos-grasp synth: interrupted by {signal.Signals(exc.signum).name} with {finished} of "
            f"{args.scenes} scenes finished (kept in {staging}); run the same command with --resume to continue",
            file=sys.stderr,
        )
        return exc.exit_code
    except BaseException:
        with contextlib.suppress(OSError):
            shutil.rmtree(staging)
        raise
    finally:
        for bar in bars:
            bar.close()
    elapsed = time.perf_counter() - start
    print(f"wrote {total} frames ({args.scenes} scenes) to {out / split.name} in {elapsed:.1f} s")
    return 0


def _check_resume(staging: Path, params: dict[str, Any]) -> None:
    """InputError naming the options that differ from those of the interrupted run staged in `staging`."""
    try:
        old = json.loads((staging / RESUME_FILE).read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError):
        old = None
    if not isinstance(old, dict):
        raise InputError(f"--resume: {staging / RESUME_FILE} is not a synth run record; run without --resume")
    diff = [k for k in sorted(set(old) | set(params)) if old.get(k) != params.get(k)]
    if diff:
        shown = ", ".join(f"{k} {json.dumps(old.get(k))} -> {json.dumps(params.get(k))}" for k in diff)
        raise InputError(
            f"--resume: the interrupted run in {staging} was started with other options ({shown}); repeat its "
            "options or run without --resume to start again"
        )


def _check_out(out: Path, overwrite: bool) -> bool:
    """Validate --out before anything is written; True when an earlier dataset there is to be replaced."""
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out} is an existing file; give a folder for the dataset")
    if not out.is_dir() or not any(out.iterdir()):
        return False
    if not overwrite:
        raise InputError(
            f"--out {out} already holds files (an earlier dataset?); pass --overwrite to replace it "
            "or choose an empty folder"
        )
    if not ((out / "parts.json").is_file() or (out / "models" / "models_info.json").is_file()):
        raise InputError(
            f"--out {out} holds files but no synthetic dataset (no parts.json or models/models_info.json); "
            "--overwrite replaces only an earlier synth output: choose another folder"
        )
    return True


def _move_into_place(staging: Path, out: Path, replace_old: bool) -> None:
    """Rename the finished staging folder to `out` (an earlier dataset there is removed after the swap)."""
    if not replace_old:
        if out.is_dir():
            out.rmdir()  # empty (checked before)
        os.replace(staging, out)
        return
    old = out.parent / f".{out.name}.old-{os.getpid()}"
    os.replace(out, old)
    os.replace(staging, out)
    shutil.rmtree(old)
