"""`normpos-grasp estimate SPLIT [--library DIR ...] --out results.csv`: 6D poses in the BOP results format.

For every frame of every scene of a BOP split: segment (bundled ONNX model, depth segmenter or BOP GT
masks, whose obj_ids are matched to the library's parts), measure the norm-positions, fit the templates of the
part library (default: the built-in parts, obj_id 1..8) and write one CSV row per accepted fit, with the
template's own obj_id:
`scene_id,im_id,obj_id,score,R,t,time` (R row-major, 9 values space-separated; t in mm; time in s per
image), which the BOP toolkit scores directly.

The CSV is written under a temporary name and moved into place only when every frame is done, so an error
leaves no (header-only or partial) results file; an existing --out is refused unless --overwrite. A run that
finds instances but accepts no pose says why (the commonest rejection reasons) on stderr.
"""

from __future__ import annotations

import argparse
import csv
import io
import logging
import re
import sys
import time
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

from normpos_grasp.atomic import atomic_write_text
from normpos_grasp.cli.args import (
    add_library_args,
    add_segmenter_args,
    check_out_file,
    float_in,
    int_in,
    library_from_args,
    seg_model_from_args,
)
from normpos_grasp.cli.measure import scene_segmenter
from normpos_grasp.errors import InputError

logger = logging.getLogger(__name__)


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "estimate",
        help="fit CAD templates to a BOP split and write BOP results (CSV)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("split", help="BOP split folder (for example test/) holding numeric scene folders")
    add_library_args(p)
    p.add_argument("--out", required=True, help="results CSV to write (refused when it exists, see --overwrite)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing results CSV")
    add_segmenter_args(p, "auto")
    p.add_argument("--max-frames", type=int_in(0, 1_000_000), default=0,
                   help="stop after this many frames per scene (0 = all)")  # fmt: skip
    p.add_argument("--include-rejected", action="store_true", help="also write rejected fits (score halved)")
    p.add_argument("--depth-bias-mm", type=float_in(-100.0, 100.0, "mm"), default=0.0,
                   help="calibrated sensor depth offset, mm (within +-100)")  # fmt: skip
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from normpos_grasp.io.bop import read_split
    from normpos_grasp.measure.measure import measure_instances
    from normpos_grasp.templates.fit import FitContext, FitOptions, fit_best
    from normpos_grasp.templates.prepared import prepare

    out = check_out_file(Path(args.out), getattr(args, "overwrite", False))
    scenes = read_split(args.split)
    work = [(scene, scene.frame_ids[: args.max_frames] if args.max_frames > 0 else scene.frame_ids) for scene in scenes]
    for scene, ids in work:  # camera entries, depth scales and image headers, before the slow part
        for im_id in ids:
            scene.check_frame(im_id)
    library = library_from_args(args)
    for template in library:  # build the fitter's caches before timing frames
        prepare(template)
    options = FitOptions(depth_bias_m=float(args.depth_bias_mm) / 1000.0)
    n_rows = n_inst = n_frames = 0
    reasons: Counter[str] = Counter()
    unknown: Counter[int] = Counter()
    t_all = time.perf_counter()
    text = io.StringIO()
    writer = csv.writer(text)
    writer.writerow(["scene_id", "im_id", "obj_id", "score", "R", "t", "time"])
    for scene, ids in work:
        choice = scene_segmenter(args.segmenter, scene, seg_model_from_args(args), None, library.labels, library)
        segmenter, args.segmenter_used = choice.segmenter, choice.kind
        for im_id in ids:
            frame = scene.load_frame(im_id)
            t0 = time.perf_counter()
            instances = segmenter.segment(frame)
            normpos = measure_instances(frame, instances)
            ctx = FitContext(frame.camera, frame.depth_m)
            fits = [fit_best(n, library, options, ctx) for n in normpos]
            dt = time.perf_counter() - t0
            n_frames += 1
            n_inst += len(normpos)
            for fit in fits:
                if not fit.accepted:
                    reasons[_reason_kind(fit.reason)] += 1
                if not fit.accepted and not args.include_rejected:
                    logger.info("scene %d im %d: %s rejected: %s", scene.scene_id, im_id, fit.template.name, fit.reason)
                    continue
                writer.writerow(_row(scene.scene_id, im_id, fit, frame.camera, dt))
                n_rows += 1
        seen = getattr(segmenter, "unknown", None)  # the 'gt' segmenter's obj_ids outside the library
        if isinstance(seen, dict):  # (a class-agnostic model's `unknown` is a method: a taught library)
            unknown.update(seen)
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out, text.getvalue())
    print(
        f"estimate: {n_rows} poses from {n_inst} instances in {n_frames} frames "
        f"({time.perf_counter() - t_all:.1f} s) -> {out}"
    )
    if unknown and n_rows > 0:
        missing = ", ".join(f"{k} (x{v})" for k, v in sorted(unknown.items()))
        print(f"estimate: note: the data's obj_ids {missing} are not in the part library (no pose)", file=sys.stderr)
    if n_rows == 0 and n_inst > 0:
        why = why_none(reasons, unknown, library)
        print(f"estimate: no pose accepted from {n_inst} instances: {why}", file=sys.stderr)
    return 0


def _reason_kind(reason: str) -> str:
    """A rejection reason without its numbers, so that equal causes count together."""
    return re.sub(r"[-+]?\d+(\.\d+)?(e[-+]?\d+)?", "#", reason).strip() or "rejected"


def why_none(reasons: Counter[str], unknown: Counter[int], library: Any) -> str:
    """One line saying why no pose was accepted: obj_ids the library lacks, then the commonest rejection reasons."""
    parts = []
    if unknown:
        ids = ", ".join(f"{k} (x{v})" for k, v in sorted(unknown.items()))
        parts.append(
            f"the data's obj_ids {ids} are not in the part library ({library.describe()}); pass the --library the "
            "data was made from"
        )
    top = "; ".join(f"{n} x {r}" for r, n in reasons.most_common(3))
    if top:
        parts.append(f"fits rejected: {top}")
    return "; ".join(parts) or "every fit was rejected"


def _row(scene_id: int, im_id: int, fit: Any, camera: Any, dt: float) -> list[str]:
    pose = np.asarray(fit.frame_from_object, dtype=np.float64)
    if fit.frame == "world":
        pose = camera.camera_from_world @ pose
    if fit.template.obj_id < 0:
        raise InputError(
            f"template '{fit.template.name}' has no BOP obj_id; add 'obj_id:' to its template.yaml "
            "or load a BOP models folder"
        )
    score = fit.score if fit.accepted else 0.5 * fit.score
    rot = " ".join(f"{v:.8f}" for v in pose[:3, :3].ravel())
    t = " ".join(f"{v:.4f}" for v in pose[:3, 3] * 1000.0)
    return [str(scene_id), str(im_id), str(fit.template.obj_id), f"{score:.5f}", rot, t, f"{dt:.4f}"]
