"""Training / evaluation samples from the synthetic scenes (normpos_grasp.sim): frames with ground-truth instances.

A sample is one rendered view of a settled scene with D435 sensor noise; ground truth are the visible masks of the
parts with their part names as labels. `pack_sample` turns it into the arrays the trainer reads, at the model's
input resolution (letterboxed exactly as `OnnxSegmenter` does at run time).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np

from normpos_grasp.camera.model import RGBDFrame
from normpos_grasp.cell.config import CellConfig
from normpos_grasp.errors import DatasetError
from normpos_grasp.perception.onnx_segmenter import DepthChannelSpec, preprocess
from normpos_grasp.records.instance import Instance
from normpos_grasp.records.template import Template
from normpos_grasp.typing import FloatArray

logger = logging.getLogger(__name__)

CLASS_NAMES: tuple[str, ...] = ("cube", "box", "bar", "cylinder", "sphere", "plate", "bracket", "ring")


@dataclass(frozen=True, eq=False)
class Sample:
    """One frame and its ground truth: instances (visible masks, part names) and their visible fractions (N,)."""

    frame: RGBDFrame
    instances: list[Instance]
    visib_fract: FloatArray


def synth_samples(
    seed: int,
    views: int = 2,
    sensor: str = "d435",
    resolution: tuple[int, int] = (640, 480),
    **scene_overrides: object,
) -> list[Sample]:
    """`views` noisy views of one random scene (container, part count, clutter and stacking drawn from `seed`;
    `scene_overrides` replace SceneOptions fields, for example clutter=1.0, stack_layers=1)."""
    from normpos_grasp.sim.cameras import CameraOptions, sample_camera
    from normpos_grasp.sim.parts import default_part_library
    from normpos_grasp.sim.render import make_renderer
    from normpos_grasp.sim.scene import SceneOptions, compose_scene
    from normpos_grasp.sim.sensor import sensor_preset

    rng = np.random.default_rng(seed)
    container = str(rng.choice(["bin", "bin", "table", "conveyor"]))
    opts = SceneOptions(
        count=int(rng.integers(3, 15)),
        container=container,
        clutter=float(rng.uniform(0.0, 0.8)),
        stack_layers=int(rng.integers(1, 4)),
        seed=int(rng.integers(2**31)),
    )
    if scene_overrides:
        opts = replace(opts, **scene_overrides)  # type: ignore[arg-type]
    layout = compose_scene(opts, default_part_library())
    renderer = make_renderer(layout, resolution[0], resolution[1])
    noise = sensor_preset(sensor)
    out: list[Sample] = []
    try:
        for _ in range(views):
            camera = sample_camera(CameraOptions(resolution=resolution, sensor=sensor), layout.container_centre(), rng)
            ren = renderer.render(camera)
            rgb, depth = noise.apply(ren, camera, rng)
            frame = RGBDFrame(rgb=rgb, depth_m=depth, camera=camera, scene_id=seed)
            inst: list[Instance] = []
            fr = ren.visib_fractions
            keep = []
            for k, name in enumerate(layout.part_names):
                m = ren.masks_visible[k]
                if m.any():
                    inst.append(Instance(mask=m.copy(), label=name, score=1.0, instance_id=len(inst) + 1, source_id=k))
                    keep.append(fr[k])
            out.append(Sample(frame, inst, np.asarray(keep, dtype=np.float64)))
    finally:
        renderer.close()
    return out


def pile_samples(seed: int, views: int = 2, sensor: str = "d435") -> list[Sample]:
    """`views` views of a dense pile (as the benchmark's 'touching' set, but drawn per seed): 5-14 parts dropped
    with clutter 0.8-1.0 into 1-2 layers (container as in `synth_samples`)."""
    rng = np.random.default_rng(seed + 7)
    return synth_samples(
        seed,
        views,
        sensor,
        clutter=float(rng.uniform(0.8, 1.0)),
        stack_layers=int(rng.integers(1, 3)),
        count=int(rng.integers(5, 15)),
    )


def cell_samples(
    cell: CellConfig,
    seed: int,
    sensor: str = "d435",
    library: list[Template] | None = None,
    parts: Sequence[str] = (),
) -> list[Sample]:
    """Two views of a bin of a cell (`normpos_grasp.sim.cell_scene`), seen by the cell's own camera as in the demo:
    2-14 parts (drawn from `seed`; from `parts` of `library` when given, else the built-in parts) dropped into the
    cell's bin, then the same bin with some parts taken out (as after picks)."""
    from normpos_grasp.sim.cell_scene import cell_camera, compose_cell_scene, remove_parts
    from normpos_grasp.sim.dataset import render_frame
    from normpos_grasp.sim.render import make_renderer
    from normpos_grasp.sim.sensor import sensor_preset

    rng = np.random.default_rng(seed)
    layout = compose_cell_scene(cell, int(rng.integers(2, 15)), seed, library, parts)
    camera = cell_camera(cell, sensor)
    noise = sensor_preset(sensor)
    out: list[Sample] = []
    for view in range(2):
        if view == 1:
            if layout.n_parts <= 1:
                break
            take = int(rng.integers(1, layout.n_parts))
            layout = remove_parts(layout, rng.choice(layout.n_parts, size=take, replace=False).tolist())
        renderer = make_renderer(layout, camera.width, camera.height)
        try:
            sf = render_frame(layout, renderer, camera, noise, rng, scene_id=seed, im_id=view)
        finally:
            renderer.close()
        vis = np.array([sf.visib_fractions[i.source_id] for i in sf.instances], dtype=np.float64)
        out.append(Sample(sf.frame, sf.instances, vis))
    return out


def frame_samples(seed: int, sensor: str = "d435", resolution: tuple[int, int] = (640, 480)) -> list[Sample]:
    """One view of a random scene from `normpos_grasp.sim.dataset.generate_frame` (bin, table or conveyor, 3-14
    parts, clutter and stacking drawn from `seed`)."""
    from normpos_grasp.sim.cameras import CameraOptions
    from normpos_grasp.sim.dataset import generate_frame
    from normpos_grasp.sim.scene import SceneOptions

    rng = np.random.default_rng(seed)
    opts = SceneOptions(
        count=int(rng.integers(3, 15)),
        container=str(rng.choice(["bin", "table", "conveyor"])),
        clutter=float(rng.uniform(0.0, 1.0)),
        stack_layers=int(rng.integers(1, 4)),
        seed=seed,
    )
    sf = generate_frame(opts, sensor, CameraOptions(resolution=resolution, sensor=sensor), seed)
    vis = np.array([sf.visib_fractions[i.source_id] for i in sf.instances], dtype=np.float64)
    return [Sample(sf.frame, sf.instances, vis)]


def pack_sample(
    sample: Sample,
    input_hw: tuple[int, int],
    depth_spec: DepthChannelSpec,
    min_pixels: int = 100,
    class_names: Sequence[str] = CLASS_NAMES,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(x (4, H, W) float16, masks (N, H/4, W/4) bool, boxes (N, 4) float32 xyxy input pixels, classes (N,) int64:
    index of the label in `class_names`) for instances with at least `min_pixels` visible pixels."""
    f = sample.frame
    x, lb = preprocess(f.rgb, f.depth_m, input_hw, depth_spec)
    mh, mw = input_hw[0] // 4, input_hw[1] // 4
    masks, boxes, classes = [], [], []
    for inst in sample.instances:
        if inst.pixel_count < min_pixels:
            continue
        ys, xs = np.nonzero(inst.mask)
        box = np.array([xs.min(), ys.min(), xs.max() + 1, ys.max() + 1], np.float64) * lb.scale
        box += [lb.left, lb.top, lb.left, lb.top]
        m = cv2.resize(inst.mask.astype(np.float32), (lb.new_w, lb.new_h), interpolation=cv2.INTER_AREA)
        canvas = np.zeros(input_hw, np.float32)
        canvas[lb.top : lb.top + lb.new_h, lb.left : lb.left + lb.new_w] = m
        small = cv2.resize(canvas, (mw, mh), interpolation=cv2.INTER_AREA) > 0.5
        masks.append(small)
        boxes.append(box)
        classes.append(list(class_names).index(inst.label))
    n = len(masks)
    return (
        x[0].astype(np.float16),
        np.asarray(masks, bool).reshape(n, mh, mw),
        np.asarray(boxes, np.float32).reshape(n, 4),
        np.asarray(classes, np.int64).reshape(n),
    )


def write_shard(path: Path, packed: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]) -> None:
    """Store packed samples in one .npz (masks/boxes/classes concatenated with per-sample offsets)."""
    counts = np.array([len(p[2]) for p in packed], np.int64)
    np.savez(
        path,
        x=np.stack([p[0] for p in packed]),
        masks=np.concatenate([p[1] for p in packed]) if counts.sum() else np.zeros((0, 1, 1), bool),
        boxes=np.concatenate([p[2] for p in packed]),
        classes=np.concatenate([p[3] for p in packed]),
        counts=counts,
    )


def read_shards(folder: Path) -> tuple[np.ndarray, list[np.ndarray], list[np.ndarray], list[np.ndarray]]:
    """All shards of `folder`: x (S, C, H, W) float16 and per-sample lists of masks, boxes, classes."""
    files = sorted(Path(folder).glob("shard_*.npz"))
    if not files:
        raise DatasetError(f"no shard_*.npz files in {folder}; generate data with `normpos-grasp train-segmenter`")
    xs, ms, bs, cs = [], [], [], []
    for f in files:
        d = np.load(f)
        xs.append(d["x"])
        off = np.concatenate([[0], np.cumsum(d["counts"])])
        for i in range(len(d["counts"])):
            ms.append(d["masks"][off[i] : off[i + 1]])
            bs.append(d["boxes"][off[i] : off[i + 1]])
            cs.append(d["classes"][off[i] : off[i + 1]])
    return np.concatenate(xs), ms, bs, cs


def assign_cells(boxes: np.ndarray, masks: np.ndarray, centres: np.ndarray, stride: int) -> np.ndarray:
    """The part each head cell learns, (A,) int64 (-1 none): cells whose centre (`centres` (A, 2), input pixels)
    lies inside the part's mask (`masks` (n, H/4, W/4)) and near its box centre (`boxes` (n, 4) xyxy), the smallest
    part winning; every part gets at least the cell nearest its mask centroid."""
    a = len(centres)
    assign = np.full(a, -1, np.int64)
    best_area = np.full(a, np.inf)
    n = len(boxes)
    mh, mw = masks.shape[1:] if n else (1, 1)
    cx = np.clip((centres[:, 0] / 4).astype(int), 0, mw - 1)
    cy = np.clip((centres[:, 1] / 4).astype(int), 0, mh - 1)
    for g in range(n):
        x1, y1, x2, y2 = boxes[g]
        bw, bh = x2 - x1, y2 - y1
        gx, gy = (x1 + x2) / 2, (y1 + y2) / 2
        inside = masks[g][cy, cx]
        near = (np.abs(centres[:, 0] - gx) < max(stride, 0.35 * bw)) & (
            np.abs(centres[:, 1] - gy) < max(stride, 0.35 * bh)
        )
        cand = inside & near
        if not cand.any():
            ys, xs = np.nonzero(masks[g])
            if len(ys) == 0:
                continue
            mx, my = (xs.mean() + 0.5) * 4, (ys.mean() + 0.5) * 4
            d = (centres[:, 0] - mx) ** 2 + (centres[:, 1] - my) ** 2
            cand = np.zeros(a, bool)
            cand[int(np.argmin(d))] = True
        area = float(masks[g].sum())
        take = cand & (area < best_area)
        assign[take] = g
        best_area[take] = area
    return assign
