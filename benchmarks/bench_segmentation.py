"""Segmentation benchmark on held-out synthetic scenes (seeds disjoint from training), D435 noise, 640x480.

Prints, for the bundled ONNX model and for DepthSegmenter: recall and precision at mask IoU 0.5 (ground truth with
>= 400 visible pixels and visible fraction >= 0.3; predictions matching only smaller / more occluded parts are not
counted), mean IoU of matches, class accuracy (model), for the model with and without its full-resolution mask
refinement (normpos_grasp.perception.mask_refine), and latency per 640x480 frame (median wall and CPU time
over repeats, onnxruntime / numpy limited to 2 threads).

    .venv/bin/python benchmarks/bench_segmentation.py --frames 40
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import pickle
import time
from dataclasses import replace
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "2")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "2")

import numpy as np

from normpos_grasp.perception.base import Segmenter
from normpos_grasp.perception.depth_segmenter import DepthSegmenter, DepthSegmenterOptions
from normpos_grasp.perception.onnx_segmenter import OnnxSegmenter
from normpos_grasp.training.data import Sample, synth_samples
from normpos_grasp.training.metrics import MatchStats

SCENE_SETS: dict[str, dict[str, object]] = {
    "mixed": {},  # container, count, clutter and stacking drawn per seed, as in training
    "separated": {"clutter": 0.0, "stack_layers": 1, "count": 6},
    "touching": {"clutter": 1.0, "stack_layers": 1, "count": 8},
}


def scenes(name: str, first_seed: int, frames: int, cache: Path | None) -> list[Sample]:
    """Held-out samples of one set; with `cache`, stored there (pickle) and reused on the next run."""
    path = cache / f"{name}_{first_seed}_{frames}.pkl" if cache is not None else None
    if path is not None and path.exists():
        with path.open("rb") as fh:
            return list(pickle.load(fh))
    samples = [synth_samples(first_seed + i, views=1, **SCENE_SETS[name])[0] for i in range(frames)]  # type: ignore[arg-type]
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        with path.open("wb") as fh:
            pickle.dump(samples, fh)
    return samples


def evaluate(seg: Segmenter, samples: list[Sample]) -> MatchStats:
    stats = MatchStats()
    for s in samples:
        stats.add(seg.segment(s.frame), s.instances, s.visib_fract)
    return stats


def latency(seg: Segmenter, samples: list[Sample], repeats: int) -> tuple[float, float]:
    """Median wall and CPU milliseconds per frame."""
    wall, cpu = [], []
    seg.segment(samples[0].frame)
    for k in range(repeats):
        f = samples[k % len(samples)].frame
        t0, c0 = time.perf_counter(), time.process_time()
        seg.segment(f)
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return float(np.median(wall) * 1e3), float(np.median(cpu) * 1e3)


def report(name: str, stats: MatchStats, lat: tuple[float, float], labels: bool) -> None:
    line = (
        f"{name:28s} gt {stats.gt:4d} pred {stats.pred:4d} recall {stats.recall:.3f} "
        f"precision {stats.precision:.3f} mean IoU {stats.mean_iou:.3f}"
    )
    if labels:
        line += f" class acc {stats.class_accuracy:.3f}"
    print(f"{line} | latency median {lat[0]:.1f} ms wall, {lat[1]:.1f} ms CPU")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=40, help="frames per scene set")
    parser.add_argument("--first-seed", type=int, default=900000, help="first held-out scene seed")
    parser.add_argument("--model", default=None, help="ONNX model (default: the bundled one)")
    parser.add_argument("--repeats", type=int, default=30, help="latency repeats")
    parser.add_argument("--cache", type=Path, default=None, help="folder to keep the rendered scenes in")
    parser.add_argument("--skip-model", action="store_true")
    parser.add_argument("--skip-unrefined", action="store_true", help="no rows for the model without mask refinement")
    parser.add_argument("--skip-depth", action="store_true")
    parser.add_argument(
        "--depth-option",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="a DepthSegmenterOptions field for the depth rows, e.g. --depth-option stride=2 (repeatable)",
    )
    args = parser.parse_args()
    print(f"cpu count {os.cpu_count()}, load average {os.getloadavg()[0]:.1f} (timings are inflated when loaded)")
    sets = {
        name: scenes(name, args.first_seed + 10000 * i, args.frames, args.cache) for i, name in enumerate(SCENE_SETS)
    }
    if not args.skip_model:
        model = OnnxSegmenter(args.model)
        # the same model without the full-resolution mask refinement (masks from the upsampled prototypes only)
        raw = OnnxSegmenter(args.model, options=replace(model.options, refine_masks=False))
        for name, samples in sets.items():
            report(f"model / {name}", evaluate(model, samples), latency(model, samples, args.repeats), True)
            if not args.skip_unrefined:
                report(f"model unrefined / {name}", evaluate(raw, samples), latency(raw, samples, args.repeats), True)
    if not args.skip_depth:
        fields = {f.name: f.type for f in dataclasses.fields(DepthSegmenterOptions)}
        overrides: dict[str, object] = {}
        for item in args.depth_option:
            name, _, value = item.partition("=")
            if name not in fields:
                parser.error(f"--depth-option {item!r}: no DepthSegmenterOptions field {name!r}")
            kind = str(fields[name])
            overrides[name] = value.lower() in ("1", "true", "yes") if kind == "bool" else float(value)
            if kind == "int":
                overrides[name] = int(value)
        depth = DepthSegmenter(DepthSegmenterOptions(**overrides))  # type: ignore[arg-type]
        for name, samples in sets.items():
            report(f"depth / {name}", evaluate(depth, samples), latency(depth, samples, args.repeats), False)


if __name__ == "__main__":
    main()
