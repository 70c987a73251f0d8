"""Synthetic scenes placed in a cell: the bin of a cell YAML filled with parts, seen by the cell's camera.

`compose_cell_scene` builds the scene around the origin with the cell's bin dimensions and moves it to the cell's
bin pose, so the rendered frame, the ground truth and the cell's collision geometry share one world frame. A cell
with several bins gets one such scene per bin (the parts shared out in turn), merged into one layout.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from normpos_grasp.camera.model import Camera
from normpos_grasp.cell.config import CellConfig
from normpos_grasp.errors import InputError
from normpos_grasp.records.template import Template
from normpos_grasp.sim.cameras import camera_intrinsics
from normpos_grasp.sim.parts import default_part_library
from normpos_grasp.sim.scene import SceneLayout, SceneOptions, compose_scene
from normpos_grasp.typing import FloatArray


def scene_options_for_cell(cell: CellConfig, count: int, seed: int, parts: Sequence[str] = ()) -> SceneOptions:
    """SceneOptions whose bin matches the cell's bin `cell.bin` (inner size, wall height and thickness)."""
    if cell.bin is None:
        raise InputError(f"cell {cell.name!r} has no bin; synthetic cell scenes need one")
    lx, ly, h = (float(v) for v in cell.bin.inner_size)
    return SceneOptions(
        parts=tuple(parts),
        count=count,
        container="bin",
        bin_inner_size_m=(lx, ly),
        bin_wall_thickness_m=cell.bin.wall_m,
        bin_wall_height_m=h,
        bin_floor_thickness_m=cell.bin.wall_m,
        seed=seed,
    )


def world_from_scene(cell: CellConfig) -> FloatArray:
    """(4, 4) pose of the synthetic scene's frame (table top at z = 0, bin `cell.bin` centred) in the cell's world."""
    if cell.bin is None:
        raise InputError(f"cell {cell.name!r} has no bin")
    pose = np.array(cell.bin.world_from_bin, dtype=np.float64)
    pose[:3, 3] -= pose[:3, 2] * cell.bin.wall_m  # the scene's bin floor sits on its table top
    return pose


def transform_layout(layout: SceneLayout, a_from_scene: FloatArray) -> SceneLayout:
    """A copy of `layout` with every part pose and static box premultiplied by `a_from_scene` (4, 4)."""
    poses = np.einsum("ij,njk->nik", a_from_scene, layout.world_from_object)
    boxes = tuple((name, a_from_scene @ pose, size) for name, pose, size in layout.static_boxes)
    return replace(layout, world_from_object=poses, static_boxes=boxes)


def remove_parts(layout: SceneLayout, indices: Sequence[int]) -> SceneLayout:
    """A copy of `layout` without the parts at `indices` (for example after they were picked)."""
    drop = set(int(i) for i in indices)
    if any(i < 0 or i >= layout.n_parts for i in drop):
        raise InputError(f"part indices {sorted(drop)} out of range for {layout.n_parts} parts")
    keep = [i for i in range(layout.n_parts) if i not in drop]
    return replace(
        layout,
        templates=tuple(layout.templates[i] for i in keep),
        world_from_object=layout.world_from_object[keep].copy(),
    )


def compose_cell_scene(
    cell: CellConfig,
    count: int,
    seed: int,
    library: list[Template] | None = None,
    parts: Sequence[str] = (),
) -> SceneLayout:
    """Drop `count` parts into the cell's bin (physics-settled, seeded) and return the layout in the cell's world.

    Several bins: bin k gets parts k, k + n, ... of the `count` (seed + k for its scene); the merged layout keeps the
    first scene's table and every bin's walls (the later bins' boxes renamed '<box>@<bin>')."""
    lib = default_part_library() if library is None else library
    if len(cell.bins) <= 1:
        options = scene_options_for_cell(cell, count, seed, parts)
        return transform_layout(compose_scene(options, lib), world_from_scene(cell))
    layouts = []
    for k, b in enumerate(cell.bins):
        n = count // len(cell.bins) + (1 if k < count % len(cell.bins) else 0)
        one = cell.picking_from(b.name)
        options = scene_options_for_cell(one, max(n, 1), seed + k, parts)
        layout = transform_layout(compose_scene(options, lib), world_from_scene(one))
        if n == 0:
            layout = remove_parts(layout, range(layout.n_parts))
        layouts.append((b.name, layout))
    first = layouts[0][1]
    boxes = list(first.static_boxes)
    for name, layout in layouts[1:]:
        boxes.extend((f"{box}@{name}", pose, size) for box, pose, size in layout.static_boxes if box != "table")
    return replace(
        first,
        templates=tuple(t for _, layout in layouts for t in layout.templates),
        world_from_object=np.concatenate([layout.world_from_object.reshape(-1, 4, 4) for _, layout in layouts]),
        static_boxes=tuple(boxes),
        max_penetration_m=max(layout.max_penetration_m for _, layout in layouts),
        settle_time_s=max(layout.settle_time_s for _, layout in layouts),
        settled=all(layout.settled for _, layout in layouts),
    )


def cell_camera(cell: CellConfig, sensor: str = "d435", resolution: tuple[int, int] | None = None) -> Camera:
    """The sensor preset's intrinsics at the cell's `world_from_camera`."""
    if cell.world_from_camera is None:
        raise InputError(f"cell {cell.name!r} has no camera.world_from_camera")
    return camera_intrinsics(sensor, resolution).with_extrinsics(cell.world_from_camera)
