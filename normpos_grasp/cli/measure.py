"""`normpos-grasp measure PATH --out OUT [--segmenter model|depth|gt]`: norm-positions of every object in a BOP
scene or split folder.

Output per frame (documented in docs/measurement.md, a public interface):
    OUT/<scene_id:06d>/<im_id:06d>.json            summary (see below)
    OUT/<scene_id:06d>/<im_id:06d>_instances.png   uint16, 0 background, k = instance_id
    OUT/<scene_id:06d>/<im_id:06d>_<instance_id:03d>.ply   points (+ normals) of each object, metres

Every file is written under a temporary name and moved into place when complete. OUT is created only once the
first frame has been read and measured; an OUT that already holds files is refused unless --overwrite.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from normpos_grasp.atomic import atomic_write_bytes, atomic_write_text
from normpos_grasp.cli.args import (
    LIBRARY_HELP,
    OVERWRITE_HELP,
    add_segmenter_args,
    check_out_dir,
    int_in,
    library_from_args,
    library_paths,
    seg_model_from_args,
)
from normpos_grasp.errors import InputError, MeasurementError, NormposError
from normpos_grasp.io.bop import BopScene, is_scene_dir, read_split
from normpos_grasp.measure.depth import MAX_HALF_WINDOW, DepthFillOptions
from normpos_grasp.measure.measure import MeasureOptions, measure_instances, normpos_to_dict
from normpos_grasp.perception.base import Segmenter
from normpos_grasp.records.instance import Instance


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "measure",
        help="measure norm-positions (world surface points per object) in BOP scenes",
        description="Segment every frame of a BOP scene or split folder and measure each object's surface points.",
    )
    p.add_argument("path", type=Path, help="BOP scene folder (with scene_camera.json) or split folder of scenes")
    p.add_argument("--out", type=Path, required=True, help="output folder (created; must be empty or absent)")
    p.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    add_segmenter_args(p, "gt")
    p.add_argument("--library", action="append", metavar="DIR", default=None,
                   help=f"{LIBRARY_HELP}; with it, ground-truth labels are the library's part labels (by obj_id) "
                   "instead of obj_XXXXXX")  # fmt: skip
    p.add_argument("--models-dir", type=Path, default=None, help="BOP models folder to render GT masks when a scene "
                   "has no mask_visib (default: PATH/../models)")  # fmt: skip
    p.add_argument("--frames", type=str, default=None, help="comma-separated image ids (default: all)")
    p.add_argument("--half-window", type=int_in(0, MAX_HALF_WINDOW), default=2,
                   help=f"depth window S in 0..{MAX_HALF_WINDOW}, the window is (2S+1)^2 (default 2)")  # fmt: skip
    p.add_argument("--plain-mean", action="store_true", help="use the paper's plain window mean, not edge-aware")
    p.add_argument("--erode", type=int_in(0, 100), default=0,
                   help="erode masks by this many pixels first, 0..100 (default 0)")  # fmt: skip
    p.add_argument("--no-ply", action="store_true", help="do not write per-object PLY files")
    p.set_defaults(handler=run)


class LibraryLabels:
    """A BOP ground-truth segmenter whose labels ('obj_000101') are the part library's labels of those obj_ids.

    Objects the library does not hold keep their 'obj_XXXXXX' label (their fits are then rejected with a reason
    that names it). `unknown` counts the instances of each such obj_id.
    """

    def __init__(self, inner: Segmenter, library: Any) -> None:
        self.inner = inner
        self.library = library
        self.unknown: dict[int, int] = {}

    def segment(self, frame: Any) -> list[Instance]:
        from dataclasses import replace

        out = []
        for inst in self.inner.segment(frame):
            label = inst.label
            if label.startswith("obj_") and label[4:].isdigit():
                obj_id = int(label[4:])
                mapped = self.library.label_of_obj_id(obj_id)
                if mapped is None:
                    self.unknown[obj_id] = self.unknown.get(obj_id, 0) + 1
                else:
                    label = mapped
            out.append(replace(inst, label=label))
        return out


def scene_segmenter(
    kind: str,
    scene: BopScene,
    seg_model: Path | None,
    models_dir: Path | None,
    labels: Any = (),
    library: Any = None,
) -> Any:
    """`perception.factory.choose_segmenter` for a BOP scene: 'gt' reads the scene's masks (rendered from the models
    in `models_dir` when the scene has no mask_visib); with a part `library` its labels are the library's labels
    of the objects' obj_ids (`LibraryLabels`)."""
    from normpos_grasp.perception.factory import SegmenterChoice, choose_segmenter
    from normpos_grasp.perception.gt import GroundTruthOptions, GroundTruthSegmenter

    md = None if models_dir is None else str(models_dir)
    choice = choose_segmenter(
        kind, seg_model, labels, lambda: GroundTruthSegmenter(scene, GroundTruthOptions(models_dir=md)), library
    )
    if choice.kind == "gt" and library is not None:
        return SegmenterChoice(LibraryLabels(choice.segmenter, library), "gt")
    return choice


