"""`normpos-grasp train-segmenter`: generate synthetic training scenes and train the bundled segmentation model."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from tqdm import tqdm

from normpos_grasp.cli.args import add_library_args, float_in, library_from_args, library_paths
from normpos_grasp.errors import InputError

logger = logging.getLogger(__name__)


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"expected WxH like 256x192, got {text!r}") from exc
    return h, w


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "train-segmenter",
        help="teach the bundled segmentation model a part library (--library, CPU, no extra) or train it anew",
        description=(
            "With --library: teach the bundled model the library's labels it lacks by refitting its output heads on "
            "its frozen trunk (numpy and scipy, minutes on 2 cores, within --time-limit-min, default 10): bins of "
            "--cell with the new parts mixed with the built-in ones, a confidence threshold chosen on held-back "
            "seeds, OUT/normpos_seg.onnx and OUT/MODEL_CARD.md. Without --library: render synthetic scenes (D435 "
            "noise) into OUT/data (resumable), train the YOLACT-style model on CPU (the train extra, torch) and "
            "export OUT/normpos_seg.onnx in the YOLOv8-seg layout. The same --seed and --scenes give the same model."
        ),
    )
    add_library_args(p, default_help="none: train the whole model on the built-in parts")
    p.add_argument("--val-scenes", type=int, default=20, help="with --library: held-back bins to validate on")
    p.add_argument("--val-first-seed", type=int, default=560000, help="with --library: seed of the first of them")
    p.add_argument("--base-model", type=Path, default=None, help="with --library: the ONNX model to teach (bundled)")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument("--seed", type=int, default=0, help="training seed (weights, order, augmentation)")
    p.add_argument("--data", type=Path, default=None, help="folder of shard_*.npz (default: OUT/data)")
    p.add_argument("--scenes", type=int, default=500, help="scenes to render if data is missing (2 views each)")
    p.add_argument("--first-scene-seed", type=int, default=100000, help="seed of the first training scene")
    p.add_argument("--cell", default=None, help="also render bins of this cell (packaged name or YAML), its camera")
    p.add_argument("--cell-scenes", type=int, default=0, help="cell bins to render (2 frames each: full, picked)")
    p.add_argument("--cell-first-seed", type=int, default=300000, help="seed of the first cell bin")
    p.add_argument("--frame-scenes", type=int, default=0, help="extra generate_frame scenes (1 frame each)")
    p.add_argument("--frame-first-seed", type=int, default=310000, help="seed of the first generate_frame scene")
    p.add_argument("--extra-scenes", type=int, default=0, help="more scenes like --scenes into an existing data folder")
    p.add_argument("--extra-first-seed", type=int, default=200000, help="seed of the first --extra-scenes scene")
    p.add_argument("--pile-scenes", type=int, default=0, help="extra dense-pile scenes (2 views each, pile_samples)")
    p.add_argument("--pile-first-seed", type=int, default=400000, help="seed of the first dense-pile scene")
    p.add_argument("--steps", type=int, default=3000, help="optimiser steps")
    p.add_argument("--batch", type=int, default=16, help="images per step")
    p.add_argument("--lr", type=float_in(1e-7, 1.0), default=4e-3, help="peak learning rate")
    p.add_argument("--input-size", type=_size, default=(192, 256), help="network input WxH (multiples of 32)")
    p.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    p.add_argument("--init-from", type=Path, default=None, help="start from this .pt state dict (fine-tuning)")
    p.add_argument(
        "--time-limit-min",
        type=float_in(0.0, 1e5, "min"),
        default=0.0,
        help="stop training after this many minutes (0: none)",
    )
    p.add_argument("--checkpoint-every", type=int, default=0, help="save OUT/normpos_seg.pt every N steps (0: at end)")
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    if library_paths(args):
        return _teach_library(args)
    from functools import partial

    from normpos_grasp.training.data import cell_samples, frame_samples, pile_samples
    from normpos_grasp.training.trainer import TrainOptions, generate_sample_shards, generate_shards, train

    h, w = args.input_size
    if h % 32 or w % 32:
        raise InputError(f"--input-size must be multiples of 32, got {w}x{h}")
    data = args.data or args.out / "data"
    if args.data is None or not any(Path(data).glob("shard_*.npz")):
        seeds = range(args.first_scene_seed, args.first_scene_seed + args.scenes)
        with tqdm(total=len(seeds), desc="rendering scenes", unit="scene") as bar:
            generate_shards(Path(data), seeds, (h, w), progress=bar.update)
    if args.cell_scenes > 0:
        if args.cell is None:
            raise InputError("--cell-scenes needs --cell (a packaged cell name or a cell YAML)")
        from normpos_grasp.cell import resolve_cell

        cell = resolve_cell(args.cell)
        seeds = range(args.cell_first_seed, args.cell_first_seed + args.cell_scenes)
        with tqdm(total=len(seeds), desc="rendering cell bins", unit="scene") as bar:
            generate_sample_shards(Path(data), "cell", seeds, (h, w), partial(cell_samples, cell), progress=bar.update)
    if args.frame_scenes > 0:
        seeds = range(args.frame_first_seed, args.frame_first_seed + args.frame_scenes)
        with tqdm(total=len(seeds), desc="rendering frames", unit="scene") as bar:
            generate_sample_shards(Path(data), "frame", seeds, (h, w), frame_samples, progress=bar.update)
    if args.extra_scenes > 0:
        seeds = range(args.extra_first_seed, args.extra_first_seed + args.extra_scenes)
        with tqdm(total=len(seeds), desc="rendering more scenes", unit="scene") as bar:
            generate_shards(Path(data), seeds, (h, w), progress=bar.update)
    if args.pile_scenes > 0:
        seeds = range(args.pile_first_seed, args.pile_first_seed + args.pile_scenes)
        with tqdm(total=len(seeds), desc="rendering piles", unit="scene") as bar:
            generate_sample_shards(Path(data), "pile", seeds, (h, w), pile_samples, progress=bar.update)
    options = TrainOptions(
        input_hw=(h, w),
        steps=args.steps,
        batch=args.batch,
        lr=args.lr,
        threads=args.threads,
        seed=args.seed,
        time_limit_s=args.time_limit_min * 60.0,
        init_from=str(args.init_from) if args.init_from is not None else "",
        checkpoint_every=args.checkpoint_every,
    )
    path = train(Path(data), args.out, options, log=lambda msg: tqdm.write(msg))
    print(f"model written to {path}")
    return 0


def _teach_library(args: argparse.Namespace) -> int:
    """`train-segmenter --library`: the head refit (`training.head_tune.tune_segmenter`), its figures printed."""
    from normpos_grasp.cell import resolve_cell
    from normpos_grasp.templates.library import resolve_library
    from normpos_grasp.training.head_tune import tune_segmenter

    if args.scenes < 1 or args.val_scenes < 1:
        raise InputError("--scenes and --val-scenes must be at least 1")
    library = list(library_from_args(args))
    names = {t.name for t in library}
    library += [t for t in resolve_library(["builtin"]) if t.name not in names]  # mixed with the built-in parts
    cell = resolve_cell(args.cell or "ur5e_bin_parallel")
    budget_s = (args.time_limit_min or 10.0) * 60.0
    report = tune_segmenter(
        library,
        args.out,
        cell,
        scenes=args.scenes,
        val_scenes=args.val_scenes,
        first_seed=args.first_scene_seed,
        val_first_seed=args.val_first_seed,
        budget_s=budget_s,
        base_model=args.base_model,
        log=print,
    )
    print(f"taught {', '.join(report.new_labels)}: {report.frames} frames, threshold {report.conf_threshold:.2f}")
    for k, f in report.figures.items():
        print(f"  {k}: recall {f['recall']:.3f}, precision {f['precision']:.3f}, mask IoU {f['mean_iou']:.3f} "
              f"({f['gt']:.0f} true instances, held-back seeds)")  # fmt: skip
    print(f"model written to {report.model_path} (card: {report.model_path.parent / 'MODEL_CARD.md'})")
    return 0
