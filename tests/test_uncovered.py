"""Surfaces the segmenter missed become obstacles (`measure.uncovered`, `planning.plan.build_world`): an empty bin
under D435 noise leaves nothing, a part whose mask is dropped comes back as points on that part, points a fit
explains are not clutter, and a slab no instance covers turns the jaws away from it."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import trimesh

from normpos_grasp.cell import load_cell
from normpos_grasp.cell.config import CellConfig
from normpos_grasp.errors import InputError
from normpos_grasp.geometry import make_pose
from normpos_grasp.kinematics.arm import ArmModel
from normpos_grasp.loop import SyntheticBinSource
from normpos_grasp.measure.uncovered import UncoveredOptions, uncovered_points
from normpos_grasp.planning import PlanOptions, plan_pick
from normpos_grasp.planning.evaluate import EvaluationOptions
from normpos_grasp.planning.plan import build_world
from normpos_grasp.records.template import Template, TemplateFit
from normpos_grasp.sim.parts import default_part_library

CELL = Path(__file__).resolve().parents[1] / "examples" / "cells" / "ur5e_bin_parallel.yaml"
FLOOR_Z = 0.01  # inner bin floor of the example cell (bin centre x = 0.5, y = 0)


@pytest.fixture(scope="module")
def cell() -> CellConfig:
    return load_cell(CELL)


@pytest.mark.parametrize("seed", [9000, 9003])
def test_an_empty_bin_under_d435_noise_leaves_no_point(cell: CellConfig, seed: int) -> None:
    frame = SyntheticBinSource(cell, count=0, seed=seed, validate_physics=False).capture()
    assert len(uncovered_points(frame, [], cell.bins)) == 0
    # two bins, one seen from the side: its far wall, seen at a slant, must not lift the floor beside it (heights are
    # averaged over the bin's own uncovered pixels: with the wall's in the window 50-60 floor points passed the band)
    two = load_cell(CELL.parent / "ur5e_two_bins.yaml")
    frame = SyntheticBinSource(two, count=0, seed=seed, validate_physics=False).capture()
    assert len(uncovered_points(frame, [], two.bins)) == 0
    # the walls and the floor are what a zero band would report: the bands are what keeps them out
    bare = uncovered_points(frame, [], cell.bins, UncoveredOptions(floor_band_m=-0.0, wall_band_m=0.0, smooth_px=1))
    assert len(bare) > 1000


def test_a_part_whose_mask_is_dropped_comes_back_on_that_part(cell: CellConfig) -> None:
    library = default_part_library()
    source = SyntheticBinSource(cell, count=6, seed=9101, validate_physics=False, library=library)
    frame = source.capture()
    instances = source.ground_truth_segmenter().segment(frame)
    assert len(uncovered_points(frame, [i.mask for i in instances], cell.bins)) == 0
    for k, missed in enumerate(instances):
        others = [i.mask for j, i in enumerate(instances) if j != k]
        pts = uncovered_points(frame, others, cell.bins)
        visible = int(missed.mask[::2, ::2].sum())
        assert len(pts) >= 0.4 * visible, (missed.label, len(pts), visible)
        # all of them come from that part's pixels: covering its mask (grown by 2 px: smoothing and stride) again
        # leaves nothing
        grown = cv2.dilate(missed.mask.view(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
        assert len(uncovered_points(frame, [*others, grown], cell.bins)) == 0, missed.label


def _cube_fit(x: float, y: float) -> TemplateFit:
    cube = Template("cube", "cube", trimesh.creation.box((0.04, 0.04, 0.04)), shape="box")
    pose = make_pose(None, [x, y, FLOOR_Z + 0.02])
    return TemplateFit(cube, pose, 1.0, 0.0, 1.0, 1.0, 0.0, True, instance_id=1)


def _slab(x0: float, x1: float, y0: float, y1: float, z: float, step: float = 0.003) -> np.ndarray:
    xs, ys = np.meshgrid(np.arange(x0, x1, step), np.arange(y0, y1, step))
    return np.column_stack([xs.ravel(), ys.ravel(), np.full(xs.size, z)])


def test_points_a_fit_explains_are_not_clutter_and_the_others_are(cell: CellConfig) -> None:
    fit = _cube_fit(0.5, 0.0)
    arm = ArmModel.from_name(cell.robot_model, cell.world_from_base)
    on_cube = _slab(0.481, 0.519, -0.019, 0.019, FLOOR_Z + 0.04)  # the cube's own top face, missed by its mask
    far = _slab(0.58, 0.62, 0.05, 0.09, FLOOR_Z + 0.02)  # something 2 cm high nobody segmented
    world, targets, _ = build_world(cell, [fit], [], arm, PlanOptions(), np.concatenate([on_cube, far]))
    voxels = [e for name, e in world.elements.items() if name.startswith("clutter/uncovered")]
    assert voxels and len(targets) == 1
    lo = np.min([e.lo for e in voxels], axis=0)
    hi = np.max([e.hi for e in voxels], axis=0)
    assert lo[0] >= 0.57 and hi[0] <= 0.63 and lo[1] >= 0.04 and hi[1] <= 0.10  # the far slab only
    world, _, _ = build_world(cell, [fit], [], arm, PlanOptions(), on_cube)
    assert not any(name.startswith("clutter/") for name in world.elements)


def test_a_slab_nobody_segmented_turns_the_jaws_away(cell: CellConfig) -> None:
    fit = _cube_fit(0.5, 0.0)
    options = PlanOptions(evaluation=EvaluationOptions(max_feasible=0, max_feasible_per_target=0))
    free = plan_pick([fit], [], cell, options)
    across_y = [e for e in free.evaluations if e.feasible and abs(e.candidate.world_from_tcp[1, 0]) > 0.9]
    assert across_y, "without the slab some top-down grasp closes along y"
    # a plate under both sides of the cube along y, 1 cm off its faces, where those jaws reach down: only the mask
    # missed it (clutter is whole 1 cm grid cells: nearer than that, it would touch the cube and block every lift)
    y0 = 0.03
    slab = np.concatenate([_slab(0.47, 0.53, y0, 0.05, FLOOR_Z + 0.01), _slab(0.47, 0.53, -0.05, -y0, FLOOR_Z + 0.01)])
    plan = plan_pick([fit], [], cell, options, uncovered=slab)
    assert plan.status == "ok"
    for e in plan.evaluations:
        if e.feasible:
            assert abs(e.candidate.world_from_tcp[1, 0]) < 0.9, e.candidate.grasp_id


def test_bad_options_are_refused() -> None:
    with pytest.raises(InputError):
        UncoveredOptions(smooth_px=4)
    with pytest.raises(InputError):
        UncoveredOptions(floor_band_m=-0.001)


def test_a_bin_holding_only_what_the_segmenter_missed_is_not_called_empty(cell: CellConfig) -> None:
    from normpos_grasp.planning.plan import stop_line

    unseen = _slab(0.45, 0.5, -0.03, 0.02, FLOOR_Z + 0.02)  # a surface 2 cm high that no instance covers
    plan = plan_pick([], [], cell, uncovered=unseen)
    assert plan.status == "no_feasible_grasp" and plan.uncovered_voxels > 0
    assert plan.to_json()["uncovered_voxels"] == plan.uncovered_voxels
    assert "surfaces no instance covers remain" in stop_line(plan)
    bare = plan_pick([], [], cell)
    assert bare.uncovered_voxels == 0 and "uncovered_voxels" not in bare.to_json()
    assert "nothing perceived as a known part" in stop_line(bare)
    # several bins: the bin holding only such a surface is not among the empty ones; a cube in the other is picked
    two = load_cell(CELL.parent / "ur5e_two_bins.yaml")
    cube = _cube_fit(0.5, -0.175)
    left_only = _slab(0.45, 0.5, 0.15, 0.2, FLOOR_Z + 0.02)
    plan = plan_pick([cube], [], two, uncovered=left_only)
    assert plan.status == "ok" and plan.bin == "right" and plan.bins_empty == ()
    assert plan_pick([cube], [], two).bins_empty == ("left",)
