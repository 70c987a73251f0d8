"""Hand-built scenes with known answers: wall side, out of reach, lid on top, suction vs parallel, symmetric parts;
plan validity checked by an independent world built from the ground truth (trimesh + the kinematics' own FK)."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import trimesh

from normpos_grasp.cell import cell_from_dict, load_cell
from normpos_grasp.cell.config import CellConfig
from normpos_grasp.geometry import make_pose, rotation_from_rotvec
from normpos_grasp.kinematics import Gripper, Robot
from normpos_grasp.planning import PlanOptions, plan_pick
from normpos_grasp.planning.evaluate import EvaluationOptions
from normpos_grasp.records.normpos import NormPosition, OrientedBox
from normpos_grasp.records.template import GraspAnnotation, Symmetry, Template, TemplateFit
from normpos_grasp.report.scene3d import capsule_mesh

EXAMPLES = Path(__file__).resolve().parents[1] / "examples" / "cells"
FLOOR_Z = 0.01  # inner bin floor of the example UR5e cell (bin centre x = 0.5, walls at x = 0.3 / 0.7)


@pytest.fixture(scope="module")
def bin_cell() -> CellConfig:
    return load_cell(EXAMPLES / "ur5e_bin_parallel.yaml")


def _fit(template: Template, pose: np.ndarray, iid: int) -> TemplateFit:
    return TemplateFit(template, pose, 1.0, 0.0, 1.0, 1.0, 0.0, True, instance_id=iid)


def _box(name: str, extents: tuple[float, float, float], shape: str = "box") -> Template:
    return Template(name, name, trimesh.creation.box(extents), shape=shape)


def _on_floor(template: Template, x: float, y: float, yaw: float = 0.0, z0: float = FLOOR_Z) -> np.ndarray:
    return make_pose(rotation_from_rotvec([0.0, 0.0, yaw]), [x, y, z0 + template.extents_m[2] / 2.0])


def _all_options(**kw: object) -> PlanOptions:
    """Evaluate every candidate (no early stop) so that verdicts can be inspected."""
    return PlanOptions(evaluation=EvaluationOptions(max_feasible=0, max_feasible_per_target=0, **kw))  # type: ignore[arg-type]


def test_part_against_wall_only_open_side(bin_cell: CellConfig) -> None:
    part = _box("tall", (0.03, 0.03, 0.17))  # taller than the wall, so the palm clears the rim
    # touching the +x wall (inner face at x = 0.7)
    pose = _on_floor(part, 0.7 - 0.015 - 0.001, 0.0)
    plan = plan_pick([_fit(part, pose, 1)], [], bin_cell, _all_options(max_approach_up=0.3))
    assert plan.status == "ok"
    feasible = [e for e in plan.evaluations if e.feasible]
    assert feasible
    for e in feasible:
        a = e.candidate.world_from_tcp[:3, 2]
        x = e.candidate.world_from_tcp[:3, 0]
        assert a[0] > -0.5, "approached from the wall side"
        if a[2] < -0.9:  # top-down: jaws must not close across the wall
            assert abs(x[0]) < 0.5
    # the top-down grasps whose jaws close towards the wall are rejected for a collision
    across = [
        e
        for e in plan.evaluations
        if e.candidate.world_from_tcp[2, 2] < -0.9 and abs(e.candidate.world_from_tcp[0, 0]) > 0.9
    ]
    assert across and all(not e.feasible and e.reason.startswith("collision") for e in across)


def test_part_out_of_reach_reason_ik(bin_cell: CellConfig) -> None:
    part = _box("box", (0.06, 0.04, 0.03))
    far = make_pose(None, [1.6, 0.0, 0.015])
    cell = replace(
        bin_cell, motion=replace(bin_cell.motion, workspace_min=np.full(3, -5.0), workspace_max=np.full(3, 5.0))
    )
    plan = plan_pick([_fit(part, far, 1)], [], cell, _all_options())
    assert plan.status == "no_feasible_grasp"
    assert plan.chosen is None and plan.trajectory is None and not plan.waypoints
    reachable_geometry = {k: v for k, v in plan.counts.items() if k not in ("stroke", "approach_angle")}
    assert set(reachable_geometry) == {"ik"}
    doc = plan.to_json()
    assert doc["status"] == "no_feasible_grasp" and doc["candidates"]["rejected_by_reason"]["ik"] > 0


def test_lid_on_top_reason_collision(bin_cell: CellConfig) -> None:
    part = _box("box", (0.06, 0.04, 0.03))
    pose = _on_floor(part, 0.5, 0.0)
    # control: the bare part is pickable
    assert plan_pick([_fit(part, pose, 1)], [], bin_cell).status == "ok"
    # a lid (measured points no template explains) lying on the part
    xs, ys = np.meshgrid(np.linspace(0.43, 0.57, 30), np.linspace(-0.07, 0.07, 30))
    lid_pts = np.column_stack([xs.ravel(), ys.ravel(), np.full(xs.size, FLOOR_Z + 0.033)])
    lid = NormPosition(
        "lid",
        0.9,
        np.zeros((1, 1), bool),
        lid_pts,
        np.tile([0, 0, 1.0], (len(lid_pts), 1)),
        np.zeros((len(lid_pts), 2), np.int64),
        "world",
        np.array([0.5, 0, 1.0]),
        2,
        lid_pts.mean(0),
        lid_pts.min(0),
        lid_pts.max(0),
        OrientedBox(lid_pts.mean(0), np.eye(3), np.array([0.14, 0.14, 0.002])),
    )
    plan = plan_pick([_fit(part, pose, 1)], [lid], bin_cell, _all_options())
    assert plan.status == "no_feasible_grasp"
    after_ik = {k: v for k, v in plan.counts.items() if k not in ("ik", "joint_limits", "stroke", "approach_angle")}
    assert after_ik and all(k.startswith("collision") for k in after_ik)
    assert after_ik.get("collision_clutter", 0) > 0


def _plate_scene() -> tuple[Template, np.ndarray]:
    plate = _box("plate", (0.12, 0.10, 0.006), shape="plate")
    return plate, _on_floor(plate, 0.5, 0.0, yaw=0.3)


def test_suction_vs_parallel_on_a_plate(bin_cell: CellConfig) -> None:
    plate, pose = _plate_scene()
    parallel = plan_pick([_fit(plate, pose, 1)], [], bin_cell, _all_options())
    # a flat plate on the floor: edge pinches put the lower jaw into the floor, across-plate openings exceed stroke
    assert parallel.status == "no_feasible_grasp"
    assert all(e.candidate.scheme == "parallel" for e in parallel.evaluations)
    suction_cell = replace(bin_cell, tool=_suction_tool())
    suction = plan_pick([_fit(plate, pose, 1)], [], suction_cell)
    assert suction.status == "ok" and suction.chosen is not None
    assert suction.chosen.candidate.scheme == "suction"
    assert suction.chosen.candidate.world_from_tcp[2, 2] < -0.99  # straight down onto the top face


def _suction_tool():  # type: ignore[no-untyped-def]
    from normpos_grasp.collision import tool_from_gripper

    return tool_from_gripper(Gripper.load("suction"))


def _table_cell(fixtures: list[dict] | None = None) -> CellConfig:
    return cell_from_dict(
        {
            "robot": {"model": "ur5e", "world_from_base": {"rpy_deg": [0, 0, 180]}},
            "gripper": {"model": "2f85"},
            "table": {"pose": {"xyz": [0.3, 0, -0.025]}, "size": [1.2, 1.2, 0.05]},
            "fixtures": fixtures or [],
            "place": [{"world_from_tcp": {"xyz": [0.0, -0.45, 0.0], "rpy_deg": [180, 0, 0]}}],
        }
    )


def test_symmetric_part_free_axis_rotations() -> None:
    """An annotated side grasp with a free axis: rotations from the wall side are rejected, the open ones survive."""
    side = make_pose(np.array([[0, 0, 1.0], [1.0, 0, 0], [0, 1.0, 0]]), [0.0, 0.0, 0.0])  # approach +x, close along y
    cyl = Template(
        "cyl",
        "cyl",
        trimesh.creation.cylinder(0.02, 0.12),
        shape="cylinder",
        symmetry=Symmetry(continuous=((np.array([0.0, 0.0, 1.0]), np.zeros(3)),)),
        grasps=(GraspAnnotation("side", "parallel", side, opening_m=0.06, free_axis=np.array([0.0, 0.0, 1.0])),),
    )
    # a standing cylinder next to a wall on its -y side
    cell = _table_cell([{"name": "wall", "pose": {"xyz": [0.45, -0.05, 0.15]}, "size": [0.4, 0.02, 0.3]}])
    pose = make_pose(None, [0.45, -0.04 + 0.021, 0.06])
    plan = plan_pick([_fit(cyl, pose, 1)], [], cell, _all_options(max_approach_up=0.3))
    evs = plan.evaluations
    assert len(evs) == 8 and all(e.candidate.source == "annotated" for e in evs)
    feasible = [e for e in evs if e.feasible]
    from_wall = [e for e in evs if e.candidate.world_from_tcp[1, 2] > 0.7]  # gripper on the -y (wall) side
    assert feasible and from_wall
    assert all(not e.feasible and e.reason.startswith("collision") for e in from_wall)
    for e in feasible:
        assert e.candidate.world_from_tcp[1, 2] < 0.5
        # every rotation keeps the jaw axis horizontal and across the diameter
        assert abs(e.candidate.world_from_tcp[2, 0]) < 1e-9


def test_synthesised_cylinder_symmetry_same_verdict_under_rotation(bin_cell: CellConfig) -> None:
    """Rotating a symmetric part about its axis does not change whether it can be picked."""
    cyl = Template(
        "cyl",
        "cyl",
        trimesh.creation.cylinder(0.02, 0.07),
        shape="cylinder",
        symmetry=Symmetry(continuous=((np.array([0.0, 0.0, 1.0]), np.zeros(3)),)),
    )
    counts = []
    for yaw in (0.0, 0.7, 2.1):
        pose = _on_floor(cyl, 0.5, 0.05, yaw=yaw)
        plan = plan_pick([_fit(cyl, pose, 1)], [], bin_cell, _all_options())
        assert plan.status == "ok"
        counts.append(plan.n_feasible)
    assert min(counts) > 0


def _independent_collisions(
    plan,
    cell: CellConfig,
    gt: list[tuple[trimesh.Trimesh, np.ndarray]],  # type: ignore[no-untyped-def]
    target: int,
) -> list[str]:
    """Check the plan's trajectory with a world built here: trimesh's manager, Robot.link_poses, Gripper shapes
    (tool checked until 1 s before the grasp; the arm all along)."""
    robot = Robot.load(cell.robot_model)
    gripper = Gripper.load("2f85")
    env = trimesh.collision.CollisionManager()
    for box in cell.static_boxes:
        env.add_object(box.name, trimesh.creation.box(box.size), box.world_from_box)
    for k, (mesh, pose) in enumerate(gt):
        if k != target:
            env.add_object(f"gt{k}", mesh, pose)
    arm = trimesh.collision.CollisionManager()
    shapes = [s for s in robot.collision_geometry if s.link != "base"]
    for i, shape in enumerate(shapes):
        r, length = shape.size
        geom = capsule_mesh(r, length) if shape.kind == "capsule" else trimesh.creation.cylinder(r, length)
        arm.add_object(f"arm{i}", geom)
    opening = plan.chosen.candidate.opening_m
    tool = trimesh.collision.CollisionManager()
    tool_shapes = gripper.collision_shapes(opening)
    for i, shape in enumerate(tool_shapes):
        geom = (
            trimesh.creation.box(shape.size)
            if shape.kind == "box"
            else trimesh.creation.cylinder(shape.size[0], shape.size[1])
        )
        tool.add_object(f"tool{i}", geom)
    base = cell.world_from_base
    grasp_q = next(w.q for w in plan.waypoints if w.name == "grasp")
    t_grasp = plan.trajectory.t[int(np.argmin(np.abs(plan.trajectory.q - grasp_q).sum(axis=1)))]
    problems = []
    for t, q in zip(plan.trajectory.t[::2], plan.trajectory.q[::2], strict=True):
        links = robot.link_poses(q)
        for i, shape in enumerate(shapes):
            arm.set_transform(f"arm{i}", base @ links[shape.link] @ shape.link_from_shape)
        if env.in_collision_other(arm):
            problems.append(f"t={t:.2f} arm")
        if t < t_grasp - 1.0:
            world_from_tcp = base @ links["flange"] @ gripper.flange_from_tcp
            for i, shape in enumerate(tool_shapes):
                tool.set_transform(f"tool{i}", world_from_tcp @ shape.link_from_shape)
            if env.in_collision_other(tool):
                problems.append(f"t={t:.2f} tool")
    return problems


def test_plan_valid_against_independent_ground_truth(bin_cell: CellConfig, tmp_path: Path) -> None:
    parts = [
        _box("box", (0.06, 0.04, 0.03)),
        _box("cube", (0.04, 0.04, 0.04)),
        Template("cyl", "cyl", trimesh.creation.cylinder(0.02, 0.07), shape="cylinder"),
    ]
    gt = []
    for k, (x, y, yaw) in enumerate([(0.42, -0.08, 0.3), (0.55, 0.06, 1.0), (0.6, -0.07, 0.0), (0.4, 0.08, 2.0)]):
        t = parts[k % len(parts)]
        gt.append((t, _on_floor(t, x, y, yaw)))
    fits = [_fit(t, p, k + 1) for k, (t, p) in enumerate(gt)]
    plan = plan_pick(fits, [], bin_cell)
    assert plan.status == "ok" and plan.chosen is not None and plan.trajectory is not None
    names = [w.name for w in plan.waypoints]
    assert names == ["home", "entry", "pre_grasp", "grasp", "lift", "retreat", "pre_place", "place", "post_place"]
    robot = Robot.load("ur5e")
    tool = Gripper.load("2f85")
    for w in plan.waypoints:  # FK (pinocchio, independent of the planner's DH code) matches the TCP pose
        fk = bin_cell.world_from_base @ robot.fk(w.q) @ tool.flange_from_tcp
        assert np.abs(fk[:3, 3] - w.world_from_tcp[:3, 3]).max() < 1e-4
        assert np.abs(fk[:3, :3] - w.world_from_tcp[:3, :3]).max() < 1e-6
        assert robot.within_limits(w.q)
    grasp_wp = plan.waypoints[3]
    np.testing.assert_allclose(grasp_wp.world_from_tcp, plan.chosen.candidate.world_from_tcp, atol=1e-7)
    # velocity caps on the time-stamped samples
    traj = plan.trajectory
    vel = np.abs(np.diff(traj.q, axis=0)) / np.diff(traj.t)[:, None]
    assert np.all(vel <= bin_cell.motion.joint_velocity * 1.02)
    # independent collision check against the ground truth
    target = plan.chosen.candidate.target
    gt_meshes = [(t.mesh, p) for t, p in gt]
    assert _independent_collisions(plan, bin_cell, gt_meshes, target) == []
    # the checker does see obstacles: one the planner never knew about, where the wrist passes, is reported
    entry = next(w for w in plan.waypoints if w.name == "entry").world_from_tcp
    hidden = (trimesh.creation.box((0.1, 0.1, 0.1)), make_pose(None, entry[:3, 3] + [0.0, 0.0, 0.2]))
    assert _independent_collisions(plan, bin_cell, [*gt_meshes, hidden], target) != []
    # plan.json is self-contained and round-trips through json
    out = tmp_path / "plan.json"
    plan.save(out)
    doc = json.loads(out.read_text())
    assert doc["status"] == "ok" and doc["robot"] == "ur5e"
    for key in (
        "world_from_base",
        "tool",
        "target",
        "grasp",
        "joint_waypoints",
        "trajectory",
        "candidates",
        "timing_ms",
    ):
        assert key in doc
    assert doc["tool"]["type"] == "parallel" and len(doc["tool"]["collision"]) >= 3
    assert doc["grasp"]["opening_m"] <= doc["tool"]["stroke_m"]
    assert doc["candidates"]["feasible"] >= 1 and doc["candidates"]["evaluated"] <= doc["candidates"]["total"]
    assert len(doc["trajectory"]["samples"]) == len(traj.t)


def test_conveyor_suction_cell_plans(tmp_path: Path) -> None:
    cell = load_cell(EXAMPLES / "ur10e_conveyor_suction.yaml")
    box = _box("box", (0.10, 0.08, 0.05))
    pose = make_pose(rotation_from_rotvec([0, 0, 0.4]), [0.8, 0.1, 0.75 + 0.025])
    plan = plan_pick([_fit(box, pose, 1)], [], cell)
    assert plan.status == "ok" and plan.chosen is not None
    assert plan.chosen.candidate.scheme == "suction"
    assert plan.place in ("pallet_a", "pallet_b")


def test_unmatched_object_picked_as_primitive(bin_cell: CellConfig) -> None:
    rng = np.random.default_rng(0)
    pts = rng.uniform([-0.03, -0.02, 0.0], [0.03, 0.02, 0.0], (400, 3)) + [0.5, 0.0, FLOOR_Z + 0.03]
    obb = OrientedBox(np.array([0.5, 0.0, FLOOR_Z + 0.015]), np.eye(3), np.array([0.06, 0.04, 0.03]))
    npos = NormPosition(
        "",
        0.9,
        np.zeros((1, 1), bool),
        pts,
        np.tile([0, 0, 1.0], (400, 1)),
        np.zeros((400, 2), np.int64),
        "world",
        np.array([0.5, 0, 1.0]),
        1,
        pts.mean(0),
        pts.min(0),
        pts.max(0),
        obb,
    )
    assert plan_pick([], [npos], bin_cell).status == "no_feasible_grasp"  # clutter only
    plan = plan_pick([], [npos], bin_cell, PlanOptions(pick_unmatched=True))
    assert plan.status == "ok" and plan.chosen is not None
    assert plan.chosen.candidate.template.startswith("primitive_")


def test_camera_frame_fit_is_rejected_with_a_clear_error(bin_cell: CellConfig) -> None:
    from normpos_grasp.errors import PlanningError

    part = _box("box", (0.06, 0.04, 0.03))
    fit = replace(_fit(part, _on_floor(part, 0.5, 0.0), 1), frame="camera")
    with pytest.raises(PlanningError, match="world_from_camera"):
        plan_pick([fit], [], bin_cell)


def test_minimal_dict_cell_plans() -> None:
    cell = _table_cell()
    part = _box("box", (0.06, 0.04, 0.03))
    plan = plan_pick([_fit(part, make_pose(None, [0.45, 0.1, 0.015]), 1)], [], cell)
    assert plan.status == "ok"


def _leaning_bar(rolled: bool = False) -> tuple[Template, np.ndarray, Template, np.ndarray]:
    """A 100 x 25 x 25 mm bar, nothing above it. Pitched (default): 22 degrees about y, its low end on the floor,
    its underside 1 mm above the edge of a 40 x 40 x 30 mm block. Rolled: lying along x, rolled 22 degrees about
    its long axis, one edge on the floor, its underside 1 mm above the edge of an 8 mm plate-like block."""
    tilt = np.deg2rad(22.0)
    if rolled:
        bar, block = _box("bar", (0.1, 0.025, 0.025)), _box("block", (0.12, 0.04, 0.008))
        c, s = np.cos(tilt), np.sin(tilt)
        bar_pose = make_pose(rotation_from_rotvec([tilt, 0.0, 0.0]), [0.5, -0.02, FLOOR_Z + 0.0125 * (c + s)])
        edge = 0.009 / np.tan(tilt) - 0.0125 * (c - s)  # where the rising underside is 9 mm above the floor
        return bar, bar_pose, block, make_pose(None, [0.5, -0.02 + edge + 0.02, FLOOR_Z + 0.004])
    bar, block = _box("bar", (0.1, 0.025, 0.025)), _box("block", (0.04, 0.04, 0.03))
    cz = FLOOR_Z + 0.05 * np.sin(tilt) + 0.0125 * np.cos(tilt)
    bar_pose = make_pose(rotation_from_rotvec([0.0, -tilt, 0.0]), [0.48, 0.0, cz])
    s_edge = (FLOOR_Z + 0.031 - cz + 0.0125 * np.cos(tilt)) / np.sin(tilt)  # along the bar, where it meets z = 41 mm
    block_pose = make_pose(None, [0.48 + s_edge * np.cos(tilt) + 0.02, 0.0, FLOOR_Z + 0.015])
    return bar, bar_pose, block, block_pose


def test_vertical_prism_grasps_only_for_tilted_prisms() -> None:
    from normpos_grasp.grasp.candidates import vertical_prism_grasps
    from normpos_grasp.grasp.synthesis import SynthesisOptions

    bar, bar_pose, _, _ = _leaning_bar()
    opts = SynthesisOptions(finger_tip_m=0.02)
    grasps = vertical_prism_grasps(bar, bar_pose, opts)
    assert grasps
    long_axis = bar_pose[:3, 0]
    for _, pose, opening, _ in grasps:
        np.testing.assert_allclose(pose[:3, 2], [0.0, 0.0, -1.0], atol=1e-9)  # straight down
        assert abs(pose[:3, 0] @ long_axis) < 1e-9 and abs(pose[2, 0]) < 1e-9  # closes horizontally, across
        # the bar is 25 mm wide across; pitched about y, its cut stays 25 mm wide
        assert opening == pytest.approx(0.025 + 2 * opts.clearance_m, abs=1e-6)
        top = (pose[:3, 3] - bar_pose[:3, 3]) @ long_axis  # along the bar, within its length
        assert abs(top) <= 0.05
    # lying flat, standing up, or a cube: no such grasps (the face grasps already come from above, or none apply)
    assert vertical_prism_grasps(bar, _on_floor(bar, 0.5, 0.0, 0.7), opts) == []
    standing = make_pose(rotation_from_rotvec([0.0, np.pi / 2, 0.0]), [0.5, 0.0, 0.07])
    assert vertical_prism_grasps(bar, standing, opts) == []
    cube = _box("cube", (0.04, 0.04, 0.04))
    assert vertical_prism_grasps(cube, bar_pose, opts) == []


def test_rolled_bar_vertical_pinch_refused_by_the_grip_mechanics(bin_cell: CellConfig) -> None:
    # rolled 22 degrees about its long axis, a straight-down pinch closes on two edges: the squeeze turns the bar
    # in the jaws (MuJoCo: 12 degrees, a slip), so the mechanics refuse it and say why
    bar, bar_pose, block, block_pose = _leaning_bar(rolled=True)
    plan = plan_pick([_fit(bar, bar_pose, 1), _fit(block, block_pose, 2)], [], bin_cell, _all_options())
    vertical = [
        e for e in plan.evaluations if e.candidate.target == 0 and e.candidate.grasp_id.startswith("vert_prism")
    ]
    assert vertical and all(not e.feasible for e in vertical)
    assert {e.reason for e in vertical} <= {"friction_cone", "collision_cell", "collision_object"}
    assert any(e.reason == "friction_cone" for e in vertical)


def test_leaning_bar_gets_a_vertical_grasp(bin_cell: CellConfig, rolled: bool = False) -> None:
    bar, bar_pose, block, block_pose = _leaning_bar(rolled)
    fits = [_fit(bar, bar_pose, 1), _fit(block, block_pose, 2)]
    plan = plan_pick(fits, [], bin_cell, _all_options())
    vertical = [
        e
        for e in plan.evaluations
        if e.feasible and e.candidate.target == 0 and e.candidate.world_from_tcp[2, 2] < -0.99999
    ]
    assert vertical, f"no feasible straight-down grasp of the bar: {plan.counts}"
    plan = plan_pick(fits, [], bin_cell)
    assert plan.status == "ok" and plan.chosen is not None
    gt = [(bar.mesh, bar_pose), (block.mesh, block_pose)]
    assert _independent_collisions(plan, bin_cell, gt, plan.chosen.candidate.target) == []


def test_lone_unexplained_points_are_not_clutter(bin_cell: CellConfig) -> None:
    part = _box("box", (0.06, 0.04, 0.03))
    pose = _on_floor(part, 0.5, 0.0)
    top = FLOOR_Z + 0.03

    def measured(extra: np.ndarray) -> NormPosition:
        # the part's top face as measured, plus `extra` points no fit explains
        xs, ys = np.meshgrid(np.linspace(0.475, 0.525, 12), np.linspace(-0.015, 0.015, 8))
        pts = np.vstack([np.column_stack([xs.ravel(), ys.ravel(), np.full(xs.size, top)]), extra])
        return NormPosition(
            "box",
            0.9,
            np.zeros((1, 1), bool),
            pts,
            np.tile([0, 0, 1.0], (len(pts), 1)),
            np.zeros((len(pts), 2), np.int64),
            "world",
            np.array([0.5, 0, 1.0]),
            1,
            pts.mean(0),
            pts.min(0),
            pts.max(0),
            OrientedBox(pts.mean(0), np.eye(3), np.ptp(pts, axis=0)),
        )

    # one flying pixel 4 cm above the part, where the jaws pass: a sensor outlier, not an obstacle
    stray = np.array([[0.5, 0.0, top + 0.04]])
    assert plan_pick([_fit(part, pose, 1)], [measured(stray)], bin_cell).status == "ok"
    # a dense patch there is something real and blocks every grasp from above
    xs, ys = np.meshgrid(np.linspace(0.47, 0.53, 10), np.linspace(-0.03, 0.03, 10))
    patch = np.column_stack([xs.ravel(), ys.ravel(), np.full(xs.size, top + 0.04)])
    plan = plan_pick([_fit(part, pose, 1)], [measured(patch)], bin_cell, _all_options())
    assert plan.status == "no_feasible_grasp" and plan.counts.get("collision_clutter", 0) > 0


def _points(label: str, iid: int, pts: np.ndarray) -> NormPosition:
    return NormPosition(
        label,
        0.9,
        np.zeros((1, 1), bool),
        pts,
        np.tile([0, 0, 1.0], (len(pts), 1)),
        np.zeros((len(pts), 2), np.int64),
        "world",
        np.array([0.5, 0, 1.0]),
        iid,
        pts.mean(0),
        pts.min(0),
        pts.max(0),
        OrientedBox(pts.mean(0), np.eye(3), np.ptp(pts, axis=0)),
    )


def test_points_inside_a_neighbours_fit_are_not_clutter(bin_cell: CellConfig) -> None:
    from normpos_grasp.planning.plan import build_world

    a, b = _box("a", (0.06, 0.04, 0.03)), _box("b", (0.06, 0.04, 0.03))
    pose_a, pose_b = _on_floor(a, 0.46, 0.0), _on_floor(b, 0.53, 0.0)
    # a's mask bled over b: a dense patch of b's top face is labelled a; and a real obstacle 3 cm above b
    xs, ys = np.meshgrid(np.linspace(0.51, 0.55, 8), np.linspace(-0.015, 0.015, 6))
    bled = np.column_stack([xs.ravel(), ys.ravel(), np.full(xs.size, FLOOR_Z + 0.03)])
    above = bled + [0.0, 0.0, 0.03]
    fits = [_fit(a, pose_a, 1), _fit(b, pose_b, 2)]
    for extra, clutter in ((bled, False), (above, True)):
        world, _, _ = build_world(bin_cell, fits, [_points("a", 1, extra)], None)  # type: ignore[arg-type]
        assert any(name.startswith("clutter") for name in world.elements) is clutter


def test_stop_line_names_the_parts_and_the_closest_call(bin_cell: CellConfig) -> None:
    from normpos_grasp.planning.plan import rejections_by_target, stop_line

    part = _box("box", (0.06, 0.04, 0.03))
    far = make_pose(None, [1.6, 0.0, 0.015])
    cell = replace(
        bin_cell, motion=replace(bin_cell.motion, workspace_min=np.full(3, -5.0), workspace_max=np.full(3, 5.0))
    )
    plan = plan_pick([_fit(part, far, 1)], [], cell, _all_options())
    rows = rejections_by_target(plan)
    assert len(rows) == 1 and rows[0].template == "box"
    assert rows[0].best_reason == "ik" and sum(rows[0].counts.values()) == len(plan.evaluations)
    line = stop_line(plan)
    assert "\n" not in line and "1 part(s) left (box)" in line and "closest" in line and "ik" in line
    doc = rows[0].to_json()
    assert doc["best_rejected"]["reason"] == "ik" and np.asarray(doc["best_rejected"]["world_from_tcp"]).shape == (4, 4)


def test_push_motion_follows_the_planned_push(bin_cell: CellConfig) -> None:
    from normpos_grasp.kinematics.arm import ArmModel
    from normpos_grasp.planning.push import PushHand, plan_push, push_motion

    part = _box("box", (0.06, 0.04, 0.03))
    pose = _on_floor(part, 0.5, 0.0)
    fits = [_fit(part, pose, 1)]
    plan = plan_pick(fits, [], bin_cell)
    push = plan_push(plan, fits, [], bin_cell, PushHand(0.013, 0.027, 0.02), FLOOR_Z, 0.05)
    assert push is not None
    traj = push_motion(push, fits, [], bin_cell, np.asarray(bin_cell.home_q))
    assert np.allclose(traj.q[0], bin_cell.home_q) and np.all(np.diff(traj.t) > 0)
    arm = ArmModel.from_name(bin_cell.robot_model, bin_cell.world_from_base)
    tcp = (arm.fk(traj.q) @ bin_cell.tool.flange_from_tcp)[:, :3, 3]
    start, end = push.world_from_tcp[:3, 3], push.world_from_tcp[:3, 3] + push.push
    # the TCP passes the push's start and end, and ends straight above the end
    assert np.min(np.linalg.norm(tcp - start, axis=1)) < 2e-3
    assert np.min(np.linalg.norm(tcp - end, axis=1)) < 2e-3
    assert np.allclose(tcp[-1], end + [0.0, 0.0, 0.08], atol=1e-3)