def run(args: argparse.Namespace) -> int:
    path: Path = args.path
    out_root = check_out_dir(args.out, getattr(args, "overwrite", False))
    if is_scene_dir(path):
        scenes = [BopScene(path)]
    elif path.is_dir():
        scenes = read_split(path)
    else:
        raise InputError(f"{path} is neither a BOP scene folder nor a split folder")
    frames_filter = None
    if args.frames:
        try:
            frames_filter = {int(x) for x in args.frames.split(",") if x.strip()}
        except ValueError as exc:
            raise InputError(f"--frames must be comma-separated integers, got {args.frames!r}") from exc
    options = MeasureOptions(
        depth=DepthFillOptions(half_window=args.half_window, edge_aware=not args.plain_mean), erode_px=args.erode
    )
    work = [(scene, [i for i in scene.frame_ids if frames_filter is None or i in frames_filter]) for scene in scenes]
    if not any(ids for _, ids in work):
        raise InputError(f"no frames matched in {path}" + (f" for --frames {args.frames}" if args.frames else ""))
    for scene, ids in work:  # camera entries, depth scales and image headers, before anything is written
        for im_id in ids:
            scene.check_frame(im_id)
    library = library_from_args(args) if library_paths(args) else None
    labels = () if library is None else library.labels
    n_frames = n_objects = 0
    for scene, ids in work:
        segmenter: Segmenter | None = None
        out_dir = out_root / f"{scene.scene_id:06d}"
        for im_id in ids:
            if segmenter is None:
                segmenter = scene_segmenter(
                    args.segmenter, scene, seg_model_from_args(args), args.models_dir, labels, library
                ).segmenter
            result = measure_frame(scene, im_id, segmenter, options, out_dir, write_ply=not args.no_ply)
            n_frames += 1
            n_objects += len(result["objects"])
            print(
                f"scene {scene.scene_id:06d} frame {im_id:06d}: {len(result['objects'])} objects, "
                f"{result['timing_ms']['total']:.1f} ms"
            )
    print(f"measured {n_objects} objects in {n_frames} frames -> {out_root}")
    return 0


def measure_frame(
    scene: BopScene, im_id: int, segmenter: Segmenter, options: MeasureOptions, out_dir: Path, write_ply: bool = True
) -> dict[str, Any]:
    """Measure one frame and write its JSON, instance PNG and PLYs into `out_dir`; returns the JSON dict.

    `out_dir` is created only after the frame has been read and measured; each file is written atomically.
    Raises MeasurementError when the segmenter found objects but none of them has usable depth.
    """
    import cv2

    from normpos_grasp.io.ply import write_ply as write_points

    t0 = time.perf_counter()
    frame = scene.load_frame(im_id)
    t1 = time.perf_counter()
    try:
        instances = segmenter.segment(frame)
    except NormposError:
        raise
    t2 = time.perf_counter()
    items = measure_instances(frame, instances, options)
    t3 = time.perf_counter()
    if instances and not items:
        raise MeasurementError(
            f"scene {scene.scene_id} frame {im_id}: none of the {len(instances)} objects has enough valid depth "
            "inside its mask; check the depth image and depth_scale"
        )
    png = instance_image(instances, frame.depth_m.shape)
    ok, buf = cv2.imencode(".png", png)
    if not ok:
        raise InputError("cannot encode the instance image")
    out_dir.mkdir(parents=True, exist_ok=True)
    objects = []
    for item in items:
        points_file = None
        if write_ply:
            points_file = f"{im_id:06d}_{item.instance_id:03d}.ply"
            write_points(out_dir / points_file, item.points, normals=item.normals)
        entry = normpos_to_dict(item, points_file)
        objects.append(entry)
    result: dict[str, Any] = {
        "scene_id": scene.scene_id,
        "im_id": int(im_id),
        "frame": frame.frame_name,
        "objects": objects,
        "timing_ms": {
            "load": round((t1 - t0) * 1000, 3),
            "segment": round((t2 - t1) * 1000, 3),
            "measure": round((t3 - t2) * 1000, 3),
            "total": round((t3 - t0) * 1000, 3),
        },
    }
    atomic_write_bytes(out_dir / f"{im_id:06d}_instances.png", buf.tobytes())
    atomic_write_text(out_dir / f"{im_id:06d}.json", json.dumps(result, indent=2))
    return result


def instance_image(instances: list[Instance], shape: tuple[int, ...]) -> np.ndarray:
    """(H, W) uint16: 0 background, k = instance_id (later instances win where masks overlap)."""
    out = np.zeros(shape[:2], dtype=np.uint16)
    for inst in instances:
        if not 0 < inst.instance_id < 65536:
            raise InputError(f"instance_id must lie in 1..65535 for a uint16 image, got {inst.instance_id}")
        out[inst.mask] = inst.instance_id
    return out
