"""Best-first evaluation (mechanics judged last, only when reached): with the early stop it finds exactly the first
feasible grasps, in exact prior order and within the per-object cap, of a full evaluation of the same candidates."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import numpy as np
import pytest
import trimesh

from normpos_grasp.cell import load_cell
from normpos_grasp.geometry import make_pose, rotation_from_rotvec
from normpos_grasp.grasp.candidates import candidates_for_object
from normpos_grasp.grasp.quality import QualityOptions, judge
from normpos_grasp.kinematics.arm import ArmModel
from normpos_grasp.planning.evaluate import EvaluationOptions, evaluate_candidates
from normpos_grasp.planning.plan import build_world
from normpos_grasp.records.template import Template, TemplateFit

EXAMPLES = Path(__file__).resolve().parents[1] / "examples" / "cells"
FLOOR_Z = 0.01  # inner bin floor of the example UR5e cell (bin centre x = 0.5)


def _evaluate(options: EvaluationOptions) -> list[tuple[int, int]]:
    """(candidate index, object index) of the feasible grasps on a five-box bin, in exact prior order (ties by
    index), the prior recomputed here from the weights and the mechanics' predicted success."""
    cell = load_cell(EXAMPLES / "ur5e_bin_parallel.yaml")
    parts = [
        ((0.06, 0.04, 0.03), 0.45, -0.05, 0.3),
        ((0.10, 0.025, 0.025), 0.52, 0.02, 1.2),
        ((0.04, 0.04, 0.04), 0.47, 0.06, 0.0),
        ((0.08, 0.05, 0.008), 0.56, -0.06, 2.0),
        ((0.05, 0.03, 0.05), 0.41, 0.05, 0.7),
    ]
    fits = []
    for k, (size, x, y, yaw) in enumerate(parts):
        template = Template(f"box{k}", f"box{k}", trimesh.creation.box(size), shape="box")
        pose = make_pose(rotation_from_rotvec([0.0, 0.0, yaw]), [x, y, FLOOR_Z + size[2] / 2.0])
        fits.append(TemplateFit(template, pose, 1.0, 0.0, 1.0, 1.0, 0.0, True, instance_id=k + 1))
    arm = ArmModel.from_name(cell.robot_model, cell.world_from_base)
    world, targets, templates = build_world(cell, fits, [], arm)
    world.set_arm(arm)
    world.set_tool(cell.tool)
    world.update()
    candidates = [
        c
        for k, (t, tp) in enumerate(zip(targets, templates, strict=True))
        for c in candidates_for_object(k, tp, t.world_from_object, cell.tool.kind)
    ]
    limits = (cell.motion.workspace_min, cell.motion.workspace_max)
    home = np.asarray(cell.home_q, dtype=np.float64)
    result = evaluate_candidates(
        candidates, targets, world, arm, home, cell.entry_z, cell.lift_m, cell.entry_clearance_m, limits, options
    )
    mechanics = options.mechanics or QualityOptions()
    ranked = []
    for i, e in enumerate(result.evaluations):
        if not e.feasible:
            continue
        c, t = e.candidate, targets[e.candidate.target]
        success = judge(c.scheme, t.mesh, t.mass_kg, t.world_from_object, c.world_from_tcp, cell.tool, mechanics)
        prior = (
            options.w_height * t.height_m
            + options.w_quality * success.success * c.quality
            + options.w_approach * (-c.world_from_tcp[2, 2])
            + options.w_priority * c.priority
        )
        assert prior == e.prior  # the evaluation ranked it by the exact prior
        ranked.append((-prior, i, c.target))
    return [(i, target) for _, i, target in sorted(ranked)]


@pytest.mark.parametrize("grip_force_n", [100.0, 2.5])
def test_early_stop_finds_the_first_feasible_grasps_in_exact_prior_order(grip_force_n: float) -> None:
    # at 2.5 N the mechanics predict 0.5 or 0.8 for some grasps of these 0.1 kg boxes: their priors fall below
    # the bound they were taken at, so they go back in line
    mechanics = QualityOptions(grip_force_n=grip_force_n)
    quick_opts = EvaluationOptions(mechanics=mechanics)
    full = _evaluate(EvaluationOptions(max_feasible=0, max_feasible_per_target=0, mechanics=mechanics))
    quick = _evaluate(quick_opts)
    assert len(full) > quick_opts.max_feasible  # the early stop has something to leave out
    # the first feasible ones in the full evaluation's exact prior order, at most max_feasible_per_target per object
    expected: list[tuple[int, int]] = []
    per_object: Counter[int] = Counter()
    for i, target in full:
        if per_object[target] >= quick_opts.max_feasible_per_target:
            continue
        expected.append((i, target))
        per_object[target] += 1
        if len(expected) == quick_opts.max_feasible:
            break
    assert quick == expected
